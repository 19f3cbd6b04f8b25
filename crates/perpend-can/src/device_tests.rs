//! Behaviour tests of [`Device`]: one test per CiA 301 service and rule,
//! and property tests over arbitrary frame sequences.
#![allow(clippy::unwrap_used, clippy::panic)]

use super::*;
use crate::status;
use proptest::prelude::*;

const NODE: u8 = 0x10;

struct Bus {
    dev: Device,
    now: u64,
    out: Vec<Frame>,
}

impl Bus {
    fn new() -> Self {
        let mut b = Bus {
            dev: Device::new(NODE, &Defaults::nominal()),
            now: 0,
            out: Vec::new(),
        };
        b.poll();
        b
    }
    fn poll(&mut self) {
        let out = &mut self.out;
        self.dev.poll(self.now, &mut |f| out.push(f));
    }
    fn advance(&mut self, us: u64) {
        self.now += us;
        self.poll();
    }
    fn send(&mut self, f: Frame) -> Vec<Frame> {
        let mut v = Vec::new();
        self.dev.handle(&f, self.now, &mut |f| v.push(f));
        self.out.extend_from_slice(&v);
        v
    }
    fn take(&mut self) -> Vec<Frame> {
        core::mem::take(&mut self.out)
    }
    fn nmt(&mut self, cs: u8, node: u8) {
        self.send(Frame::new(0, &[cs, node]));
    }
    fn sync(&mut self) -> Vec<Frame> {
        self.send(Frame::new(0x80, &[]))
    }
    fn sdo(&mut self, req: [u8; 8]) -> Option<[u8; 8]> {
        let id = 0x600 + self.dev.node_id() as u16;
        let r = self.send(Frame::new(id, &req));
        assert!(r.len() <= 1);
        r.first().map(|f| {
            assert_eq!(f.id, 0x580 + self.dev.node_id() as u16);
            assert_eq!(f.len, 8);
            f.data
        })
    }
    /// Upload (expedited or segmented) -> bytes or abort code.
    fn upload(&mut self, index: u16, sub: u8) -> Result<Vec<u8>, u32> {
        let i = index.to_le_bytes();
        let r = self.sdo([0x40, i[0], i[1], sub, 0, 0, 0, 0]).unwrap();
        if r[0] == 0x80 {
            return Err(u32::from_le_bytes([r[4], r[5], r[6], r[7]]));
        }
        assert_eq!(&r[1..4], &[i[0], i[1], sub]);
        if r[0] & 0x02 != 0 {
            let n = 4 - ((r[0] >> 2) & 3) as usize;
            return Ok(r[4..4 + n].to_vec());
        }
        let size = u32::from_le_bytes([r[4], r[5], r[6], r[7]]) as usize;
        let mut v = Vec::new();
        let mut t = 0u8;
        loop {
            let r = self.sdo([0x60 | t, 0, 0, 0, 0, 0, 0, 0]).unwrap();
            if r[0] == 0x80 {
                return Err(u32::from_le_bytes([r[4], r[5], r[6], r[7]]));
            }
            let n = 7 - ((r[0] >> 1) & 7) as usize;
            v.extend_from_slice(&r[1..1 + n]);
            t ^= 0x10;
            if r[0] & 1 != 0 {
                break;
            }
        }
        assert_eq!(v.len(), size);
        Ok(v)
    }
    fn read32(&mut self, index: u16, sub: u8) -> u32 {
        let v = self.upload(index, sub).unwrap();
        let mut b = [0u8; 4];
        b[..v.len()].copy_from_slice(&v);
        u32::from_le_bytes(b)
    }
    /// Expedited download -> abort code or Ok.
    fn download(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<(), u32> {
        let i = index.to_le_bytes();
        let n = data.len().min(4);
        let mut req = [0x23 | (((4 - n) as u8) << 2), i[0], i[1], sub, 0, 0, 0, 0];
        req[4..4 + n].copy_from_slice(&data[..n]);
        match self.sdo(req) {
            Some(r) if r[0] == 0x60 => Ok(()),
            Some(r) if r[0] == 0x80 => Err(u32::from_le_bytes([r[4], r[5], r[6], r[7]])),
            Some(r) => panic!("bad response {r:02x?}"),
            None => Err(0),
        }
    }
    fn write_u32(&mut self, index: u16, sub: u8, v: u32) -> Result<(), u32> {
        self.download(index, sub, &v.to_le_bytes())
    }
    fn write_f32(&mut self, index: u16, sub: u8, v: f32) -> Result<(), u32> {
        self.download(index, sub, &v.to_le_bytes())
    }
    /// Completes a pending store/restore with `ok`; returns the response.
    fn finish(&mut self, ok: bool) -> Vec<Frame> {
        let mut v = Vec::new();
        self.dev.finish_request(ok, &mut |f| v.push(f)).unwrap();
        v
    }
}

fn sample() -> Measurement {
    Measurement {
        normal: [0.1, -0.2, -0.97],
        theta1_deg: 1.5,
        theta2_deg: -2.25,
        theta_deg: 2.7,
        pitch_deg: 0.5,
        yaw_deg: -0.75,
        distances_mm: [40.0, 41.0, 42.0, 43.0],
        status: 0x1111,
        rms_mm: 0.003,
    }
}

#[test]
fn boot_up_then_heartbeat_with_state_codes() {
    let mut b = Bus::new();
    assert_eq!(b.take(), vec![Frame::new(0x710, &[0])]);
    assert_eq!(b.dev.nmt_state(), NmtState::PreOperational);
    b.advance(999_000);
    assert!(b.take().is_empty());
    b.advance(1_000);
    assert_eq!(b.take(), vec![Frame::new(0x710, &[0x7F])]);
    b.nmt(0x01, NODE);
    b.advance(1_000_000);
    assert_eq!(b.take(), vec![Frame::new(0x710, &[0x05])]);
    b.nmt(0x02, 0);
    b.advance(1_000_000);
    assert_eq!(b.take(), vec![Frame::new(0x710, &[0x04])]);
    // heartbeat off: nothing after pre-op
    b.nmt(0x80, 0);
    b.download(0x1017, 0, &[0, 0]).unwrap();
    b.take();
    b.advance(5_000_000);
    assert!(b.take().is_empty());
    b.download(0x1017, 0, &[100, 0]).unwrap();
    b.advance(1); // the new period starts at this poll
    b.take();
    b.advance(99_999);
    assert!(b.take().is_empty());
    b.advance(1);
    assert_eq!(b.take(), vec![Frame::new(0x710, &[0x7F])]);
}

/// The boot-up is the node's first frame: an error raised while the node
/// initialises (after power-on or an NMT reset) is sent by the poll after
/// the one that sends the boot-up, so no transmit queue in CAN priority
/// order can put the EMCY (0x090) ahead of it (0x710). Seen on the virtual
/// board before the fix (peer test `test_one_emcy_per_error_with_thirteen_active`).
#[test]
fn no_emcy_before_the_boot_up() {
    for reset in [None, Some(0x81u8), Some(0x82)] {
        let mut b = Bus::new();
        b.take();
        if let Some(cs) = reset {
            b.nmt(cs, NODE);
            assert_eq!(b.dev.nmt_state(), NmtState::Initialising);
        } else {
            b.dev = Device::new(NODE, &Defaults::nominal());
        }
        assert!(b.dev.signal_emcy(0x2111, error_register::GENERIC, [0; 5]));
        b.advance(10);
        assert_eq!(b.take(), vec![Frame::new(0x710, &[0])], "{reset:?}");
        b.advance(1_000);
        let out = b.take();
        assert_eq!(out.len(), 1, "{reset:?}: {out:?}");
        assert_eq!((out[0].id, &out[0].data[..2]), (0x090, &[0x11, 0x21][..]));
    }
}

#[test]
fn nmt_commands_and_addressing() {
    let mut b = Bus::new();
    b.nmt(0x01, NODE + 1);
    assert_eq!(b.dev.nmt_state(), NmtState::PreOperational);
    b.nmt(0x01, 0);
    assert_eq!(b.dev.nmt_state(), NmtState::Operational);
    b.nmt(0x80, NODE);
    assert_eq!(b.dev.nmt_state(), NmtState::PreOperational);
    b.nmt(0x02, NODE);
    assert_eq!(b.dev.nmt_state(), NmtState::Stopped);
    // SDO silent in stopped
    assert_eq!(b.sdo([0x40, 0x00, 0x10, 0, 0, 0, 0, 0]), None);
    // unknown command and short frame ignored
    b.nmt(0x55, NODE);
    b.send(Frame::new(0, &[0x01]));
    assert_eq!(b.dev.nmt_state(), NmtState::Stopped);
    b.nmt(0x01, NODE);
    assert_eq!(b.dev.nmt_state(), NmtState::Operational);
    assert!(b.dev.take_events().contains(Events::STATE_CHANGED));
}

#[test]
fn frames_before_boot_up_are_ignored() {
    let mut d = Device::new(NODE, &Defaults::nominal());
    let mut out = Vec::new();
    d.handle(&Frame::new(0, &[1, 0]), 0, &mut |f| out.push(f));
    d.handle(
        &Frame::new(0x610, &[0x40, 0, 0x10, 0, 0, 0, 0, 0]),
        0,
        &mut |f| out.push(f),
    );
    assert!(out.is_empty());
    assert_eq!(d.nmt_state(), NmtState::Initialising);
}

#[test]
fn identity_device_type_and_strings() {
    let mut b = Bus::new();
    let d = Defaults::nominal();
    assert_eq!(b.read32(0x1000, 0), d.device_type);
    assert_eq!(b.read32(0x1018, 0), 4);
    assert_eq!(b.read32(0x1018, 2), d.identity.product_code);
    assert_eq!(b.read32(0x1018, 3), d.identity.revision);
    assert_eq!(b.upload(0x1008, 0).unwrap(), d.device_name.as_bytes());
    assert_eq!(b.upload(0x100A, 0).unwrap(), d.software_version.as_bytes());
    assert_eq!(b.read32(0x1014, 0), 0x80 + NODE as u32);
    assert_eq!(b.read32(0x1200, 1), 0x600 + NODE as u32);
    assert_eq!(b.read32(0x1010, 1), 1);
    assert_eq!(b.dev.read_str(0x1009, 0), Some(d.hardware_version));
}

#[test]
fn sdo_abort_codes() {
    let mut b = Bus::new();
    assert_eq!(b.upload(0x3000, 0), Err(0x0602_0000));
    assert_eq!(b.upload(0x1018, 9), Err(0x0609_0011));
    assert_eq!(b.write_u32(0x1000, 0, 5), Err(0x0601_0002));
    assert_eq!(b.write_u32(0x2001, 1, 5), Err(0x0601_0002));
    assert_eq!(b.write_u32(0x1017, 0, 5), Err(0x0607_0012)); // U16 written as 4 bytes
    assert_eq!(b.write_u32(0x1800, 2, 0), Err(0x0607_0012));
    assert_eq!(b.download(0x2300, 1, &[1, 2]), Err(0x0607_0013)); // U32 as 2 bytes
    assert_eq!(b.download(0x2101, 1, &[0, 0, 0x80]), Err(0x0607_0013));
    assert_eq!(b.download(0x1800, 2, &[245]), Err(0x0609_0030));
    assert_eq!(b.write_u32(0x2300, 1, 200_000), Err(0x0609_0031));
    assert_eq!(b.write_u32(0x2300, 1, 50), Err(0x0609_0032));
    assert_eq!(b.download(0x2300, 2, &[3, 0]), Err(0x0609_0030));
    assert_eq!(b.download(0x2400, 2, &[0x2C, 0x01]), Err(0x0609_0030)); // 300 kbit/s
    assert_eq!(b.write_u32(0x1010, 1, 0x1234), Err(0x0800_0020));
    assert_eq!(b.write_f32(0x2101, 1, 1.0), Err(0x0800_0021)); // locked
    assert_eq!(b.write_u32(0x2010, 0, 0x1234), Err(0x0609_0030));
    b.nmt(0x01, 0);
    assert_eq!(b.write_u32(0x2300, 1, 500), Err(0x0800_0022));
    assert_eq!(
        b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE),
        Err(0x0800_0022)
    );
    // block upload request
    let r = b.sdo([0xA0, 0x08, 0x10, 0, 0, 0, 0, 0]).unwrap();
    assert_eq!(u32::from_le_bytes([r[4], r[5], r[6], r[7]]), 0x0504_0001);
    // nothing changed
    assert_eq!(b.dev.acquisition(), Defaults::nominal().acquisition);
}

#[test]
fn calibration_write_needs_preop_and_unlock() {
    let mut b = Bus::new();
    assert_eq!(b.write_f32(0x2102, 8, 0.01), Err(0x0800_0021));
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    assert_eq!(b.read32(0x2010, 0), 1);
    assert!(b.dev.calibration_unlocked());
    b.write_f32(0x2102, 8, 0.01).unwrap();
    assert_eq!(b.dev.calibration(1).unwrap().gain, 0.01);
    assert_eq!(b.write_f32(0x2102, 8, f32::NAN), Err(0x0609_0030));
    assert_eq!(b.write_f32(0x2102, 8, 0.9), Err(0x0609_0031));
    assert_eq!(b.write_f32(0x2102, 4, -1.5), Err(0x0609_0032));
    b.download(0x2202, 1, &[1]).unwrap();
    assert_eq!(b.download(0x2202, 1, &[2]), Err(0x0609_0030));
    assert_eq!(b.dev.transfer(1).unwrap().kind, 1);
    // any state change locks again
    b.nmt(0x01, 0);
    b.nmt(0x80, 0);
    assert!(!b.dev.calibration_unlocked());
    assert_eq!(b.read32(0x2010, 0), 0);
    assert_eq!(b.write_f32(0x2102, 8, 0.02), Err(0x0800_0021));
    // explicit lock
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_u32(0x2010, 0, 0).unwrap();
    assert_eq!(b.write_f32(0x2102, 8, 0.02), Err(0x0800_0021));
    assert!(!b.dev.calibration_is_default());
}

#[test]
fn config_write_bumps_generation_and_event() {
    let mut b = Bus::new();
    b.dev.take_events();
    let g = b.dev.config_generation();
    b.write_u32(0x2300, 1, 2000).unwrap();
    assert_eq!(b.dev.acquisition().period_us, 2000);
    assert_ne!(b.dev.config_generation(), g);
    assert!(b.dev.take_events().contains(Events::CONFIG_CHANGED));
    b.download(0x2300, 2, &[64, 0]).unwrap();
    b.download(0x2300, 3, &[0]).unwrap();
    assert_eq!(
        b.dev.acquisition().plane_method(),
        perpend_core::normal::Method::Chen
    );
}

#[test]
fn store_reset_and_restore() {
    let mut b = Bus::new();
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_f32(0x2103, 1, 12.5).unwrap();
    b.write_u32(0x2300, 1, 5000).unwrap();
    // store: deferred until the application finishes
    assert_eq!(b.write_u32(0x1010, 1, od::SAVE_SIGNATURE), Err(0));
    assert_eq!(b.dev.pending_request(), Some(Request::Store(Group::All)));
    assert!(b.dev.take_events().contains(Events::REQUEST));
    let mut img = [0u8; IMAGE_LEN];
    b.dev.persistent_image(&mut img);
    let r = b.finish(true);
    assert_eq!(
        r,
        vec![Frame::new(0x590, &[0x60, 0x10, 0x10, 1, 0, 0, 0, 0])]
    );
    // unsaved change, then reset node: the stored values come back
    b.write_f32(0x2103, 1, 99.0).unwrap();
    b.take();
    b.nmt(0x81, NODE);
    assert_eq!(b.dev.nmt_state(), NmtState::Initialising);
    b.poll();
    assert_eq!(b.take(), vec![Frame::new(0x710, &[0])]);
    assert_eq!(b.dev.calibration(2).unwrap().zero[0], 12.5);
    assert_eq!(b.dev.acquisition().period_us, 5000);
    assert!(b.dev.take_events().contains(Events::RESET_NODE));
    // a fresh device with the image has the same values
    let mut d2 = Device::new(NODE, &Defaults::nominal());
    d2.load_image(&img).unwrap();
    assert_eq!(d2.calibration(2), b.dev.calibration(2));
    // restore defaults: effective at the next reset
    assert_eq!(b.write_u32(0x1011, 1, od::LOAD_SIGNATURE), Err(0));
    assert_eq!(b.dev.pending_request(), Some(Request::Restore(Group::All)));
    b.finish(true);
    assert_eq!(b.dev.calibration(2).unwrap().zero[0], 12.5);
    b.nmt(0x81, 0);
    b.poll();
    assert_eq!(
        b.dev.calibration(2),
        Some(Defaults::nominal().calibration[2])
    );
    assert_eq!(b.dev.acquisition(), Defaults::nominal().acquisition);
    assert!(b.dev.calibration_is_default());
}

#[test]
fn failed_store_aborts_and_keeps_boot_values() {
    let mut b = Bus::new();
    b.write_u32(0x2300, 1, 7000).unwrap();
    assert_eq!(b.write_u32(0x1010, 1, od::SAVE_SIGNATURE), Err(0));
    // second request while pending is refused: the abort names the store
    // and ends its transfer (issue 49), so its outcome is sent to nobody
    let r = b.sdo([0x40, 0x00, 0x10, 0, 0, 0, 0, 0]).unwrap();
    assert_eq!(&r[..4], &[0x80, 0x10, 0x10, 1]);
    assert_eq!(u32::from_le_bytes([r[4], r[5], r[6], r[7]]), 0x0800_0020);
    let r = b.finish(false);
    assert!(r.is_empty(), "{r:?}");
    // without a request meanwhile the failure is the store's abort
    assert_eq!(b.write_u32(0x1010, 1, od::SAVE_SIGNATURE), Err(0));
    let r = b.finish(false);
    assert_eq!(r.len(), 1);
    assert_eq!(&r[0].data[..4], &[0x80, 0x10, 0x10, 1]);
    assert_eq!(
        u32::from_le_bytes([r[0].data[4], r[0].data[5], r[0].data[6], r[0].data[7]]),
        0x0800_0020
    );
    assert_eq!(
        b.dev.finish_request(true, &mut |_| {}),
        Err(Error::NoRequest)
    );
    b.nmt(0x81, 0);
    b.poll();
    assert_eq!(b.dev.acquisition().period_us, 1000);
}

#[test]
fn image_validation() {
    let d = Device::new(NODE, &Defaults::nominal());
    let mut img = [0u8; IMAGE_LEN];
    d.persistent_image(&mut img);
    let mut d2 = Device::new(NODE, &Defaults::nominal());
    assert_eq!(
        d2.load_image(&img[..10]),
        Err(Error::ImageLength {
            expected: IMAGE_LEN,
            got: 10
        })
    );
    let mut bad = img;
    bad[0] ^= 1;
    assert_eq!(d2.load_image(&bad), Err(Error::ImageLayout));
    // find the slot of 0x2101 sub 1 in the image and put NaN there
    let pos = od::entries()
        .filter(|(_, _, e)| e.persist)
        .position(|(_, i, e)| i == 0x2101 && e.sub == 1)
        .unwrap();
    let mut bad = img;
    bad[8 + 4 * pos..12 + 4 * pos].copy_from_slice(&f32::NAN.to_bits().to_le_bytes());
    assert_eq!(
        d2.load_image(&bad),
        Err(Error::Value {
            index: 0x2101,
            sub: 1
        })
    );
    // a mapping count pointing at empty entries
    let pos = od::entries()
        .filter(|(_, _, e)| e.persist)
        .position(|(_, i, e)| i == 0x1A00 && e.sub == 0)
        .unwrap();
    let mut bad = img;
    bad[8 + 4 * pos] = 5;
    assert_eq!(
        d2.load_image(&bad),
        Err(Error::Value {
            index: 0x1A00,
            sub: 0
        })
    );
    assert_eq!(d2.calibration(0), d.calibration(0));
    assert_eq!(d2.load_image(&img), Ok(()));
}

#[test]
fn default_tpdos_on_every_sync() {
    let mut b = Bus::new();
    b.dev.set_measurement(&sample());
    assert!(b.sync().is_empty(), "no PDOs in pre-operational");
    b.nmt(0x01, 0);
    let f = b.sync();
    let m = sample();
    let cat = |a: f32, c: f32| {
        let mut v = a.to_le_bytes().to_vec();
        v.extend_from_slice(&c.to_le_bytes());
        v
    };
    assert_eq!(f.len(), 4);
    assert_eq!(f[0].id, 0x190);
    assert_eq!(f[0].payload(), cat(m.theta1_deg, m.theta2_deg));
    assert_eq!(f[1].id, 0x290);
    let mut st = m.status.to_le_bytes().to_vec();
    st.extend_from_slice(&1u32.to_le_bytes());
    assert_eq!(f[1].payload(), st);
    assert_eq!(f[2].id, 0x390);
    assert_eq!(f[2].payload(), cat(m.normal[0], m.normal[1]));
    assert_eq!(f[3].id, 0x490);
    assert_eq!(f[3].payload(), cat(m.normal[2], m.rms_mm));
    assert_eq!(b.dev.sample_counter(), 1);
    assert_eq!(b.dev.measurement(), m);
    // with 0x1019 = 0 a SYNC carrying a counter byte is no SYNC (CiA 301
    // §7.2.5: DLC 0 without counter; CANopenNode ignores it too)
    assert!(b.send(Frame::new(0x80, &[7])).is_empty());
    b.nmt(0x02, 0);
    assert!(b.sync().is_empty());
}

#[test]
fn tpdo_remap_and_cyclic_type() {
    let mut b = Bus::new();
    // mapping can't change while valid
    assert_eq!(b.download(0x1A00, 0, &[0]), Err(0x0800_0022));
    b.write_u32(0x1800, 1, 0x8000_0190).unwrap();
    // entries need sub0 = 0 first
    assert_eq!(
        b.write_u32(0x1A00, 1, od::mapping(0x2005, 0, 32)),
        Err(0x0800_0022)
    );
    b.download(0x1A00, 0, &[0]).unwrap();
    assert_eq!(
        b.write_u32(0x1A00, 1, od::mapping(0x2101, 1, 32)),
        Err(0x0604_0041)
    );
    assert_eq!(
        b.write_u32(0x1A00, 1, od::mapping(0x2005, 0, 16)),
        Err(0x0604_0043)
    );
    assert_eq!(
        b.write_u32(0x1A00, 1, od::mapping(0x2099, 0, 32)),
        Err(0x0602_0000)
    );
    b.write_u32(0x1A00, 1, od::mapping(0x2004, 1, 32)).unwrap();
    b.write_u32(0x1A00, 2, od::mapping(0x2004, 2, 32)).unwrap();
    b.write_u32(0x1A00, 3, od::mapping(0x1001, 0, 8)).unwrap();
    assert_eq!(b.download(0x1A00, 0, &[3]), Err(0x0604_0042));
    assert_eq!(b.download(0x1A00, 0, &[9]), Err(0x0609_0031));
    b.download(0x1A00, 0, &[2]).unwrap();
    b.download(0x1800, 2, &[2]).unwrap(); // every 2nd SYNC
                                          // changing the id while valid is refused; setting it valid works
    b.write_u32(0x1800, 1, 0x4000_01A0).unwrap();
    assert_eq!(b.write_u32(0x1800, 1, 0x4000_01A1), Err(0x0609_0030));
    assert_eq!(
        b.write_u32(0x1801, 1, 0x8000_0000 | 0x2000_0000),
        Err(0x0609_0030)
    );
    b.write_u32(0x1801, 1, 0x8000_0290).unwrap();
    assert_eq!(b.write_u32(0x1801, 1, 0x4000_0601), Err(0x0609_0030));
    b.nmt(0x01, 0);
    b.dev.set_measurement(&sample());
    let ids = |v: Vec<Frame>| v.iter().map(|f| f.id).collect::<Vec<_>>();
    assert_eq!(ids(b.sync()), vec![0x390, 0x490]);
    let f = b.sync();
    assert_eq!(ids(f.clone()), vec![0x1A0, 0x390, 0x490]);
    assert_eq!(f[0].payload()[..4], 40.0f32.to_le_bytes());
    assert_eq!(f[0].len, 8);
}

/// Values of 8 and 32 bits at every byte offset the mapping gives them
/// (a 32-bit value from offset 3 straddles the payload's halves): the
/// payload holds each value little-endian at its offset and zeros past
/// the mapped length.
#[test]
fn tpdo_payload_of_mixed_lengths() {
    let mut b = Bus::new();
    assert!(b.dev.signal_emcy(
        status::emcy::sensor_current(1),
        status::error_register::CURRENT,
        [1, 0, 0, 0, 0]
    ));
    let pdo = |b: &mut Bus, map: &[(u16, u8, u8)]| {
        b.write_u32(0x1800, 1, 0x8000_0190).unwrap();
        b.download(0x1A00, 0, &[0]).unwrap();
        for (i, &(index, sub, bits)) in map.iter().enumerate() {
            b.write_u32(0x1A00, i as u8 + 1, od::mapping(index, sub, bits))
                .unwrap();
        }
        b.download(0x1A00, 0, &[map.len() as u8]).unwrap();
        b.write_u32(0x1800, 1, 0x4000_0190).unwrap();
        b.download(0x1800, 2, &[1]).unwrap();
        b.nmt(0x01, 0);
        b.dev.set_measurement(&sample());
        let f = b.sync().into_iter().find(|f| f.id == 0x190).unwrap();
        b.nmt(0x80, 0);
        f
    };
    let er = b.read32(0x1001, 0) as u8;
    assert_ne!(er, 0, "the error register is set");
    let d = 40.0f32.to_le_bytes();
    let f = pdo(&mut b, &[(0x1001, 0, 8), (0x2004, 1, 32), (0x1001, 0, 8)]);
    assert_eq!(f.len, 6);
    assert_eq!(f.data, [er, d[0], d[1], d[2], d[3], er, 0, 0]);
    let f = pdo(
        &mut b,
        &[
            (0x1001, 0, 8),
            (0x1001, 0, 8),
            (0x1001, 0, 8),
            (0x2004, 1, 32),
        ],
    );
    assert_eq!(f.len, 7);
    assert_eq!(f.data, [er, er, er, d[0], d[1], d[2], d[3], 0]);
    let f = pdo(&mut b, &[(0x2004, 1, 32), (0x2005, 0, 32)]);
    assert_eq!(f.len, 8);
    assert_eq!(f.data[..4], d);
    assert_eq!(f.data[4..], 0x1111u32.to_le_bytes());
}

#[test]
fn event_driven_tpdo_with_inhibit_and_timer() {
    let mut b = Bus::new();
    b.download(0x1801, 2, &[255]).unwrap();
    // the inhibit time changes only while the PDO does not exist
    assert_eq!(b.download(0x1801, 3, &[0x10, 0x27]), Err(0x0609_0030));
    b.write_u32(0x1801, 1, 0x8000_0290).unwrap();
    b.download(0x1801, 3, &[0x10, 0x27]).unwrap(); // 10000 × 100 µs = 1 s
    b.write_u32(0x1801, 1, 0x4000_0290).unwrap();
    b.download(0x1801, 5, &[0xD0, 0x07]).unwrap(); // 2000 ms
    b.download(0x1017, 0, &[0, 0]).unwrap();
    b.nmt(0x01, 0);
    b.take();
    b.poll();
    assert!(b.take().is_empty());
    // application event: sent at the next poll
    b.dev.set_measurement(&sample());
    b.advance(10);
    let f = b.take();
    assert_eq!(f.len(), 1);
    assert_eq!(f[0].id, 0x290);
    // second event inside the inhibit time: delayed until it elapses
    b.dev.set_measurement(&sample());
    b.advance(500_000);
    assert!(b.take().is_empty());
    b.advance(500_010);
    let f = b.take();
    assert_eq!(f.len(), 1);
    assert_eq!(&f[0].payload()[4..], &2u32.to_le_bytes());
    // no event: the event timer fires 2 s after the last transmission
    b.advance(1_999_000);
    assert!(b.take().is_empty());
    b.advance(1_000);
    assert_eq!(b.take().len(), 1);
    // SYNC does not send type 255
    assert!(b.sync().iter().all(|f| f.id != 0x290));
}

#[test]
fn acyclic_sync_type_zero() {
    let mut b = Bus::new();
    b.download(0x1800, 2, &[0]).unwrap();
    b.nmt(0x01, 0);
    assert!(b.sync().iter().all(|f| f.id != 0x190));
    b.dev.set_measurement(&sample());
    assert!(b.sync().iter().any(|f| f.id == 0x190));
    assert!(b.sync().iter().all(|f| f.id != 0x190));
    // the same angles again: no change, nothing at SYNC
    b.dev.set_measurement(&sample());
    assert!(b.sync().iter().all(|f| f.id != 0x190));
    let mut m = sample();
    m.theta1_deg += 0.5;
    b.dev.set_measurement(&m);
    assert!(b.sync().iter().any(|f| f.id == 0x190));
}

/// Types 254/255 send on change of the mapped data (beyond the deadband
/// of 0x2009) and on the event timer, never faster than the inhibit time.
#[test]
fn change_driven_tpdo_with_deadband_timer_and_inhibit() {
    let mut b = Bus::new();
    b.download(0x1017, 0, &[0, 0]).unwrap();
    b.download(0x1800, 2, &[254]).unwrap();
    b.write_u32(0x1800, 1, 0x8000_0190).unwrap();
    b.download(0x1800, 3, &[0xE8, 0x03]).unwrap(); // 100 ms
    b.write_u32(0x1800, 1, 0x4000_0190).unwrap();
    b.nmt(0x01, 0);
    b.take();
    let tpdo1 = |v: Vec<Frame>| v.into_iter().filter(|f| f.id == 0x190).count();
    let mut m = sample();
    b.dev.set_measurement(&m);
    b.advance(10);
    assert_eq!(tpdo1(b.take()), 1, "first sample is a change");
    // noise below the deadband (0.01°) is no change
    for i in 0..50 {
        m.theta1_deg = sample().theta1_deg + if i % 2 == 0 { 0.004 } else { -0.004 };
        b.dev.set_measurement(&m);
        b.advance(10_000);
    }
    assert_eq!(tpdo1(b.take()), 0);
    // a change: sent, the next one only after the inhibit time
    m.theta1_deg += 0.05;
    b.dev.set_measurement(&m);
    b.advance(10);
    assert_eq!(tpdo1(b.take()), 1);
    m.theta2_deg += 0.05;
    b.dev.set_measurement(&m);
    b.advance(50_000);
    assert_eq!(tpdo1(b.take()), 0);
    b.advance(50_010);
    assert_eq!(tpdo1(b.take()), 1);
    // a wider deadband (written in operational: an application object)
    b.write_f32(0x2009, 1, 1.0).unwrap();
    m.theta2_deg += 0.5;
    b.dev.set_measurement(&m);
    b.advance(200_000);
    assert_eq!(tpdo1(b.take()), 0);
    // event timer 100 ms: ten frames a second without any change
    b.download(0x1800, 5, &[100, 0]).unwrap();
    for _ in 0..1000 {
        b.advance(1_000);
    }
    let n = tpdo1(b.take());
    assert!((9..=11).contains(&n), "{n} frames in 1 s");
}

#[test]
fn tpdo_communication_parameters_change_only_while_invalid() {
    let mut b = Bus::new();
    // COB-ID: bits 0-30 while valid refused (0x06090030), valid bit alone ok
    assert_eq!(b.write_u32(0x1800, 1, 0x4000_0191), Err(0x0609_0030));
    assert_eq!(b.write_u32(0x1800, 1, 0x0000_0190), Err(0x0609_0030));
    assert_eq!(b.download(0x1800, 3, &[1, 0]), Err(0x0609_0030));
    b.write_u32(0x1800, 1, 0x8000_0190).unwrap();
    b.write_u32(0x1800, 1, 0x8000_0191).unwrap();
    b.download(0x1800, 3, &[1, 0]).unwrap();
    b.write_u32(0x1800, 1, 0x4000_0191).unwrap();
    // transmission type and event timer: any time (CiA 301 does not
    // restrict them)
    b.download(0x1800, 2, &[254]).unwrap();
    b.download(0x1800, 5, &[10, 0]).unwrap();
    assert_eq!(b.read32(0x1800, 3), 1);
}

#[test]
fn empty_pdos_are_not_sent() {
    let mut b = Bus::new();
    b.write_u32(0x1800, 1, 0x8000_0190).unwrap();
    b.download(0x1A00, 0, &[0]).unwrap();
    b.write_u32(0x1800, 1, 0x4000_0190).unwrap();
    b.download(0x1800, 2, &[255]).unwrap();
    b.download(0x1800, 5, &[10, 0]).unwrap();
    b.nmt(0x01, 0);
    b.dev.set_measurement(&sample());
    for _ in 0..100 {
        b.advance(1_000);
    }
    assert!(b.take().iter().all(|f| f.id != 0x190));
    b.download(0x1800, 2, &[1]).unwrap();
    assert!(b.sync().iter().all(|f| f.id != 0x190));
}

/// An image stored by firmware before issue 16 (layout 1, without 0x2009)
/// still loads; the new entries keep their defaults.
#[test]
fn layout_1_images_still_load() {
    let mut b = Bus::new();
    b.write_u32(0x2300, 1, 4000).unwrap();
    b.write_f32(0x2009, 1, 0.5).unwrap();
    let mut img = [0u8; IMAGE_LEN];
    b.dev.persistent_image(&mut img);
    // drop the words of layouts 2 and 3, sign as layout 1
    let mut buf = [0u8; IMAGE_LEN];
    let n = image_as_v1(&img, &mut buf);
    assert_eq!(n, IMAGE_LEN_V1);
    let mut old = buf[..n].to_vec();
    let mut d = Device::new(NODE, &Defaults::nominal());
    d.load_image(&old).unwrap();
    assert_eq!(d.acquisition().period_us, 4000);
    assert_eq!(d.read_f32(0x2009, 1), Some(od::DEADBAND_DEG));
    // a layout-1 length with the current signature is refused
    old[..4].copy_from_slice(&layout_signature().to_le_bytes());
    assert_eq!(d.load_image(&old), Err(Error::ImageLayout));
}

#[test]
fn emergency_producer_and_error_history() {
    let mut b = Bus::new();
    b.take();
    assert!(b.dev.signal_emcy(
        status::emcy::sensor_current(1),
        status::error_register::CURRENT,
        [2, 0x04, 0, 0, 0]
    ));
    assert!(!b
        .dev
        .signal_emcy(status::emcy::sensor_current(1), 0, [0; 5]));
    b.poll();
    assert_eq!(
        b.take(),
        vec![Frame::new(0x90, &[0x12, 0x21, 0x03, 2, 4, 0, 0, 0])]
    );
    assert_eq!(b.dev.error_register(), 0x03);
    assert_eq!(b.read32(0x1001, 0), 3);
    assert_eq!(b.read32(0x1003, 0), 1);
    assert_eq!(b.read32(0x1003, 1), 0x0402_2112);
    b.dev.signal_emcy(
        status::emcy::NO_PLANE,
        status::error_register::MANUFACTURER,
        [2, 0, 0, 0, 0],
    );
    assert_eq!(b.read32(0x1003, 0), 2);
    assert_eq!(b.read32(0x1003, 1) & 0xFFFF, 0xFF02);
    assert_eq!(b.read32(0x1003, 2) & 0xFFFF, 0x2112);
    // every clear: one error reset with the remaining register and the
    // cleared code
    assert!(b.dev.clear_emcy(status::emcy::sensor_current(1)));
    assert!(!b.dev.clear_emcy(status::emcy::sensor_current(1)));
    assert_eq!(b.dev.error_register(), 0x81);
    b.take();
    b.poll();
    let f = b.take();
    assert_eq!(f.len(), 2); // the NO_PLANE EMCY, the error reset
    assert_eq!(f[1], Frame::new(0x90, &[0, 0, 0x81, 0x12, 0x21, 0, 0, 0]));
    b.dev.clear_emcy(status::emcy::NO_PLANE);
    b.poll();
    assert_eq!(
        b.take(),
        vec![Frame::new(0x90, &[0, 0, 0, 0x02, 0xFF, 0, 0, 0])]
    );
    assert_eq!(b.dev.error_register(), 0);
    // history clear: only 0 accepted
    assert_eq!(b.download(0x1003, 0, &[1]), Err(0x0609_0030));
    b.download(0x1003, 0, &[0]).unwrap();
    assert_eq!(b.read32(0x1003, 0), 0);
    assert_eq!(b.read32(0x1003, 1), 0);
    // not sent while stopped: raised just before the stop or in it, the
    // EMCYs wait for pre-operational (issue 49; CANopenNode keeps its
    // FIFO); the state (0x1001, active set) follows meanwhile
    b.dev.signal_emcy(status::emcy::NO_PLANE, 0x80, [0; 5]);
    b.nmt(0x02, 0);
    b.take();
    b.dev.signal_emcy(status::emcy::DATA_SET, 1, [0; 5]);
    b.poll();
    assert!(b.take().is_empty());
    assert!(b.dev.emcy_active(status::emcy::DATA_SET));
    assert_eq!(b.dev.error_register(), 0x81);
    b.nmt(0x80, 0);
    b.poll();
    let sent: Vec<u16> = emcys_of(&b.take()).iter().map(|e| e.0).collect();
    assert_eq!(sent, [status::emcy::NO_PLANE, status::emcy::DATA_SET]);
    // reset node clears errors
    b.nmt(0x81, 0);
    b.poll();
    assert_eq!(b.dev.error_register(), 0);
    assert!(!b.dev.emcy_active(status::emcy::DATA_SET));
}

/// 0x200C counts seconds since power-on; 0x2012 holds, at the sub-index of
/// each 0x1003 entry, the uptime at which it was recorded: the entries and
/// their times move together, a repeated code takes its latest time, and
/// clearing the history clears the times.
#[test]
fn error_history_times_follow_their_entries() {
    let mut b = Bus::new();
    b.download(0x1017, 0, &[0, 0]).unwrap();
    b.advance(5_200_000);
    assert_eq!(b.read32(0x200C, 0), 5);
    b.dev.signal_emcy(status::emcy::NO_PLANE, 0x80, [0; 5]);
    b.advance(2_000_000);
    b.dev.signal_emcy(status::emcy::DATA_SET, 0x01, [0; 5]);
    b.advance(3_000_000);
    assert_eq!(b.read32(0x200C, 0), 10);
    assert_eq!(b.read32(0x1003, 1) & 0xFFFF, status::emcy::DATA_SET as u32);
    assert_eq!((b.read32(0x2012, 1), b.read32(0x2012, 2)), (7, 5));
    // NO_PLANE again (cleared, raised at 10 s): back to sub 1 with its time.
    b.dev.clear_emcy(status::emcy::NO_PLANE);
    b.dev.signal_emcy(status::emcy::NO_PLANE, 0x80, [0; 5]);
    assert_eq!(b.read32(0x1003, 0), 2);
    assert_eq!(b.read32(0x1003, 1) & 0xFFFF, status::emcy::NO_PLANE as u32);
    assert_eq!((b.read32(0x2012, 1), b.read32(0x2012, 2)), (10, 7));
    b.download(0x1003, 0, &[0]).unwrap();
    assert_eq!((b.read32(0x2012, 1), b.read32(0x2012, 2)), (0, 0));
    assert_eq!(b.download(0x2012, 1, &[1, 0, 0, 0]), Err(0x0601_0002));
}

/// 0x1015: at most one EMCY per inhibit time; a flapping code appears
/// once in 0x1003.
#[test]
fn emcy_inhibit_time_and_history_without_duplicates() {
    let mut b = Bus::new();
    b.download(0x1015, 0, &[0xE8, 0x03]).unwrap(); // 1000 × 100 µs = 100 ms
    b.download(0x1017, 0, &[0, 0]).unwrap();
    b.take();
    for _ in 0..3 {
        b.dev
            .signal_emcy(status::emcy::NO_PLANE, 0x80, [1, 0, 0, 0, 0]);
        b.dev.clear_emcy(status::emcy::NO_PLANE);
    }
    b.dev
        .signal_emcy(status::emcy::DATA_SET, 0x01, [0, 0, 0, 0, 0]);
    // 7 queued: one now, then one per 100 ms
    b.poll();
    assert_eq!(b.take().len(), 1);
    b.advance(99_000);
    assert!(b.take().is_empty());
    b.advance(1_000);
    assert_eq!(b.take().len(), 1);
    for _ in 0..600 {
        b.advance(1_000);
    }
    assert_eq!(b.take().len(), 5);
    // history: NO_PLANE once, DATA_SET newest
    assert_eq!(b.read32(0x1003, 0), 2);
    assert_eq!(b.read32(0x1003, 1) & 0xFFFF, 0x6300);
    assert_eq!(b.read32(0x1003, 2) & 0xFFFF, 0xFF02);
    b.dev
        .signal_emcy(status::emcy::NO_PLANE, 0x80, [3, 0, 0, 0, 0]);
    assert_eq!(b.read32(0x1003, 0), 2);
    assert_eq!(b.read32(0x1003, 1), 0x0003_FF02);
    assert_eq!(b.read32(0x1003, 2) & 0xFFFF, 0x6300);
}

#[test]
fn node_id_change_at_reset_communication() {
    let mut b = Bus::new();
    b.download(0x2400, 1, &[0x20]).unwrap();
    assert_eq!(b.download(0x2400, 1, &[0]), Err(0x0609_0032));
    assert_eq!(b.download(0x2400, 1, &[128]), Err(0x0609_0031));
    assert_eq!(b.dev.node_id(), NODE);
    b.write_u32(0x1802, 1, 0x8000_0390).unwrap(); // disabled TPDO3 keeps flags
    b.take();
    b.nmt(0x82, NODE);
    b.poll();
    assert_eq!(b.take(), vec![Frame::new(0x720, &[0])]);
    assert_eq!(b.dev.node_id(), 0x20);
    assert!(b.dev.take_events().contains(Events::RESET_COMM));
    assert_eq!(b.read32(0x1014, 0), 0xA0);
    assert_eq!(b.read32(0x1200, 2), 0x5A0);
    assert_eq!(b.read32(0x1800, 1), 0x4000_01A0);
    // reset comm restored TPDO3 to its power-on value, then followed the id
    assert_eq!(b.read32(0x1802, 1), 0x4000_03A0);
    // reset node without a store: the configured id stays active (it is
    // not dropped silently; it is lost at power-off unless saved)
    b.nmt(0x81, 0x20);
    b.poll();
    assert_eq!(b.dev.node_id(), 0x20);
    assert_eq!(b.read32(0x1800, 1), 0x4000_01A0);
    assert_eq!(b.read32(0x1802, 1), 0x4000_03A0);
}

#[test]
fn reset_comm_keeps_application_parameters() {
    let mut b = Bus::new();
    b.write_u32(0x2300, 1, 3000).unwrap();
    b.download(0x1017, 0, &[50, 0]).unwrap();
    b.nmt(0x82, 0);
    b.poll();
    assert_eq!(b.dev.acquisition().period_us, 3000);
    assert_eq!(b.dev.heartbeat_ms(), 1000);
}

#[test]
fn sdo_segmented_download_and_timeout_in_device() {
    let mut b = Bus::new();
    let r = b.sdo([0x21, 0x00, 0x23, 1, 4, 0, 0, 0]).unwrap();
    assert_eq!(r[0], 0x60);
    let r = b.sdo([0x07, 0xB8, 0x0B, 0, 0, 0, 0, 0]).unwrap();
    assert_eq!(r[0], 0x20);
    assert_eq!(b.dev.acquisition().period_us, 3000);
    // segmented upload left hanging times out
    b.sdo([0x40, 0x08, 0x10, 0, 0, 0, 0, 0]).unwrap();
    b.take();
    b.advance(999_999);
    assert!(b.take().iter().all(|f| f.id != 0x590));
    b.advance(1);
    let f: Vec<_> = b.take().into_iter().filter(|f| f.id == 0x590).collect();
    assert_eq!(f.len(), 1);
    assert_eq!(&f[0].data[..4], &[0x80, 0x08, 0x10, 0]);
    assert_eq!(&f[0].data[4..], &0x0504_0000u32.to_le_bytes());
}

#[test]
fn stored_params_bridge() {
    use perpend_core::params::Params;
    let mut p = Params::factory();
    p.head.sensors[1].zero.x += 0.5;
    p.head.sensors[2].ext.gain = 2e-3;
    p.acq.period_us = 2000;
    p.can.node_id = 0x30;
    let mut b = Bus::new();
    b.dev.take_events();
    b.dev.load_params(&p).unwrap();
    assert!(b.dev.take_events().contains(Events::CONFIG_CHANGED));
    assert_eq!(b.dev.node_id(), 0x30);
    assert_eq!(b.dev.acquisition().period_us, 2000);
    let q = b.dev.params(&Params::factory());
    assert!(q.validate().is_ok());
    for (a, c) in q.head.sensors.iter().zip(p.head.sensors.iter()) {
        assert!((a.zero - c.zero).norm() < 1e-6);
        assert!((a.dir - c.dir).norm() < 1e-6);
        assert_eq!(a.ext, c.ext);
    }
    assert_eq!((q.transfer, q.acq, q.can), (p.transfer, p.acq, p.can));
    // SDO writes show up in params(); a zero direction stays invalid
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    for sub in 4..=6 {
        b.write_f32(0x2101, sub, 0.0).unwrap();
    }
    assert!(b.dev.params(&p).validate().is_err());
    // out-of-range record: refused as a whole
    let mut bad = p;
    bad.head.sensors[3].zero.z = 5000.0;
    let before = b.dev.calibration(0);
    assert_eq!(
        b.dev.load_params(&bad),
        Err(Error::Value {
            index: 0x2104,
            sub: 3
        })
    );
    assert_eq!(b.dev.calibration(0), before);
    // the loaded record is the power-on value; restore brings the factory back
    b.nmt(0x81, 0);
    b.poll();
    assert_eq!(b.dev.calibration(2).unwrap().gain, 2e-3);
    assert_eq!(b.write_u32(0x1011, 1, od::LOAD_SIGNATURE), Err(0));
    b.finish(true);
    b.nmt(0x81, 0);
    b.poll();
    assert!(b.dev.calibration_is_default());
    // the node-id of the record is a layer setting: no restore touches it
    assert_eq!(b.dev.node_id(), 0x30);
}

#[test]
fn publish_follows_the_status_word() {
    use status::*;
    let mut b = Bus::new();
    b.take();
    let ok = sensor_bits(0, SENSOR_VALID)
        | sensor_bits(1, SENSOR_VALID)
        | sensor_bits(2, SENSOR_VALID)
        | sensor_bits(3, SENSOR_VALID);
    let mut m = sample();
    m.status = ok;
    b.dev.publish(&m);
    b.poll();
    assert!(b.take().is_empty());
    assert_eq!(b.dev.error_register(), 0);
    // sensor 3 open loop: one EMCY, degraded plane
    m.status = (ok & !sensor_bits(2, SENSOR_MASK)) | sensor_bits(2, SENSOR_OPEN_LOOP) | DEGRADED;
    b.dev.publish(&m);
    b.dev.publish(&m);
    b.poll();
    assert_eq!(
        b.take(),
        vec![Frame::new(0x90, &[0x13, 0x21, 0x03, 3, 0x04, 0, 0, 0])]
    );
    // two sensors lost: no plane as well
    m.status = sensor_bits(0, SENSOR_VALID)
        | sensor_bits(1, SENSOR_VALID)
        | sensor_bits(2, SENSOR_OPEN_LOOP)
        | NO_PLANE
        | SENSOR_STUCK;
    b.dev.publish(&m);
    b.poll();
    let f = b.take();
    assert_eq!(f.len(), 2);
    assert_eq!(f[0].data[..3], [0x14, 0xFF, 0x83]); // current bit of sensor 3 still set
    assert_eq!(f[0].data[3..6], [4, 0, 1]);
    assert_eq!(f[1].data[..4], [0x02, 0xFF, 0x83, 2]);
    // all good again: one error reset per cleared code, the last with an
    // empty error register
    m.status = ok;
    b.dev.publish(&m);
    b.poll();
    let f = b.take();
    assert_eq!(f.len(), 3);
    assert!(f.iter().all(|f| f.data[..2] == [0, 0]));
    assert_eq!(f[2], Frame::new(0x90, &[0, 0, 0, 0x02, 0xFF, 0, 0, 0]));
    m.status = ok | CONFIG_INVALID;
    b.dev.publish(&m);
    assert!(b.dev.emcy_active(emcy::DATA_SET));
}

// ---------------------------------------------------------------------
// Property tests

/// Frames a fuzzing client might send: mostly SDO requests to our node
/// built from a pool of relevant objects, some NMT/SYNC, some noise.
fn arb_frame() -> impl Strategy<Value = Frame> {
    let indices = prop::sample::select(vec![
        0x1000u16, 0x1001, 0x1003, 0x1005, 0x1008, 0x1010, 0x1011, 0x1014, 0x1017, 0x1018, 0x1200,
        0x1800, 0x1801, 0x1A00, 0x1A01, 0x2001, 0x2005, 0x2010, 0x2101, 0x2104, 0x2201, 0x2300,
        0x2400, 0x2500, 0x6000,
    ]);
    let sdo = (
        prop::sample::select(vec![
            0x40u8, 0x43, 0x23, 0x27, 0x2B, 0x2F, 0x22, 0x21, 0x20, 0x60, 0x70, 0x00, 0x10, 0x07,
            0x17, 0x80, 0xA0, 0xC0, 0xE0,
        ]),
        indices,
        0u8..18,
        prop::array::uniform4(prop::sample::select(vec![
            0u8, 1, 2, 5, 0x80, 0xFF, 0x73, 0x61, 0x76, 0x65, 0x75, 0x63, 0x6C, 0x90, 0x01, 0x20,
        ])),
        any::<bool>(),
    )
        .prop_map(|(cmd, idx, sub, d, raw)| {
            let i = idx.to_le_bytes();
            let mut data = [cmd, i[0], i[1], sub, d[0], d[1], d[2], d[3]];
            if raw {
                // occasionally a write of a mapping / signature value
                data[4..].copy_from_slice(&od::UNLOCK_SIGNATURE.to_le_bytes());
            }
            Frame::new(0x600 + NODE as u16, &data)
        });
    let nmt = (
        prop::sample::select(vec![1u8, 2, 0x80, 0x81, 0x82, 0x33]),
        prop::sample::select(vec![0u8, NODE, NODE + 1]),
    )
        .prop_map(|(cs, n)| Frame::new(0, &[cs, n]));
    let noise = (0u16..0x900, any::<bool>(), 0u8..12, any::<[u8; 8]>())
        .prop_map(|(id, rtr, len, data)| Frame { id, rtr, len, data });
    prop_oneof![
        8 => sdo,
        1 => nmt,
        1 => Just(Frame::new(0x80, &[])),
        1 => noise,
    ]
}

/// Whether `resp` is a well-formed server response to `req`.
fn valid_response(req: &[u8; 8], resp: &Frame, in_block: bool) -> bool {
    if resp.len != 8 {
        return false;
    }
    let r = resp.data[0];
    if r == 0x80 {
        let code = u32::from_le_bytes([resp.data[4], resp.data[5], resp.data[6], resp.data[7]]);
        return SdoAbort::from_code(code).is_some();
    }
    if in_block {
        // A segment's sub-block acknowledgement, or the end's confirmation.
        return (r == 0xA2 && resp.data[2] >= 1 && resp.data[2] <= 127) || r == 0xA1;
    }
    match req[0] >> 5 {
        6 => r == 0xA4 && resp.data[1..4] == req[1..4] && resp.data[4] == 127,
        1 => r == 0x60 && resp.data[1..4] == req[1..4],
        2 => (r & 0xE0) == 0x40 && resp.data[1..4] == req[1..4],
        0 => (r & 0xEF) == 0x20 && (r & 0x10) == (req[0] & 0x10),
        3 => (r & 0xE0) == 0x00 && (r & 0x10) == (req[0] & 0x10),
        _ => false,
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// Arbitrary frame sequences: no panic; every SDO request in
    /// pre-operational/operational is answered exactly once with a valid
    /// response or abort (client aborts and deferred stores excepted); read-
    /// only objects keep their values (the clock 0x200C and the error
    /// times 0x2012 excepted, like 0x1001/0x1003); every entry reads back over SDO as
    /// the device holds it; values stay within their limits.
    #[test]
    fn arbitrary_frames_keep_the_dictionary_sound(
        frames in prop::collection::vec((arb_frame(), 0u64..300_000), 1..120)
    ) {
        let mut b = Bus::new();
        let ro_before: Vec<(usize, u32)> = od::entries()
            .filter(|(_, i, e)| e.access != od::Access::Rw && !matches!(i, 0x1001 | 0x1003 | 0x1014 | 0x1200 | 0x2001..=0x2007 | 0x200C | 0x2012))
            .map(|(s, _, _)| (s, b.dev.core.values[s]))
            .collect();
        let meas_before: Vec<(usize, u32)> = od::entries()
            .filter(|(_, i, _)| (0x2001..=0x2007).contains(i))
            .map(|(s, _, _)| (s, b.dev.core.values[s]))
            .collect();
        for (f, dt) in frames {
            b.now += dt;
            let node = b.dev.node_id() as u16;
            let state = b.dev.nmt_state();
            let deferred_before = b.dev.pending_request().is_some();
            let in_block = b.dev.sdo.in_block();
            let out = b.send(f);
            let sdo_out: Vec<&Frame> = out.iter().filter(|o| o.id == 0x580 + node).collect();
            if f.id == 0x600 + node && f.len <= 8 && !f.rtr
                && matches!(state, NmtState::PreOperational | NmtState::Operational)
            {
                let mut req = [0u8; 8];
                req.copy_from_slice(&f.data);
                if f.len < 8 {
                    // malformed requests are answered with an abort
                    req[0] = if f.len == 0 { 0xFF } else { req[0] };
                }
                // Inside a sub-block only an 8-byte frame is a segment: a
                // shorter one with ccs 4 is a client abort there too.
                let segment = in_block && f.len == 8;
                let client_abort = f.len > 0 && (req[0] >> 5 == 4) && (!segment || req[0] == 0x80);
                let deferred_now = !deferred_before && b.dev.pending_request().is_some();
                if client_abort || deferred_now {
                    prop_assert!(sdo_out.is_empty());
                } else if in_block && f.len == 8 && sdo_out.is_empty() {
                    // A segment inside a sub-block: answered at its end.
                } else {
                    prop_assert_eq!(sdo_out.len(), 1, "request {:02x?}", req);
                    let in_block = in_block && f.len == 8;
                    prop_assert!(valid_response(&req, sdo_out[0], in_block), "{:02x?} -> {:02x?}", req, sdo_out[0].data);
                }
            } else {
                prop_assert!(sdo_out.is_empty());
            }
            // The application completes storage requests immediately.
            if b.dev.pending_request().is_some() {
                b.finish(true);
            }
            b.poll();
        }
        for (s, v) in ro_before {
            prop_assert_eq!(b.dev.core.values[s], v);
        }
        for (s, v) in meas_before {
            prop_assert_eq!(b.dev.core.values[s], v);
        }
        // Every persisted value is acceptable as an image value.
        let mut img = [0u8; IMAGE_LEN];
        b.dev.persistent_image(&mut img);
        let mut fresh = Device::new(NODE, &Defaults::nominal());
        prop_assert_eq!(fresh.load_image(&img), Ok(()));
        // Everything reads back over SDO as held (in pre-operational), a
        // block download left open ended by a client abort first.
        b.sdo([0x80, 0, 0, 0, 0, 0, 0, 0]);
        b.nmt(0x80, 0);
        if b.dev.nmt_state() == NmtState::PreOperational {
            let entries: Vec<_> = od::entries().collect();
            for (s, index, e) in entries {
                let got = b.upload(index, e.sub);
                match e.ty {
                    od::DataType::VisibleString => prop_assert!(got.is_ok()),
                    od::DataType::Domain => prop_assert_eq!(got, Err(0x0601_0001)),
                    _ => {
                        let mut want = b.dev.core.values[s].to_le_bytes().to_vec();
                        want.truncate(e.ty.size());
                        prop_assert_eq!(got, Ok(want));
                    }
                }
            }
        }
    }

    /// Writable entries change only through successful SDO downloads: a
    /// device that receives only aborted writes keeps every value.
    #[test]
    fn aborted_writes_change_nothing(
        writes in prop::collection::vec((0usize..od::ENTRIES, any::<u32>(), 0usize..5), 1..60)
    ) {
        let mut b = Bus::new();
        let entries: Vec<_> = od::entries().collect();
        for (k, v, n) in writes {
            let (_, index, e) = entries[k];
            let before = b.dev.core.values;
            let unlocked = b.dev.calibration_unlocked();
            let bytes = v.to_le_bytes();
            let mut r = b.download(index, e.sub, &bytes[..n.clamp(1, 4)]);
            if b.dev.pending_request().is_some() {
                // A deferred write (store, program control) is answered
                // when the application finishes it: that answer counts.
                let answer = b.finish(true);
                if let Some(f) = answer.iter().find(|f| f.id == 0x580 + u16::from(NODE)) {
                    r = match f.data[0] {
                        0x60 => Ok(()),
                        _ => Err(u32::from_le_bytes([f.data[4], f.data[5], f.data[6], f.data[7]])),
                    };
                }
            }
            if r.is_err() {
                prop_assert_eq!(before, b.dev.core.values, "{:#06x}/{}", index, e.sub);
                prop_assert_eq!(unlocked, b.dev.calibration_unlocked());
            } else if !matches!(e.ty, od::DataType::VisibleString | od::DataType::Domain) && index != 0x1010 && index != 0x1011 && index != 0x2010 {
                // the accepted value is what was written
                let mut want = [0u8; 4];
                want[..e.ty.size()].copy_from_slice(&bytes[..e.ty.size()]);
                prop_assert_eq!(b.dev.read_u32(index, e.sub), Some(u32::from_le_bytes(want)));
            }
        }
    }
}

#[path = "device_sync_tests.rs"]
mod sync_tests;

/// Knots and coefficients of the linearity table used below [mm, mm⁻¹]:
/// exact in `f32`.
const KNOTS: [f32; 5] = [-6.0, -3.0, 0.0, 2.0, 6.0];
const COEFFS: [f32; 3] = [1.0e-3, -2.0e-3, 1.5e-3];

/// Writes the table into sensor calibration object `index`, knots first.
fn write_table(b: &mut Bus, index: u16) {
    for (k, v) in KNOTS.iter().enumerate() {
        b.write_f32(index, CAL_SUB_KNOTS + k as u8, *v).unwrap();
    }
    for (k, v) in COEFFS.iter().enumerate() {
        b.write_f32(index, CAL_SUB_COEFFS + k as u8, *v).unwrap();
    }
}

/// The linearity table (0x2101..0x2104 sub 16..23) goes in and out by
/// SDO bit for bit, reaches the typed view, the stored record bridge and
/// the persistence image, and sub 0 announces 25 (the spot coefficients
/// follow the table).
#[test]
fn linearity_table_round_trips_through_sdo() {
    let mut b = Bus::new();
    assert_eq!(b.upload(0x2103, 0).unwrap(), vec![25]);
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    write_table(&mut b, 0x2103);
    for (k, v) in KNOTS.iter().chain(COEFFS.iter()).enumerate() {
        let got = b.upload(0x2103, CAL_SUB_KNOTS + k as u8).unwrap();
        assert_eq!(got, v.to_le_bytes().to_vec(), "sub {}", 16 + k);
    }
    let c = b.dev.calibration(2).unwrap();
    assert_eq!((c.knots, c.coeffs), (KNOTS, COEFFS));
    // the other sensors keep no table
    assert!(!b.dev.calibration(1).unwrap().table::<f32>().is_active());
    let p = b.dev.params(&perpend_core::params::Params::factory());
    let t = p.head.sensors[2].ext.table;
    assert_eq!((t.knots, t.coeffs), (KNOTS, COEFFS));
    let mut img = [0u8; IMAGE_LEN];
    b.dev.persistent_image(&mut img);
    let mut d = Device::new(NODE, &Defaults::nominal());
    d.load_image(&img).unwrap();
    assert_eq!(d.calibration(2), Some(c));
    // and through load_params (the stored record at boot)
    let mut d = Device::new(NODE, &Defaults::nominal());
    d.load_params(&p).unwrap();
    assert_eq!(d.calibration(2), Some(c));
}

/// A write that would leave an active table with knots not strictly
/// ascending is refused (0x06090030) and changes nothing; inactive
/// tables take any knots. Loads of such a table are refused as a whole.
#[test]
fn bad_linearity_table_is_refused() {
    let mut b = Bus::new();
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    // coefficients on the default knots (all 0): refused
    assert_eq!(b.write_f32(0x2101, CAL_SUB_COEFFS, 1e-3), Err(0x0609_0030));
    assert_eq!(b.dev.calibration(0).unwrap().coeffs, [0.0; 3]);
    write_table(&mut b, 0x2101);
    // a knot that coincides with its neighbour, or goes backwards
    assert_eq!(b.write_f32(0x2101, 19, 0.0), Err(0x0609_0030));
    assert_eq!(b.write_f32(0x2101, 16, -2.0), Err(0x0609_0030));
    assert_eq!(b.dev.calibration(0).unwrap().knots, KNOTS);
    // a move that keeps the order is taken
    b.write_f32(0x2101, 20, 8.0).unwrap();
    // with the coefficients zeroed the knots are free again
    for k in 0..3 {
        b.write_f32(0x2101, CAL_SUB_COEFFS + k, 0.0).unwrap();
    }
    b.write_f32(0x2101, 19, 0.0).unwrap();
    // a forged image and a record with such a table: refused whole
    write_table(&mut b, 0x2102);
    let mut img = [0u8; IMAGE_LEN];
    b.dev.persistent_image(&mut img);
    let pos = od::entries()
        .filter(|(_, _, e)| e.persist)
        .position(|(_, i, e)| i == 0x2102 && e.sub == 18)
        .unwrap();
    img[8 + 4 * pos..12 + 4 * pos].copy_from_slice(&(-3.0f32).to_bits().to_le_bytes());
    let mut d = Device::new(NODE, &Defaults::nominal());
    let bad = Error::Value {
        index: 0x2102,
        sub: 16,
    };
    assert_eq!(d.load_image(&img), Err(bad));
    let mut p = perpend_core::params::Params::factory();
    p.head.sensors[1].ext.table.coeffs = [1e-3, 0.0, 0.0];
    assert_eq!(d.load_params(&p), Err(bad));
    assert!(d.calibration_is_default());
}

/// An image written before layout 5 (no linearity tables) loads; the
/// tables keep their current values.
#[test]
fn layout_4_image_loads() {
    let mut b = Bus::new();
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_f32(0x2104, 7, 42.0).unwrap();
    write_table(&mut b, 0x2104);
    let (_, old, n) = image_and_layout(&b, 4);
    assert_eq!(n, IMAGE_LEN_V4);
    assert_eq!(IMAGE_LEN_V5 - IMAGE_LEN_V4, 4 * 4 * 8);
    let mut d = Device::new(NODE, &Defaults::nominal());
    d.load_image(&old[..n]).unwrap();
    let c = d.calibration(3).unwrap();
    assert_eq!(c.d_ref, 42.0);
    assert_eq!((c.knots, c.coeffs), ([0.0; 5], [0.0; 3]));
}

/// 0x2105, the head's thermal time constant: a REAL32 calibration object
/// (pre-operational and unlock), range 0..86400 s with the CiA 301 range
/// aborts, read back by SDO, applied at once (configuration event) and
/// carried by `params`.
#[test]
fn thermal_time_constant_write_read_and_range() {
    let mut b = Bus::new();
    assert_eq!(b.dev.thermal_tau_s(), 0.0);
    assert_eq!(b.upload(0x2105, 0), Ok(0f32.to_le_bytes().to_vec()));
    assert_eq!(b.upload(0x2105, 1), Err(0x0609_0011));
    assert_eq!(b.write_f32(0x2105, 0, 600.0), Err(0x0800_0021));
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.dev.take_events();
    let g = b.dev.config_generation();
    b.write_f32(0x2105, 0, 612.5).unwrap();
    assert!(b.dev.take_events().contains(Events::CONFIG_CHANGED));
    assert_ne!(b.dev.config_generation(), g);
    assert_eq!(b.dev.thermal_tau_s(), 612.5);
    assert_eq!(b.upload(0x2105, 0), Ok(612.5f32.to_le_bytes().to_vec()));
    assert_eq!(b.dev.read_f32(0x2105, 0), Some(612.5));
    for (v, abort) in [
        (-0.5f32, 0x0609_0032),
        (86_401.0, 0x0609_0031),
        (f32::NAN, 0x0609_0030),
        (f32::INFINITY, 0x0609_0030),
    ] {
        assert_eq!(b.write_f32(0x2105, 0, v), Err(abort), "{v}");
        assert_eq!(
            b.dev.thermal_tau_s(),
            612.5,
            "refused write changes nothing"
        );
    }
    assert_eq!(b.download(0x2105, 0, &[0, 0]), Err(0x0607_0013));
    b.write_f32(0x2105, 0, 86_400.0).unwrap();
    b.write_f32(0x2105, 0, 0.0).unwrap();
    b.write_f32(0x2105, 0, 30.0).unwrap();
    let base = perpend_core::params::Params::factory();
    assert_eq!(b.dev.params(&base).thermal_tau_s, 30.0);
    // τ alone does not make the head a calibrated one (status bit 17)
    assert!(b.dev.calibration_is_default());
    // in operational: refused like the other calibration objects
    b.nmt(0x01, 0);
    assert_eq!(b.write_f32(0x2105, 0, 40.0), Err(0x0800_0022));
}

/// τ is stored with the application group (0x1010 sub 3), survives a
/// reset node through the image, is restored to the defaults' value by
/// 0x1011, and comes in through `load_params` and `Defaults::from_params`.
#[test]
fn thermal_time_constant_is_stored_and_restored() {
    let mut b = Bus::new();
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_f32(0x2105, 0, 900.0).unwrap();
    assert_eq!(b.write_u32(0x1010, 2, od::SAVE_SIGNATURE), Err(0));
    b.finish(true);
    // a communication-group store does not store it
    b.nmt(0x81, 0);
    b.poll();
    assert_eq!(b.dev.thermal_tau_s(), 0.0);
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_f32(0x2105, 0, 900.0).unwrap();
    assert_eq!(b.write_u32(0x1010, 3, od::SAVE_SIGNATURE), Err(0));
    let mut img = [0u8; IMAGE_LEN];
    b.dev.persistent_image(&mut img);
    b.finish(true);
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_f32(0x2105, 0, 5.0).unwrap();
    b.nmt(0x81, 0);
    b.poll();
    assert_eq!(b.dev.thermal_tau_s(), 900.0);
    let mut d = Device::new(NODE, &Defaults::nominal());
    d.load_image(&img).unwrap();
    assert_eq!(d.thermal_tau_s(), 900.0);
    // a forged image with τ out of range is refused whole
    let pos = od::entries()
        .filter(|(_, _, e)| e.persist)
        .position(|(_, i, _)| i == 0x2105)
        .unwrap();
    let mut bad = img;
    bad[8 + 4 * pos..12 + 4 * pos].copy_from_slice(&(-1.0f32).to_bits().to_le_bytes());
    let mut d = Device::new(NODE, &Defaults::nominal());
    assert_eq!(
        d.load_image(&bad),
        Err(Error::Value {
            index: 0x2105,
            sub: 0
        })
    );
    // restore: the defaults' τ at the next reset node
    assert_eq!(b.write_u32(0x1011, 3, od::LOAD_SIGNATURE), Err(0));
    b.finish(true);
    b.nmt(0x81, 0);
    b.poll();
    assert_eq!(b.dev.thermal_tau_s(), 0.0);
    // from a stored record, and as a default
    let p = perpend_core::params::Params {
        thermal_tau_s: 120.0,
        ..perpend_core::params::Params::factory()
    };
    let mut d = Device::new(NODE, &Defaults::nominal());
    d.load_params(&p).unwrap();
    assert_eq!(d.thermal_tau_s(), 120.0);
    assert_eq!(
        d.params(&p),
        d.params(&perpend_core::params::Params::factory())
    );
    let d = Device::new(NODE, &Defaults::from_params(&p));
    assert_eq!(d.thermal_tau_s(), 120.0);
}

/// An image written before layout 6 (no 0x2105) loads; τ keeps its
/// current value (the defaults': no lag).
#[test]
fn layout_5_image_loads_without_lag() {
    let mut b = Bus::new();
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_f32(0x2103, 7, 41.0).unwrap();
    b.write_f32(0x2105, 0, 300.0).unwrap();
    let (img, old, n) = image_and_layout(&b, 5);
    assert_eq!(n, IMAGE_LEN_V5);
    assert_eq!(IMAGE_LEN_V6 - IMAGE_LEN_V5, 4);
    let mut d = Device::new(NODE, &Defaults::nominal());
    d.load_image(&old[..n]).unwrap();
    assert_eq!(d.calibration(2).unwrap().d_ref, 41.0);
    assert_eq!(d.thermal_tau_s(), 0.0);
    // a layout-5 signature over a layout-6 length (and the reverse) is refused
    let mut forged = img;
    forged[0..4].copy_from_slice(&old[0..4]);
    assert_eq!(d.load_image(&forged), Err(Error::ImageLayout));
}

/// The codes the device and the board application can have active at
/// once, with their error-register bits: both codes of every sensor
/// (current and reading overlap during the board's clear delay), no
/// plane, data set, and the communication errors of `device_sync.rs`.
fn codes_active_at_once() -> Vec<(u16, u8)> {
    use status::emcy;
    use status::error_register as r;
    let mut v: Vec<(u16, u8)> = (0..4)
        .flat_map(|i| {
            [
                (emcy::sensor_current(i), r::CURRENT),
                (emcy::sensor_reading(i), r::MANUFACTURER),
            ]
        })
        .collect();
    v.extend([
        (emcy::NO_PLANE, r::MANUFACTURER),
        (emcy::DATA_SET, r::GENERIC),
        (EMCY_HEARTBEAT, r::COMMUNICATION),
        (EMCY_SYNC_LENGTH, r::COMMUNICATION),
        (EMCY_PDO_LENGTH, r::COMMUNICATION),
    ]);
    v
}

/// The EMCY frames (code, register, manufacturer bytes 0-1) in `f`.
fn emcys_of(f: &[Frame]) -> Vec<(u16, u8, u16)> {
    f.iter()
        .filter(|f| f.id == 0x80 + NODE as u16)
        .map(|f| {
            (
                u16::from_le_bytes([f.data[0], f.data[1]]),
                f.data[2],
                u16::from_le_bytes([f.data[3], f.data[4]]),
            )
        })
        .collect()
}

/// More than eight codes active at once (13: what the board reaches),
/// raised again on every sample (0x1015 = 0): one EMCY per code, never a
/// repeat; each clear sends one error reset with the register that
/// remains; 0x1001 follows throughout.
#[test]
fn emcy_once_per_code_with_thirteen_active() {
    let mut b = Bus::new();
    b.take();
    let codes = codes_active_at_once();
    assert!(codes.len() > 8);
    let reg = codes
        .iter()
        .fold(0u8, |a, &(_, r)| a | r | status::error_register::GENERIC);
    let mut sent = Vec::new();
    // All at once from the first sample (the queue holds them all), then
    // again on every sample, as `publish` does.
    for k in 0..20 {
        for &(c, r) in &codes {
            b.dev.signal_emcy(c, r, [0; 5]);
        }
        assert_eq!(b.dev.error_register(), reg, "sample {k}");
        b.advance(1_000);
        sent.extend(emcys_of(&b.take()));
    }
    let want: Vec<u16> = codes.iter().map(|c| c.0).collect();
    let got: Vec<u16> = sent.iter().map(|e| e.0).collect();
    assert_eq!(got, want, "one EMCY per code");
    assert_eq!(b.read32(0x1001, 0), u32::from(reg));
    for (k, &(c, _)) in codes.iter().enumerate() {
        assert!(b.dev.emcy_active(c), "{c:#06x}");
        assert!(b.dev.clear_emcy(c), "{c:#06x}");
        assert!(!b.dev.clear_emcy(c));
        let left = codes[k + 1..]
            .iter()
            .fold(0u8, |a, &(_, r)| a | r | status::error_register::GENERIC);
        b.advance(1_000);
        assert_eq!(emcys_of(&b.take()), vec![(0, left, c)], "clear {c:#06x}");
        assert_eq!(b.dev.error_register(), left);
    }
    assert_eq!(b.read32(0x1001, 0), 0);
}

/// The device never answers a remote frame, so a TPDO that exists must
/// say "no RTR allowed" (COB-ID bit 30 = 1): a write making a TPDO valid
/// with bit 30 = 0 is refused with 0x06090030 and leaves the value; the
/// defaults (and the EDS) have bit 30 set.
#[test]
fn tpdo_cob_id_without_bit_30_is_refused() {
    let mut b = Bus::new();
    for k in 0..4u16 {
        let id = 0x4000_0000 | (0x180 + 0x100 * u32::from(k) + u32::from(NODE));
        assert_eq!(b.read32(0x1800 + k, 1), id);
        assert_eq!(
            b.write_u32(0x1800 + k, 1, id & !0x4000_0000),
            Err(0x0609_0030)
        );
        assert_eq!(b.read32(0x1800 + k, 1), id, "unchanged");
    }
    b.write_u32(0x1800, 1, 0x8000_0190).unwrap();
    assert_eq!(b.write_u32(0x1800, 1, 0x0000_0190), Err(0x0609_0030));
    assert_eq!(b.read32(0x1800, 1), 0x8000_0190, "unchanged");
    b.write_u32(0x1800, 1, 0x4000_0190).unwrap();
    assert_eq!(b.read32(0x1800, 1), 0x4000_0190);
}

/// More codes than [`MAX_ACTIVE_ERRORS`], raised on every sample while
/// their condition lasts: the first beyond the table is sent (the
/// overflow bucket), the later ones are announced once by
/// [`EMCY_TABLE_FULL`] and show in 0x1001; as conditions end and their
/// codes clear, each suppressed one is sent at its next raise. Over the
/// whole run every code is sent exactly once and every clear of an active
/// code sends one error reset.
#[test]
fn emcy_beyond_the_table_never_floods() {
    use status::error_register as r;
    let mut b = Bus::new();
    b.take();
    let n = MAX_ACTIVE_ERRORS + 3;
    let codes: Vec<(u16, u8)> = (0..n)
        .map(|k| {
            (
                0x5000 + k as u16,
                if k < n - 2 {
                    r::VOLTAGE
                } else {
                    r::TEMPERATURE
                },
            )
        })
        .collect();
    let mut emcys = Vec::new();
    let mut ended = Vec::new();
    let sample = |b: &mut Bus, emcys: &mut Vec<(u16, u8, u16)>, ended: &[u16]| {
        for &(c, reg) in codes.iter().filter(|c| !ended.contains(&c.0)) {
            b.dev.signal_emcy(c, reg, [0; 5]);
        }
        b.advance(1_000);
        emcys.extend(emcys_of(&b.take()));
    };
    for _ in 0..10 {
        sample(&mut b, &mut emcys, &ended);
    }
    let sent: Vec<u16> = emcys.iter().map(|e| e.0).collect();
    let mut want: Vec<u16> = codes[..=MAX_ACTIVE_ERRORS].iter().map(|c| c.0).collect();
    want.push(EMCY_TABLE_FULL);
    assert_eq!(sent, want, "the table and the bucket, once, then 0x6100");
    assert_eq!(emcys.last().unwrap().2, codes[MAX_ACTIVE_ERRORS + 1].0);
    assert_eq!(
        b.dev.error_register(),
        r::GENERIC | r::VOLTAGE | r::TEMPERATURE
    );
    assert!(b.dev.emcy_active(codes[MAX_ACTIVE_ERRORS].0));
    assert!(
        !b.dev.emcy_active(codes[n - 1].0),
        "suppressed, not recorded"
    );
    // Clear the bucket's code, then a recorded one: each suppressed code
    // is sent once at its next raise.
    let mut resets = 0;
    for k in [MAX_ACTIVE_ERRORS, 0] {
        ended.push(codes[k].0);
        assert!(b.dev.clear_emcy(codes[k].0));
        resets += 1;
        for _ in 0..10 {
            sample(&mut b, &mut emcys, &ended);
        }
    }
    let mut sent: Vec<u16> = emcys
        .iter()
        .filter(|e| e.0 != 0 && e.0 != EMCY_TABLE_FULL)
        .map(|e| e.0)
        .collect();
    sent.sort_unstable();
    let want: Vec<u16> = codes.iter().map(|c| c.0).collect();
    assert_eq!(sent, want, "every code once");
    assert_eq!(
        b.dev.error_register(),
        r::GENERIC | r::VOLTAGE | r::TEMPERATURE
    );
    // Clear everything: one error reset per active code, and one for
    // 0x6100 when the last recorded code clears; register 0.
    for &(c, _) in &codes {
        resets += usize::from(b.dev.clear_emcy(c));
    }
    b.advance(1_000);
    emcys.extend(emcys_of(&b.take()));
    assert_eq!(emcys.iter().filter(|e| e.0 == 0).count(), resets + 1);
    assert_eq!(emcys.last().unwrap(), &(0, 0, EMCY_TABLE_FULL));
    assert_eq!(b.dev.error_register(), 0);
}

/// Issue 49, point 4: past the table and the bucket a new code is
/// announced (0x6100 naming it, once, not once per code), and when the
/// bucket's code clears the lost codes' register bits stay in 0x1001
/// while they may still be active; 0x6100 resets once nothing recorded is
/// active.
#[test]
fn codes_past_the_table_and_the_bucket_are_announced_and_keep_their_bits() {
    use status::error_register as r;
    let mut b = Bus::new();
    b.take();
    for k in 0..=MAX_ACTIVE_ERRORS {
        assert!(b.dev.signal_emcy(0x5000 + k as u16, r::VOLTAGE, [0; 5]));
    }
    b.advance(1_000);
    assert_eq!(emcys_of(&b.take()).len(), MAX_ACTIVE_ERRORS + 1);
    // Beyond the bucket: one 0x6100 naming the first lost code.
    assert!(b.dev.signal_emcy(0x4210, r::TEMPERATURE, [0; 5]));
    assert!(
        !b.dev.signal_emcy(0x4210, r::TEMPERATURE, [0; 5]),
        "no repeat"
    );
    assert!(
        !b.dev.signal_emcy(0x4220, r::CURRENT, [0; 5]),
        "announced already"
    );
    b.advance(1_000);
    let reg = r::GENERIC | r::VOLTAGE | r::TEMPERATURE | r::CURRENT;
    assert_eq!(
        emcys_of(&b.take()),
        [(EMCY_TABLE_FULL, reg & !r::CURRENT, 0x4210)]
    );
    assert_eq!(
        b.read32(0x1003, 1),
        0x4210 << 16 | u32::from(EMCY_TABLE_FULL)
    );
    assert_eq!(b.dev.error_register(), reg);
    // The bucket's code clears: the lost bits stay.
    let bucket = 0x5000 + MAX_ACTIVE_ERRORS as u16;
    assert!(b.dev.clear_emcy(bucket));
    b.advance(1_000);
    assert_eq!(emcys_of(&b.take()), [(0, reg, bucket)]);
    assert_eq!(b.dev.error_register(), reg);
    // The bucket is free: the next raise of a lost code is sent as itself.
    assert!(b.dev.signal_emcy(0x4220, r::CURRENT, [0; 5]));
    // Every recorded code clears: 0x6100 resets after the last one.
    for k in 0..MAX_ACTIVE_ERRORS {
        assert!(b.dev.clear_emcy(0x5000 + k as u16));
    }
    assert!(b.dev.clear_emcy(0x4220));
    b.advance(1_000);
    let e = emcys_of(&b.take());
    assert_eq!(e[0].0, 0x4220);
    assert_eq!(e.last().unwrap(), &(0, 0, EMCY_TABLE_FULL));
    assert_eq!(e.len(), 1 + MAX_ACTIVE_ERRORS + 2);
    assert_eq!(b.dev.error_register(), 0);
}

/// Issue 49, point 3: an EMCY raised just before or in stopped is sent
/// at the next pre-operational/operational, so its later error reset is
/// never one for a code the master did not see; a condition that came
/// and went while stopped sends neither.
#[test]
fn emcys_wait_through_stopped() {
    let mut b = Bus::new();
    b.take();
    b.dev.signal_emcy(0x5001, 0x80, [0; 5]);
    b.nmt(0x02, 0);
    b.dev.signal_emcy(0x5002, 0x80, [0; 5]);
    b.dev.signal_emcy(0x5003, 0x80, [0; 5]);
    b.dev.clear_emcy(0x5003);
    b.advance(1_000);
    assert!(emcys_of(&b.take()).is_empty(), "nothing in stopped");
    b.nmt(0x01, 0);
    b.advance(1_000);
    let e = emcys_of(&b.take());
    assert_eq!(e, [(0x5001, 0x81, 0), (0x5002, 0x81, 0)]);
    assert_eq!(b.read32(0x1003, 1) & 0xFFFF, 0x5003, "in the history");
    // Raised before the stop and sent, cleared in stopped: the reset waits.
    b.nmt(0x02, 0);
    b.dev.clear_emcy(0x5001);
    b.advance(1_000);
    assert!(emcys_of(&b.take()).is_empty());
    b.nmt(0x80, 0);
    b.advance(1_000);
    assert_eq!(emcys_of(&b.take()), [(0, 0x81, 0x5001)]);
}

/// The calibration stamp 0x2011: sub 1/2 written like calibration (pre-op
/// and unlocked), sub 3 read-only; stored with the application group, the
/// count one higher per store (in the image too); 0x1011 clears all three
/// at the next reset node.
#[test]
fn calibration_stamp_is_written_counted_stored_and_restored() {
    let mut b = Bus::new();
    assert_eq!(b.read32(0x2011, 0), 3);
    assert_eq!(b.write_u32(0x2011, 1, 0xA1B2_C3D4), Err(0x0800_0021));
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_u32(0x2011, 1, 0xA1B2_C3D4).unwrap();
    b.write_u32(0x2011, 2, 1_795_777_123).unwrap();
    assert_eq!(b.write_u32(0x2011, 3, 7), Err(0x0601_0002));
    assert_eq!(b.read32(0x2011, 1), 0xA1B2_C3D4);
    assert_eq!(b.read32(0x2011, 3), 0);
    // a communication-group store neither stores nor counts it
    assert_eq!(b.write_u32(0x1010, 2, od::SAVE_SIGNATURE), Err(0));
    b.finish(true);
    assert_eq!(b.read32(0x2011, 3), 0);
    // stores of the application group (sub 3, then sub 1) count
    let pos = od::entries()
        .filter(|(_, _, e)| e.persist)
        .position(|(_, i, e)| i == 0x2011 && e.sub == 3)
        .unwrap();
    let mut img = [0u8; IMAGE_LEN];
    for (n, sub) in [(1, 3), (2, 1)] {
        assert_eq!(b.write_u32(0x1010, sub, od::SAVE_SIGNATURE), Err(0));
        // the image to store holds this store already
        b.dev.persistent_image(&mut img);
        assert_eq!(img[8 + 4 * pos..12 + 4 * pos], u32::to_le_bytes(n));
        b.finish(true);
        assert_eq!(b.read32(0x2011, 3), n);
    }
    // a failed store counts nothing
    assert_eq!(b.write_u32(0x1010, 3, od::SAVE_SIGNATURE), Err(0));
    b.finish(false);
    assert_eq!(b.read32(0x2011, 3), 2);
    // an unsaved change goes at the reset node, the stored stamp comes back
    b.write_u32(0x2011, 1, 5).unwrap();
    b.nmt(0x81, 0);
    b.poll();
    assert_eq!(
        [1, 2, 3].map(|s| b.read32(0x2011, s)),
        [0xA1B2_C3D4, 1_795_777_123, 2]
    );
    let mut d = Device::new(NODE, &Defaults::nominal());
    d.load_image(&img).unwrap();
    let stamp: Vec<u32> = (1..=3).map(|s| d.core.get(0x2011, s)).collect();
    assert_eq!(stamp, [0xA1B2_C3D4, 1_795_777_123, 2]);
    // refused in operational
    b.nmt(0x01, 0);
    assert_eq!(b.write_u32(0x2011, 1, 1), Err(0x0800_0022));
    assert_eq!(b.write_u32(0x2011, 2, 1), Err(0x0800_0022));
    b.nmt(0x80, 0);
    // restore of the application group: all 0 from the next reset node
    assert_eq!(b.write_u32(0x1011, 3, od::LOAD_SIGNATURE), Err(0));
    b.finish(true);
    assert_eq!(b.read32(0x2011, 3), 2);
    b.nmt(0x81, 0);
    b.poll();
    assert_eq!([1, 2, 3].map(|s| b.read32(0x2011, s)), [0, 0, 0]);
}

/// An image written before layout 7 (no 0x2011) loads with a zero stamp;
/// the next store counts from there.
#[test]
fn layout_6_image_loads_with_a_zero_stamp() {
    let mut b = Bus::new();
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_f32(0x2105, 0, 300.0).unwrap();
    b.write_u32(0x2011, 1, 0xDEAD_BEEF).unwrap();
    let (img, old, n) = image_and_layout(&b, 6);
    assert_eq!(n, IMAGE_LEN_V6);
    assert_eq!(IMAGE_LEN_V7 - IMAGE_LEN_V6, 3 * 4);
    let mut b = Bus::new();
    b.dev.load_image(&old[..n]).unwrap();
    assert_eq!(b.dev.thermal_tau_s(), 300.0);
    assert_eq!([1, 2, 3].map(|s| b.read32(0x2011, s)), [0, 0, 0]);
    assert_eq!(b.write_u32(0x1010, 1, od::SAVE_SIGNATURE), Err(0));
    b.finish(true);
    assert_eq!(b.read32(0x2011, 3), 1);
    // a layout-6 signature over a layout-7 length is refused
    let mut forged = img;
    forged[0..4].copy_from_slice(&old[0..4]);
    assert_eq!(b.dev.load_image(&forged), Err(Error::ImageLayout));
}

/// The device's current image and the same values in the image of the
/// older layout `layout` (its length `n`), as older firmware stored them.
fn image_and_layout(b: &Bus, layout: u8) -> ([u8; IMAGE_LEN], [u8; IMAGE_LEN], usize) {
    let mut img = [0u8; IMAGE_LEN];
    b.dev.persistent_image(&mut img);
    let mut old = [0u8; IMAGE_LEN];
    let n = image_as_layout(&img, layout, &mut old);
    (img, old, n)
}

/// Spot coefficients used below [mm per unit of tan²γ]: exact in `f32`.
const SPOT: [f32; 2] = [0.375, -1.25];

/// The spot coefficients (0x2101..0x2104 sub 24/25) go in and out by SDO
/// bit for bit and reach the typed view and the stored record the device
/// describes, over a base record whose own spot terms are different.
#[test]
fn spot_terms_round_trip_through_sdo_into_params() {
    let mut b = Bus::new();
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    for (k, v) in SPOT.iter().enumerate() {
        b.write_f32(0x2102, CAL_SUB_SPOT + k as u8, *v).unwrap();
        let got = b.upload(0x2102, CAL_SUB_SPOT + k as u8).unwrap();
        assert_eq!(got, v.to_le_bytes().to_vec(), "sub {}", 24 + k);
    }
    assert_eq!(b.dev.calibration(1).unwrap().spot, SPOT);
    assert_eq!(b.dev.calibration(0).unwrap().spot, [0.0; 2]);
    let mut base = perpend_core::params::Params::factory();
    for s in base.head.sensors.iter_mut() {
        s.ext.spot = [2.0, 3.0];
    }
    let p = b.dev.params(&base);
    assert_eq!(p.head.sensors[1].ext.spot, SPOT);
    // the objects are the truth: a zero object clears the base's terms
    assert_eq!(p.head.sensors[0].ext.spot, [0.0; 2]);
    assert!(p.validate().is_ok());
    // and a record with spot terms loads into the objects
    let mut d = Bus::new();
    d.dev.load_params(&base).unwrap();
    assert_eq!(d.dev.calibration(3).unwrap().spot, [2.0, 3.0]);
}

/// A spot coefficient beyond ±10 mm (the stored record's bound) or not
/// finite is refused on write with the per-entry limit aborts, the value
/// unchanged.
#[test]
fn spot_terms_out_of_bounds_are_refused() {
    let mut b = Bus::new();
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_f32(0x2101, 24, 9.5).unwrap();
    assert_eq!(b.write_f32(0x2101, 24, 10.5), Err(0x0609_0031));
    assert_eq!(b.write_f32(0x2101, 25, -10.5), Err(0x0609_0032));
    assert!(b.write_f32(0x2101, 25, f32::NAN).is_err());
    assert_eq!(b.dev.calibration(0).unwrap().spot, [9.5, 0.0]);
    let mut p = perpend_core::params::Params::factory();
    p.head.sensors[0].ext.spot = [0.0, 10.5];
    assert_eq!(
        b.dev.load_params(&p),
        Err(Error::Value {
            index: 0x2101,
            sub: 25
        })
    );
}

/// An image written before layout 8 (no spot objects) loads; the spot
/// coefficients keep their current values (those of the stored record
/// the board loaded first).
#[test]
fn layout_7_image_loads_keeping_the_spot_terms() {
    let mut b = Bus::new();
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_f32(0x2104, 1, 51.0).unwrap();
    b.write_f32(0x2104, 24, 4.0).unwrap();
    let (_, old, n) = image_and_layout(&b, 7);
    assert_eq!((n, IMAGE_LEN - n), (IMAGE_LEN_V7, 8 * 4));
    let mut base = perpend_core::params::Params::factory();
    base.head.sensors[3].ext.spot = [SPOT[0], SPOT[1]];
    let mut b = Bus::new();
    b.dev.load_params(&base).unwrap();
    b.dev.load_image(&old[..n]).unwrap();
    let c = b.dev.calibration(3).unwrap();
    assert_eq!((c.zero[0], c.spot), (51.0, SPOT));
}

/// CiA 302-3 program download through the device: 0x1F50 by block
/// download reaches the application as parts, 0x1F51 as a request,
/// 0x1F56/0x1F57 read what the application set; pre-operational only.
#[cfg(feature = "sdo-block")]
#[test]
fn program_download_objects() {
    let mut b = Bus::new();
    let data: Vec<u8> = (0..20u8).map(|i| i * 7 + 1).collect();
    let crc = crate::sdo::block::crc16_ccitt(&data, 0).to_le_bytes();
    let r = b.sdo([0xC6, 0x50, 0x1F, 1, 20, 0, 0, 0]).unwrap();
    assert_eq!(r[..5], [0xA4, 0x50, 0x1F, 1, 127]);
    for (k, chunk) in data.chunks(7).enumerate() {
        let mut f = [0u8; 8];
        f[0] = (k + 1) as u8 | if k == 2 { 0x80 } else { 0 };
        f[1..1 + chunk.len()].copy_from_slice(chunk);
        let r = b.sdo(f);
        assert_eq!(r.is_some(), k == 2, "answered at the last segment");
    }
    // 21 bytes sent, 1 unused: the part goes to the application.
    assert_eq!(b.sdo([0xC5, crc[0], crc[1], 0, 0, 0, 0, 0]), None);
    let want = Request::ProgramData {
        offset: 0,
        len: 20,
        last: true,
    };
    assert_eq!(b.dev.pending_request(), Some(want));
    assert_eq!(b.dev.program_part(), &data[..]);
    let out = b.finish(true);
    assert_eq!(out[0].data[0], 0xA1);
    assert!(b.dev.program_part().is_empty());
    // Program control: carried out by the application, then reads back.
    assert_eq!(b.download(0x1F51, 1, &[1]), Err(0));
    assert_eq!(b.dev.pending_request(), Some(Request::ProgramControl(1)));
    b.finish(true);
    assert_eq!(b.read32(0x1F51, 1), 1);
    assert_eq!(b.download(0x1F51, 1, &[4]), Err(0x0609_0031));
    // Identification and flash status as the application set them.
    b.dev.set_program_status(0x1234_5678, od::FLASH_NO_PROGRAM);
    assert_eq!(b.read32(0x1F56, 1), 0x1234_5678);
    assert_eq!(b.read32(0x1F57, 1), 2);
    assert_eq!(b.upload(0x1F50, 1), Err(0x0601_0001));
    // Operational: refused.
    b.nmt(0x01, 0);
    let r = b.sdo([0xC6, 0x50, 0x1F, 1, 20, 0, 0, 0]).unwrap();
    assert_eq!(u32::from_le_bytes([r[4], r[5], r[6], r[7]]), 0x0800_0022);
}

/// Every object [`Objects`] reads, of two views.
fn objects_eq(a: &Objects<'_>, b: &Objects<'_>) {
    for i in 0..4 {
        assert_eq!(a.calibration(i), b.calibration(i), "0x{:04X}", 0x2101 + i);
        assert_eq!(a.transfer(i), b.transfer(i), "0x{:04X}", 0x2201 + i);
    }
    assert_eq!(a.surface(), b.surface());
    assert_eq!(a.acquisition(), b.acquisition());
    assert_eq!(a.communication(), b.communication());
    assert_eq!(a.thermal_tau_s().to_bits(), b.thermal_tau_s().to_bits());
    assert_eq!(a.node_id(), b.node_id());
}

#[test]
fn staged_objects_are_those_of_a_device_that_loaded_the_image() {
    // A device whose stored image differs from its current values in
    // calibration, acquisition and node-id, as a store of the
    // application group would leave it (issue 50 item 6: the record is
    // derived from these objects, without a copy of the device).
    let mut b = Bus::new();
    b.write_u32(0x2010, 0, od::UNLOCK_SIGNATURE).unwrap();
    b.write_f32(0x2102, 3, -4.25).unwrap();
    b.write_u32(0x2300, 1, 4000).unwrap();
    b.download(0x2400, 1, &[0x22]).unwrap();
    assert_eq!(b.write_u32(0x1010, 3, od::SAVE_SIGNATURE), Err(0));
    let mut img = [0u8; IMAGE_LEN];
    b.dev.persistent_image(&mut img);
    let mut buf = [0u32; ENTRIES];
    let staged = b.dev.staged_objects(&img, &mut buf).unwrap();
    let mut copy = b.dev.clone();
    copy.load_image(&img).unwrap();
    objects_eq(&staged, &copy.objects());
    // The application group is stored, 0x2400 with it: staged, the
    // configured node-id is the active one; the device itself is
    // unchanged.
    assert_eq!(staged.node_id(), 0x22);
    assert_eq!(b.dev.node_id(), NODE);
    assert_eq!(staged.acquisition().period_us, 4000);
    // A non-configured node (0xFF) keeps the active node-id, as a load
    // does.
    let d = Device::new(crate::lss::UNCONFIGURED, &Defaults::nominal());
    d.persistent_image(&mut img);
    let staged = d.staged_objects(&img, &mut buf).unwrap();
    let mut copy = d.clone();
    copy.load_image(&img).unwrap();
    objects_eq(&staged, &copy.objects());
    // A bad image is refused as `load_image` refuses it.
    let mut bad = img;
    bad[0] ^= 1;
    assert_eq!(
        d.staged_objects(&bad, &mut buf).map(|_| ()),
        copy.load_image(&bad)
    );
}

#[test]
fn a_device_built_in_place_or_reinitialised_is_a_new_one() {
    let new = Device::new(NODE, &Defaults::nominal());
    let mut slot = MaybeUninit::uninit();
    let placed = Device::init(&mut slot, NODE, &Defaults::nominal());
    let mut a = [0u8; IMAGE_LEN];
    let mut b = [0u8; IMAGE_LEN];
    new.persistent_image(&mut a);
    placed.persistent_image(&mut b);
    assert_eq!(a, b);
    assert_eq!(placed.core.values, new.core.values);
    assert_eq!(placed.core.boot, new.core.boot);
    assert_eq!(placed.sdo, new.sdo);
    // A device that booted, was configured and is mid-transfer, reset in
    // place: the same as a new one (state, values, SDO server).
    let mut bus = Bus::new();
    bus.write_u32(0x2300, 1, 9000).unwrap();
    bus.nmt(0x01, 0);
    // A segmented upload of the device name (0x1008) left open.
    bus.sdo([0x40, 0x08, 0x10, 0, 0, 0, 0, 0]);
    assert_ne!(bus.dev.sdo, new.sdo);
    bus.dev.reinit(NODE, &Defaults::nominal());
    assert_eq!(bus.dev.nmt_state(), NmtState::Initialising);
    assert_eq!(bus.dev.core.values, new.core.values);
    assert_eq!(bus.dev.sdo, new.sdo);
    assert_eq!(bus.dev.lss, new.lss);
    assert_eq!(bus.dev.config_generation(), new.config_generation());
}

/// The resolved mapping a SYNC uses follows a remap made after TPDOs were
/// sent (the cache of issue 50 item 8 is keyed by the mapping words).
#[test]
fn a_remap_after_sending_is_followed() {
    let mut b = Bus::new();
    b.nmt(0x01, 0);
    b.dev.set_measurement(&sample());
    let before = b.sync();
    assert_eq!(before[0].id, 0x190);
    assert_eq!(before[0].len, 8);
    b.nmt(0x80, 0);
    b.write_u32(0x1800, 1, 0x8000_0190).unwrap();
    b.download(0x1A00, 0, &[0]).unwrap();
    b.write_u32(0x1A00, 1, od::mapping(0x2004, 1, 32)).unwrap();
    b.download(0x1A00, 0, &[1]).unwrap();
    b.write_u32(0x1800, 1, 0x4000_0190).unwrap();
    b.nmt(0x01, 0);
    let after = b.sync();
    assert_eq!(after[0].id, 0x190);
    assert_eq!(after[0].len, 4);
    assert_eq!(after[0].payload(), &40.0f32.to_le_bytes());
}

#[test]
fn any_emcy_active_follows_raise_and_clear() {
    let mut d = Device::new(NODE, &Defaults::nominal());
    assert!(!d.any_emcy_active());
    d.signal_emcy(0x2111, error_register::CURRENT, [1, 0, 0, 0, 0]);
    assert!(d.any_emcy_active());
    d.clear_emcy(0x2111);
    assert!(!d.any_emcy_active());
}
