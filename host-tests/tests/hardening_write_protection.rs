//! Write protection (issue 7 item 4): the obvious attacks on the
//! calibration and configuration objects, through the CANopen device
//! (`perpend_can::Device`) and the board application
//! (`perpend_board::app::App`). Every refused write must be an SDO abort
//! with the CiA 301 code of the contract (`perpend_can` crate docs: order
//! object → sub-index → access → length → state → lock → value) and leave
//! the whole dictionary unchanged (a full dump of every entry, the unlock
//! flag and the pending store request compared before and after), and on
//! the board nothing reaches the pipeline or the flash.
#![allow(missing_docs, clippy::unwrap_used, clippy::panic)]

use perpend_board::app::App;
use perpend_board::storage::{host_store, HostFlash, SeqStore};
use perpend_can::od::UNLOCK_SIGNATURE;
use perpend_can::od::{self, Access, Class, DataType, Limits, LOAD_SIGNATURE, SAVE_SIGNATURE};
use perpend_can::{Defaults, Device, Frame, NmtState};

const NODE: u8 = 0x10;

const TOGGLE: u32 = 0x0503_0000;
const TIMEOUT: u32 = 0x0504_0000;
const COMMAND: u32 = 0x0504_0001;
const READ_ONLY: u32 = 0x0601_0002;
const NO_OBJECT: u32 = 0x0602_0000;
const NOT_MAPPABLE: u32 = 0x0604_0041;
const PDO_LENGTH: u32 = 0x0604_0042;
const LENGTH: u32 = 0x0607_0010;
const TOO_LONG: u32 = 0x0607_0012;
const TOO_SHORT: u32 = 0x0607_0013;
const NO_SUB: u32 = 0x0609_0011;
const RANGE: u32 = 0x0609_0030;
const TOO_HIGH: u32 = 0x0609_0031;
const TOO_LOW: u32 = 0x0609_0032;
const STORE: u32 = 0x0800_0020;
const LOCKED: u32 = 0x0800_0021;
const STATE: u32 = 0x0800_0022;

/// Everything a write could change: every entry's value (strings by
/// content), the unlock flag, the pending store/restore request and the
/// persistence image.
#[derive(Debug, Clone, PartialEq)]
struct Dump {
    values: Vec<(u16, u8, Result<u32, String>)>,
    unlocked: bool,
    request: Option<perpend_can::Request>,
    image: Vec<u8>,
}

fn dump(d: &Device) -> Dump {
    let values = od::entries()
        // The uptime (0x200C) is a clock: it moves by itself.
        .filter(|(_, index, _)| *index != 0x200C)
        .map(|(_, index, e)| {
            let v = match e.ty {
                DataType::VisibleString => Err(d.read_str(index, e.sub).unwrap().to_string()),
                _ => Ok(d.read_u32(index, e.sub).unwrap()),
            };
            (index, e.sub, v)
        })
        .collect();
    let mut image = [0u8; perpend_can::IMAGE_LEN];
    d.persistent_image(&mut image);
    Dump {
        values,
        unlocked: d.calibration_unlocked(),
        request: d.pending_request(),
        image: image.to_vec(),
    }
}

/// SDO response: `Ok(payload)` or `Err(abort code)`; the abort's index and
/// sub-index are returned too.
type Resp = Result<[u8; 8], (u32, u16, u8)>;

fn decode(r: [u8; 8]) -> Resp {
    if r[0] == 0x80 {
        Err((
            u32::from_le_bytes([r[4], r[5], r[6], r[7]]),
            u16::from_le_bytes([r[1], r[2]]),
            r[3],
        ))
    } else {
        Ok(r)
    }
}

/// A device on a simulated bus with its own clock.
struct Bus {
    dev: Device,
    now: u64,
}

impl Bus {
    fn new() -> Self {
        let mut b = Self {
            dev: Device::new(NODE, &Defaults::nominal()),
            now: 0,
        };
        b.poll();
        assert_eq!(b.dev.nmt_state(), NmtState::PreOperational);
        b
    }

    fn poll(&mut self) -> Vec<Frame> {
        let mut v = Vec::new();
        self.dev.poll(self.now, &mut |f| v.push(f));
        v
    }

    fn send(&mut self, f: Frame) -> Vec<Frame> {
        self.now += 100;
        let mut v = Vec::new();
        self.dev.handle(&f, self.now, &mut |f| v.push(f));
        v
    }

    fn nmt(&mut self, cs: u8) {
        self.send(Frame::new(0, &[cs, NODE]));
        self.poll(); // boot-up after a reset
    }

    /// One SDO request; `None` when the device does not answer.
    fn sdo(&mut self, req: [u8; 8]) -> Option<Resp> {
        let out = self.send(Frame::new(0x600 + NODE as u16, &req));
        let r: Vec<&Frame> = out.iter().filter(|f| f.id == 0x580 + NODE as u16).collect();
        assert!(r.len() <= 1, "one answer per request");
        r.first().map(|f| {
            assert_eq!(f.len, 8);
            decode(f.data)
        })
    }

    /// Expedited download of `data` (1..=4 bytes, size indicated). A store
    /// or restore is completed by the "application" at once (`ok`).
    fn write(&mut self, index: u16, sub: u8, data: &[u8]) -> Resp {
        let n = data.len();
        assert!((1..=4).contains(&n));
        let i = index.to_le_bytes();
        let mut req = [0x23 | (((4 - n) as u8) << 2), i[0], i[1], sub, 0, 0, 0, 0];
        req[4..4 + n].copy_from_slice(data);
        match self.sdo(req) {
            Some(r) => r,
            None => {
                assert!(
                    self.dev.pending_request().is_some(),
                    "no answer to {req:02x?}"
                );
                let mut out = Vec::new();
                self.dev.finish_request(true, &mut |f| out.push(f)).unwrap();
                decode(out[0].data)
            }
        }
    }

    fn write_u32(&mut self, index: u16, sub: u8, v: u32) -> Resp {
        self.write(index, sub, &v.to_le_bytes())
    }

    fn write_typed(&mut self, index: u16, sub: u8, ty: DataType, v: u32) -> Resp {
        let n = match ty {
            DataType::VisibleString => 4,
            t => t.size(),
        };
        self.write(index, sub, &v.to_le_bytes()[..n])
    }

    fn unlock(&mut self) {
        self.write_u32(0x2010, 0, UNLOCK_SIGNATURE).unwrap();
        assert!(self.dev.calibration_unlocked());
    }

    /// Initiates a segmented download (`size`: indicated size, if any).
    fn initiate(&mut self, index: u16, sub: u8, size: Option<u32>) -> Option<Resp> {
        let i = index.to_le_bytes();
        let (cmd, s) = match size {
            Some(s) => (0x21, s.to_le_bytes()),
            None => (0x20, [0; 4]),
        };
        self.sdo([cmd, i[0], i[1], sub, s[0], s[1], s[2], s[3]])
    }

    /// One download segment of `data` (0..=7 bytes).
    fn segment(&mut self, toggle: bool, data: &[u8], last: bool) -> Option<Resp> {
        let n = data.len();
        let mut req = [0u8; 8];
        req[0] = (u8::from(toggle) << 4) | (((7 - n) as u8) << 1) | u8::from(last);
        req[1..1 + n].copy_from_slice(data);
        self.sdo(req)
    }
}

/// Asserts `r` is the abort `code` for `(index, sub)`.
#[track_caller]
fn assert_abort(r: Option<Resp>, code: u32, index: u16, sub: u8) {
    match r {
        Some(Err((c, i, s))) => {
            assert_eq!(
                (c, i, s),
                (code, index, sub),
                "abort {c:#010x} for {i:#06x}/{s}, expected {code:#010x} for {index:#06x}/{sub}"
            );
        }
        other => panic!("expected abort {code:#010x} for {index:#06x}/{sub}, got {other:02x?}"),
    }
}

/// Runs `attack`, which must be refused with `code` (checked by the
/// closure's own return), and checks the dump is unchanged.
#[track_caller]
fn refused(
    b: &mut Bus,
    code: u32,
    index: u16,
    sub: u8,
    attack: impl FnOnce(&mut Bus) -> Option<Resp>,
) {
    let before = dump(&b.dev);
    let r = attack(b);
    assert_abort(r, code, index, sub);
    assert_eq!(
        dump(&b.dev),
        before,
        "{index:#06x}/{sub}: a refused write changed the dictionary"
    );
}

fn calibration_entries() -> Vec<(u16, &'static od::Entry)> {
    od::entries()
        .filter(|(_, _, e)| e.class == Class::Calibration)
        .map(|(_, i, e)| (i, e))
        .collect()
}

fn config_entries() -> Vec<(u16, &'static od::Entry)> {
    od::entries()
        .filter(|(_, _, e)| e.class == Class::Config)
        .map(|(_, i, e)| (i, e))
        .collect()
}

/// A valid value different from the current one (so that an accepted
/// write would show in the dump).
fn valid_other(b: &Bus, index: u16, e: &od::Entry) -> u32 {
    let cur = b.dev.read_u32(index, e.sub).unwrap();
    let candidates: Vec<u32> = match e.limits {
        Limits::Real(lo, hi) => vec![
            (0.5 * (lo + hi)).to_bits(),
            (0.25 * lo + 0.75 * hi).to_bits(),
        ],
        Limits::Range(lo, hi) => vec![lo, hi],
        Limits::OneOf(set) => set.to_vec(),
        Limits::PowerOfTwo(lo, hi) => vec![lo, hi],
        Limits::Any => vec![cur ^ 1],
    };
    candidates.into_iter().find(|&v| v != cur).unwrap()
}

// ---------------------------------------------------------------------------

#[test]
fn calibration_in_operational_is_refused_even_unlocked() {
    let mut b = Bus::new();
    b.unlock();
    b.nmt(0x01);
    assert_eq!(b.dev.nmt_state(), NmtState::Operational);
    // the state change cleared the unlock; the state is reported first
    assert!(!b.dev.calibration_unlocked());
    for (index, e) in calibration_entries() {
        let v = valid_other(&b, index, e);
        refused(&mut b, STATE, index, e.sub, |b| {
            Some(b.write_typed(index, e.sub, e.ty, v))
        });
    }
    // and the unlock itself cannot be written in operational
    refused(&mut b, STATE, 0x2010, 0, |b| {
        Some(b.write_u32(0x2010, 0, UNLOCK_SIGNATURE))
    });
    for (index, e) in config_entries() {
        let v = valid_other(&b, index, e);
        refused(&mut b, STATE, index, e.sub, |b| {
            Some(b.write_typed(index, e.sub, e.ty, v))
        });
    }
}

#[test]
fn calibration_without_unlock_is_refused() {
    let mut b = Bus::new();
    for (index, e) in calibration_entries() {
        let v = valid_other(&b, index, e);
        refused(&mut b, LOCKED, index, e.sub, |b| {
            Some(b.write_typed(index, e.sub, e.ty, v))
        });
    }
    // a wrong unlock value is refused and unlocks nothing
    for v in [
        0x6C61_6374,
        1,
        u32::MAX,
        SAVE_SIGNATURE,
        UNLOCK_SIGNATURE.swap_bytes(),
    ] {
        refused(&mut b, RANGE, 0x2010, 0, |b| {
            Some(b.write_u32(0x2010, 0, v))
        });
        assert_abort(
            Some(b.write_u32(0x2101, 1, 1.0f32.to_bits())),
            LOCKED,
            0x2101,
            1,
        );
    }
    // the unlock value with a wrong length
    refused(&mut b, TOO_SHORT, 0x2010, 0, |b| {
        Some(b.write(0x2010, 0, &UNLOCK_SIGNATURE.to_le_bytes()[..2]))
    });
}

#[test]
fn unlock_does_not_survive_any_state_change_or_reset() {
    // (command, whether the device boots again)
    for cs in [0x01u8, 0x02, 0x81, 0x82] {
        let mut b = Bus::new();
        b.unlock();
        b.nmt(cs);
        if matches!(cs, 0x01 | 0x02) {
            b.nmt(0x80); // back to pre-operational
        }
        assert_eq!(b.dev.nmt_state(), NmtState::PreOperational, "after {cs:#x}");
        assert!(!b.dev.calibration_unlocked(), "unlock survived NMT {cs:#x}");
        assert_eq!(b.dev.read_u32(0x2010, 0), Some(0));
        for (index, e) in calibration_entries() {
            let v = valid_other(&b, index, e);
            refused(&mut b, LOCKED, index, e.sub, |b| {
                Some(b.write_typed(index, e.sub, e.ty, v))
            });
        }
    }
    // "enter pre-operational" while pre-operational is not a state change:
    // the unlock stays (CiA 301: no transition)
    let mut b = Bus::new();
    b.unlock();
    b.nmt(0x80);
    assert!(b.dev.calibration_unlocked());
    // explicit lock
    b.write_u32(0x2010, 0, 0).unwrap();
    refused(&mut b, LOCKED, 0x2102, 7, |b| {
        Some(b.write_u32(0x2102, 7, 40.0f32.to_bits()))
    });
    // stopped: no SDO at all, nothing changes
    b.unlock();
    b.nmt(0x02);
    let before = dump(&b.dev);
    assert_eq!(b.sdo([0x23, 0x01, 0x21, 1, 0, 0, 0x80, 0x3F]), None);
    assert_eq!(dump(&b.dev), before);
}

/// Values just outside an entry's limits, with the abort each must get.
fn outside(e: &od::Entry) -> Vec<(u32, u32)> {
    let type_max: u64 = match e.ty {
        DataType::U8 => 0xFF,
        DataType::U16 => 0xFFFF,
        _ => 0xFFFF_FFFF,
    };
    let mut v = Vec::new();
    match e.limits {
        Limits::Any => {}
        Limits::Range(lo, hi) => {
            if lo > 0 {
                v.push((lo - 1, TOO_LOW));
                v.push((0, TOO_LOW));
            }
            if (hi as u64) < type_max {
                v.push((hi + 1, TOO_HIGH));
                v.push((type_max as u32, TOO_HIGH));
            }
        }
        Limits::Real(lo, hi) => {
            for bits in [0x7FC0_0000u32, 0xFFC0_0000, 0x7F80_0001, 0x7FFF_FFFF] {
                v.push((bits, RANGE)); // NaNs: quiet, negative, signalling
            }
            v.push((f32::INFINITY.to_bits(), RANGE));
            v.push((f32::NEG_INFINITY.to_bits(), RANGE));
            v.push((f32::MAX.to_bits(), TOO_HIGH));
            v.push((f32::MIN.to_bits(), TOO_LOW));
            let below = lo - lo.abs().max(1.0) * 1e-3;
            let above = hi + hi.abs().max(1.0) * 1e-3;
            v.push((below.to_bits(), TOO_LOW));
            v.push((above.to_bits(), TOO_HIGH));
        }
        Limits::OneOf(set) => {
            let max = *set.iter().max().unwrap();
            for x in [
                max as u64 + 1,
                type_max,
                (set[0] as u64 + 1) % (type_max + 1),
            ] {
                if !set.contains(&(x as u32)) {
                    v.push((x as u32, RANGE));
                }
            }
        }
        Limits::PowerOfTwo(lo, hi) => {
            v.push((0, RANGE));
            v.push((3, RANGE));
            v.push((hi - 1, RANGE));
            if (hi as u64) * 2 <= type_max {
                v.push((hi * 2, TOO_HIGH));
            }
            if lo > 1 {
                v.push((lo / 2, TOO_LOW));
            }
        }
    }
    v
}

#[test]
fn out_of_range_values_for_every_calibration_and_config_object() {
    let mut b = Bus::new();
    b.unlock();
    let mut n = 0;
    for (index, e) in calibration_entries().into_iter().chain(config_entries()) {
        if index == 0x2011 {
            continue; // the calibration stamp: any UNSIGNED32 is a hash or a time
        }
        let cases = outside(e);
        assert!(!cases.is_empty(), "{index:#06x}/{} has no limits", e.sub);
        for (v, code) in cases {
            refused(&mut b, code, index, e.sub, |b| {
                Some(b.write_typed(index, e.sub, e.ty, v))
            });
            n += 1;
        }
        assert!(b.dev.calibration_unlocked());
    }
    assert!(n > 600, "{n} cases");
    eprintln!("{n} out-of-range writes refused, dictionary unchanged after each");
    // The limits themselves, written out (the contract of the crate docs),
    // so a laxer table cannot pass the loop above unnoticed.
    let explicit: &[(u16, u8, &[u8], u32)] = &[
        (0x2300, 1, &99u32.to_le_bytes(), TOO_LOW),
        (0x2300, 1, &100_001u32.to_le_bytes(), TOO_HIGH),
        (0x2300, 2, &0u16.to_le_bytes(), RANGE),
        (0x2300, 2, &48u16.to_le_bytes(), RANGE),
        (0x2300, 2, &512u16.to_le_bytes(), TOO_HIGH),
        (0x2300, 3, &[2], RANGE),
        (0x2300, 4, &0.0f32.to_le_bytes(), TOO_LOW),
        (0x2300, 4, &(-1.0f32).to_le_bytes(), TOO_LOW),
        (0x2300, 4, &100.5f32.to_le_bytes(), TOO_HIGH),
        (0x2300, 4, &f32::NAN.to_le_bytes(), RANGE),
        (0x2400, 1, &[0], TOO_LOW),
        (0x2400, 1, &[128], TOO_HIGH),
        (0x2400, 2, &300u16.to_le_bytes(), RANGE),
        (0x2400, 2, &0u16.to_le_bytes(), RANGE),
        (0x2400, 2, &2000u16.to_le_bytes(), RANGE),
        (0x2201, 1, &[2], RANGE),
        (0x2204, 1, &[0xFF], RANGE),
        (0x2202, 2, &0.0f32.to_le_bytes(), TOO_LOW),
        (0x2203, 2, &f32::INFINITY.to_le_bytes(), RANGE),
        (0x2101, 4, &1.5f32.to_le_bytes(), TOO_HIGH),
        (0x2102, 7, &(-0.5f32).to_le_bytes(), TOO_LOW),
        (0x2103, 8, &f32::NAN.to_le_bytes(), RANGE),
        (0x2104, 14, &(-60.0f32).to_le_bytes(), TOO_LOW),
        // a wrong unlock value while unlocked: refused, still unlocked
        (0x2010, 0, &1u32.to_le_bytes(), RANGE),
    ];
    for &(index, sub, data, code) in explicit {
        refused(&mut b, code, index, sub, |b| {
            Some(b.write(index, sub, data))
        });
    }
    assert!(b.dev.calibration_unlocked());
}

#[test]
fn nan_and_infinity_into_every_real32_calibration_object() {
    let mut b = Bus::new();
    b.unlock();
    let nans = [
        f32::NAN.to_bits(),
        0x7F80_0001, // signalling NaN
        0xFF80_0001,
        0x7FC0_1234, // NaN with payload
        0xFFFF_FFFF,
        f32::INFINITY.to_bits(),
        f32::NEG_INFINITY.to_bits(),
    ];
    let reals: Vec<_> = calibration_entries()
        .into_iter()
        .filter(|(_, e)| e.ty == DataType::Real32)
        .collect();
    // 0x2101..0x2104 sub 1..25, 0x2105 (thermal time constant), 0x2201..0x2204 sub 2..4
    assert_eq!(reals.len(), 4 * 25 + 1 + 4 * 3);
    for (index, e) in reals {
        for v in nans {
            refused(&mut b, RANGE, index, e.sub, |b| {
                Some(b.write_u32(index, e.sub, v))
            });
            // and through a segmented download
            refused(&mut b, RANGE, index, e.sub, |b| {
                assert_eq!(b.initiate(index, e.sub, Some(4)).unwrap().unwrap()[0], 0x60);
                b.segment(false, &v.to_le_bytes(), true)
            });
        }
    }
    // no NaN anywhere in the dictionary
    for (_, index, e) in od::entries() {
        if e.ty == DataType::Real32 {
            assert!(b.dev.read_f32(index, e.sub).unwrap().is_finite());
        }
    }
}

#[test]
fn writes_to_read_only_objects_are_refused() {
    let mut b = Bus::new();
    b.unlock();
    let ro: Vec<_> = od::entries()
        .filter(|(_, _, e)| !matches!(e.access, Access::Rw | Access::Wo))
        .map(|(_, i, e)| (i, e))
        .collect();
    assert!(ro.len() > 40);
    for state in [0x80u8, 0x01] {
        b.nmt(state);
        for &(index, e) in &ro {
            for v in [0u32, 1, 0xFFFF_FFFF] {
                refused(&mut b, READ_ONLY, index, e.sub, |b| {
                    Some(b.write_typed(index, e.sub, e.ty, v))
                });
            }
            // segmented, too (checked at the initiate)
            refused(&mut b, READ_ONLY, index, e.sub, |b| {
                b.initiate(index, e.sub, Some(4))
            });
            refused(&mut b, READ_ONLY, index, e.sub, |b| {
                b.initiate(index, e.sub, None)
            });
        }
    }
    // objects and sub-indices that do not exist
    refused(&mut b, NO_OBJECT, 0x2600, 0, |b| {
        Some(b.write_u32(0x2600, 0, 1))
    });
    refused(&mut b, NO_OBJECT, 0x1FFF, 0, |b| {
        Some(b.write_u32(0x1FFF, 0, 1))
    });
    refused(&mut b, NO_SUB, 0x2101, 26, |b| {
        Some(b.write_u32(0x2101, 26, 1))
    });
    refused(&mut b, NO_SUB, 0x2300, 5, |b| {
        Some(b.write_u32(0x2300, 5, 1))
    });
    refused(&mut b, NO_SUB, 0x2010, 1, |b| {
        b.initiate(0x2010, 1, Some(4))
    });
}

#[test]
fn wrong_lengths_for_every_writable_object() {
    let mut b = Bus::new();
    b.unlock();
    for (_, index, e) in od::entries().filter(|(_, _, e)| e.access == Access::Rw) {
        for n in 1..=4usize {
            if n == e.ty.size() {
                continue;
            }
            let code = if n > e.ty.size() { TOO_LONG } else { TOO_SHORT };
            refused(&mut b, code, index, e.sub, |b| {
                Some(b.write(index, e.sub, &[0x11, 0x22, 0x33, 0x44][..n]))
            });
        }
    }
}

#[test]
fn oversized_segmented_downloads_are_refused() {
    let mut b = Bus::new();
    b.unlock();
    for (index, sub) in [
        (0x2101u16, 1u8),
        (0x2300, 1),
        (0x2300, 2),
        (0x2400, 1),
        (0x2010, 0),
        (0x1017, 0),
    ] {
        let size = od::find(index, sub).unwrap().1.ty.size() as u32;
        // a declared size that is not the object's
        for declared in [0, size + 1, 8, 255, u32::MAX] {
            let code = if declared > size { TOO_LONG } else { TOO_SHORT };
            refused(&mut b, code, index, sub, |b| {
                b.initiate(index, sub, Some(declared))
            });
        }
        // declared right, then more bytes than declared
        refused(&mut b, LENGTH, index, sub, |b| {
            assert_eq!(
                b.initiate(index, sub, Some(size)).unwrap().unwrap()[0],
                0x60
            );
            b.segment(false, &[1, 2, 3, 4, 5, 6, 7], false)
        });
        refused(&mut b, LENGTH, index, sub, |b| {
            b.initiate(index, sub, Some(size)).unwrap().unwrap();
            b.segment(false, &[0x55; 7][..size as usize + 1], true)
        });
        // size not indicated: more than the object holds in one segment
        refused(&mut b, TOO_LONG, index, sub, |b| {
            b.initiate(index, sub, None).unwrap().unwrap();
            b.segment(false, &[0x55; 7][..size as usize + 1], true)
        });
        // ... or spread over segments beyond the server's buffer
        refused(&mut b, TOO_LONG, index, sub, |b| {
            b.initiate(index, sub, None).unwrap().unwrap();
            assert_eq!(b.segment(false, &[0; 7], false).unwrap().unwrap()[0], 0x20);
            b.segment(true, &[0; 7], true)
        });
        // ... and fewer bytes than declared
        if size > 1 {
            refused(&mut b, LENGTH, index, sub, |b| {
                b.initiate(index, sub, Some(size)).unwrap().unwrap();
                b.segment(false, &[0x01][..1], true)
            });
        }
        // after each refusal the server is idle: a stray segment is a
        // protocol error, not a write
        refused(&mut b, COMMAND, 0, 0, |b| {
            b.segment(false, &[1, 0, 0, 0], true)
        });
    }
}

#[test]
fn segmented_download_with_wrong_toggle_is_refused() {
    let mut b = Bus::new();
    b.unlock();
    for (index, sub) in [(0x2102u16, 8u8), (0x2300, 1), (0x1017, 0)] {
        // the first segment must have toggle 0
        refused(&mut b, TOGGLE, index, sub, |b| {
            b.initiate(index, sub, None).unwrap().unwrap();
            b.segment(true, &[0, 0, 0x20, 0x41], true)
        });
        // the second must alternate
        refused(&mut b, TOGGLE, index, sub, |b| {
            b.initiate(index, sub, None).unwrap().unwrap();
            let r = b.segment(false, &[0, 0], false).unwrap().unwrap();
            assert_eq!(r[0], 0x20);
            b.segment(false, &[0x20, 0x41], true)
        });
        refused(&mut b, COMMAND, 0, 0, |b| {
            b.segment(true, &[0x20, 0x41], true)
        });
    }
    // the same transfer with correct toggles is accepted (the attack above
    // was refused for its toggle, not its content)
    let r = b.initiate(0x2300, 1, None).unwrap().unwrap();
    assert_eq!(r[0], 0x60);
    b.segment(false, &2000u32.to_le_bytes()[..2], false)
        .unwrap()
        .unwrap();
    b.segment(true, &2000u32.to_le_bytes()[2..], true)
        .unwrap()
        .unwrap();
    assert_eq!(b.dev.acquisition().period_us, 2000);
}

#[test]
fn interrupted_downloads_write_nothing() {
    let period = 2000u32.to_le_bytes();

    // another request in between: the download is abandoned; its last
    // segment is then a protocol error
    let mut b = Bus::new();
    refused(&mut b, COMMAND, 0, 0, |b| {
        b.initiate(0x2300, 1, Some(4)).unwrap().unwrap();
        let r = b.sdo([0x40, 0x00, 0x10, 0, 0, 0, 0, 0]).unwrap().unwrap();
        assert_eq!(r[0], 0x43); // the upload is answered
        b.segment(false, &period, true)
    });
    // an expedited write in between goes through, the interrupted one not
    let before = dump(&b.dev);
    b.initiate(0x2300, 1, Some(4)).unwrap().unwrap();
    b.write(0x1017, 0, &500u16.to_le_bytes()).unwrap();
    assert_abort(b.segment(false, &period, true), COMMAND, 0, 0);
    let after = dump(&b.dev);
    let changed: Vec<_> = before
        .values
        .iter()
        .zip(after.values.iter())
        .filter(|(x, y)| x != y)
        .map(|(x, _)| (x.0, x.1))
        .collect();
    assert_eq!(changed, [(0x1017, 0)]);

    // NMT start in the middle: the last segment arrives in operational
    let mut b = Bus::new();
    b.initiate(0x2300, 1, Some(4)).unwrap().unwrap();
    b.nmt(0x01);
    refused(&mut b, STATE, 0x2300, 1, |b| {
        b.segment(false, &period, true)
    });

    // unlocked calibration, state changed and back mid-transfer: the
    // unlock is gone when the last segment arrives
    let mut b = Bus::new();
    b.unlock();
    b.initiate(0x2101, 2, Some(4)).unwrap().unwrap();
    b.nmt(0x01);
    b.nmt(0x80);
    refused(&mut b, LOCKED, 0x2101, 2, |b| {
        b.segment(false, &7.5f32.to_le_bytes(), true)
    });

    // stop, reset node, reset communication and a client abort drop the
    // transfer: nothing is written, later segments are protocol errors
    for cs in [0x02u8, 0x81, 0x82, 0] {
        let mut b = Bus::new();
        let before = dump(&b.dev);
        b.initiate(0x2300, 1, Some(4)).unwrap().unwrap();
        if cs == 0 {
            assert_eq!(b.sdo([0x80, 0x00, 0x23, 1, 0, 0, 0, 0x08]), None);
        } else {
            b.nmt(cs);
            if cs == 0x02 {
                // stopped: the segment is not even answered
                assert_eq!(b.segment(false, &period, true), None);
                b.nmt(0x80);
            }
        }
        refused(&mut b, COMMAND, 0, 0, |b| b.segment(false, &period, true));
        assert_eq!(dump(&b.dev), before, "NMT {cs:#x}");
    }

    // an upload aborted midway by the client: no answer to the abort, the
    // next request is served, a stray upload segment is a protocol error
    let mut b = Bus::new();
    let before = dump(&b.dev);
    let r = b.sdo([0x40, 0x08, 0x10, 0, 0, 0, 0, 0]).unwrap().unwrap();
    assert_eq!(r[0], 0x41); // segmented upload of the device name
    assert_eq!(
        b.sdo([0x60, 0, 0, 0, 0, 0, 0, 0]).unwrap().unwrap()[0] & 0xE0,
        0x00
    );
    assert_eq!(b.sdo([0x80, 0x08, 0x10, 0, 0, 0, 0, 0x08]), None);
    assert_eq!(
        b.sdo([0x40, 0x00, 0x10, 0, 0, 0, 0, 0]).unwrap().unwrap()[0],
        0x43
    );
    refused(&mut b, COMMAND, 0, 0, |b| {
        b.sdo([0x70, 0, 0, 0, 0, 0, 0, 0])
    });
    assert_eq!(dump(&b.dev), before);

    // a stalled transfer times out (SDO server timeout 1 s)
    let mut b = Bus::new();
    let before = dump(&b.dev);
    b.initiate(0x2300, 1, Some(4)).unwrap().unwrap();
    b.now += 999_000;
    assert!(b.poll().is_empty());
    b.now += 2_000;
    let out: Vec<Frame> = b
        .poll()
        .into_iter()
        .filter(|f| f.id == 0x580 + NODE as u16)
        .collect();
    assert_eq!(out.len(), 1);
    assert_eq!(decode(out[0].data), Err((TIMEOUT, 0x2300, 1)));
    refused(&mut b, COMMAND, 0, 0, |b| b.segment(false, &period, true));
    assert_eq!(dump(&b.dev), before);
}

#[test]
fn store_restore_and_pdo_attacks_are_refused() {
    let mut b = Bus::new();
    // store / restore with wrong signatures
    for v in [
        0,
        1,
        LOAD_SIGNATURE,
        UNLOCK_SIGNATURE,
        SAVE_SIGNATURE.swap_bytes(),
    ] {
        refused(&mut b, STORE, 0x1010, 1, |b| {
            Some(b.write_u32(0x1010, 1, v))
        });
    }
    for v in [0, SAVE_SIGNATURE, LOAD_SIGNATURE + 1] {
        refused(&mut b, STORE, 0x1011, 1, |b| {
            Some(b.write_u32(0x1011, 1, v))
        });
    }
    refused(&mut b, TOO_SHORT, 0x1010, 1, |b| {
        Some(b.write(0x1010, 1, b"sav"))
    });
    // a store while one is pending: refused with the pending store's
    // object, and (CiA 301: an abort ends the transfer on both sides,
    // issue 49) that abort ends the first transfer: the store still
    // completes, but no confirmation follows; later requests are refused
    // on their own object until it is done
    b.sdo([0x23, 0x10, 0x10, 1, b's', b'a', b'v', b'e'])
        .map(|r| r.unwrap());
    assert!(b.dev.pending_request().is_some());
    let before = dump(&b.dev);
    assert_abort(
        b.sdo([0x23, 0x10, 0x10, 1, b's', b'a', b'v', b'e']),
        STORE,
        0x1010,
        1,
    );
    assert_abort(
        b.sdo([0x23, 0x00, 0x23, 1, 0xD0, 0x07, 0, 0]),
        STORE,
        0x2300,
        1,
    );
    assert_eq!(dump(&b.dev), before);
    let mut out = Vec::new();
    b.dev.finish_request(true, &mut |f| out.push(f)).unwrap();
    assert!(
        out.iter().all(|f| f.data[0] != 0x60),
        "no confirmation of an aborted transfer: {out:?}"
    );
    // TPDO attacks: remap a valid PDO, map calibration (not mappable),
    // overflow the 64 bits, move a valid PDO's COB-ID, restricted COB-IDs
    refused(&mut b, STATE, 0x1A00, 0, |b| Some(b.write(0x1A00, 0, &[0])));
    refused(&mut b, STATE, 0x1A00, 1, |b| {
        Some(b.write_u32(0x1A00, 1, 0x2001_0120))
    });
    refused(&mut b, RANGE, 0x1800, 1, |b| {
        Some(b.write_u32(0x1800, 1, 0x0000_01A0))
    });
    b.write_u32(0x1800, 1, 0x8000_0190).unwrap(); // disable TPDO1
    b.write(0x1A00, 0, &[0]).unwrap();
    refused(&mut b, NOT_MAPPABLE, 0x1A00, 1, |b| {
        Some(b.write_u32(0x1A00, 1, 0x2101_0120))
    });
    refused(&mut b, NOT_MAPPABLE, 0x1A00, 1, |b| {
        Some(b.write_u32(0x1A00, 1, 0x2010_0020))
    });
    refused(&mut b, NO_OBJECT, 0x1A00, 1, |b| {
        Some(b.write_u32(0x1A00, 1, 0x3000_0020))
    });
    for k in 1..=8u8 {
        b.write_u32(0x1A00, k, 0x2001_0120).unwrap();
    }
    refused(&mut b, PDO_LENGTH, 0x1A00, 0, |b| {
        Some(b.write(0x1A00, 0, &[3]))
    });
    refused(&mut b, TOO_HIGH, 0x1A00, 0, |b| {
        Some(b.write(0x1A00, 0, &[9]))
    });
    for id in [
        0x000u32, 0x07F, 0x101, 0x581, 0x601, 0x6E0, 0x701, 0x7FF, 0x800,
    ] {
        refused(&mut b, RANGE, 0x1800, 1, |b| {
            Some(b.write_u32(0x1800, 1, id))
        });
    }
    refused(&mut b, RANGE, 0x1800, 2, |b| {
        Some(b.write(0x1800, 2, &[241]))
    });
    refused(&mut b, RANGE, 0x1003, 0, |b| Some(b.write(0x1003, 0, &[1])));
}

// ---------------------------------------------------------------------------
// The same attacks against the board application: nothing reaches the
// pipeline or the flash.

type HostApp = App<SeqStore<HostFlash>>;
const BOARD: u16 = 0x20;

struct Board {
    app: HostApp,
    t: u64,
}

impl Board {
    fn boot(flash: HostFlash) -> Self {
        let mut b = Self {
            app: App::new(host_store(flash)),
            t: 0,
        };
        b.app.poll(0, &mut |_| {});
        b
    }

    fn sdo(&mut self, req: [u8; 8]) -> Option<Resp> {
        self.t += 100;
        let mut out = Vec::new();
        self.app
            .handle(&Frame::new(0x600 + BOARD, &req), self.t, &mut |f| {
                out.push(f)
            });
        out.iter()
            .find(|f| f.id == 0x580 + BOARD)
            .map(|f| decode(f.data))
    }

    fn write(&mut self, index: u16, sub: u8, data: &[u8]) -> Option<Resp> {
        let n = data.len();
        let i = index.to_le_bytes();
        let mut req = [0x23 | (((4 - n) as u8) << 2), i[0], i[1], sub, 0, 0, 0, 0];
        req[4..4 + n].copy_from_slice(data);
        self.sdo(req)
    }

    fn nmt(&mut self, cs: u8) {
        self.t += 100;
        self.app
            .handle(&Frame::new(0, &[cs, BOARD as u8]), self.t, &mut |_| {});
        self.app.poll(self.t, &mut |_| {});
    }
}

#[test]
fn attacks_on_the_board_reach_neither_pipeline_nor_flash() {
    // A calibrated board (one store done), then a barrage of refused writes.
    let mut b = Board::boot(HostFlash::new());
    b.write(0x2010, 0, &UNLOCK_SIGNATURE.to_le_bytes())
        .unwrap()
        .unwrap();
    b.write(0x2101, 1, &50.25f32.to_le_bytes())
        .unwrap()
        .unwrap();
    b.write(0x1010, 1, &SAVE_SIGNATURE.to_le_bytes())
        .unwrap()
        .unwrap();
    assert_eq!(b.app.stores(), 1);
    // reboot from a copy of the flash: the attacked board must leave it
    // bit-identical
    let mut flash = b.app.into_store().into_flash();
    flash.power_on();
    let snapshot = flash.clone();
    let mut b = Board::boot(flash);
    let params = *b.app.pipeline().params();
    assert!(b.app.pipeline().calibrated());
    let before = dump(b.app.device());

    let mut refusals = 0;
    let mut expect = |b: &mut Board, r: Option<Resp>, code: u32| {
        match r {
            Some(Err((c, _, _))) => assert_eq!(c, code),
            other => panic!("expected {code:#010x}, got {other:02x?}"),
        }
        assert_eq!(dump(b.app.device()), before);
        assert_eq!(*b.app.pipeline().params(), params);
        refusals += 1;
    };
    // locked (the reboot cleared the unlock)
    let r = b.write(0x2101, 1, &51.0f32.to_le_bytes());
    expect(&mut b, r, LOCKED);
    let r = b.write(0x2201, 1, &[1]);
    expect(&mut b, r, LOCKED);
    // out of range config
    let r = b.write(0x2300, 1, &50u32.to_le_bytes());
    expect(&mut b, r, TOO_LOW);
    let r = b.write(0x2400, 2, &300u16.to_le_bytes());
    expect(&mut b, r, RANGE);
    // oversized segmented
    let r = b.sdo([0x21, 0x00, 0x23, 1, 8, 0, 0, 0]);
    expect(&mut b, r, TOO_LONG);
    // in operational
    b.nmt(0x01);
    let r = b.write(0x2010, 0, &UNLOCK_SIGNATURE.to_le_bytes());
    expect(&mut b, r, STATE);
    let r = b.write(0x2300, 1, &2000u32.to_le_bytes());
    expect(&mut b, r, STATE);
    let r = b.write(0x2102, 8, &0.01f32.to_le_bytes());
    expect(&mut b, r, STATE);
    // NaN calibration, unlocked in pre-operational
    b.nmt(0x80);
    b.write(0x2010, 0, &UNLOCK_SIGNATURE.to_le_bytes())
        .unwrap()
        .unwrap();
    let before_nan = dump(b.app.device());
    for sub in 1..=23u8 {
        let r = b.write(0x2103, sub, &f32::NAN.to_le_bytes());
        match r {
            Some(Err((c, _, _))) => assert_eq!(c, RANGE),
            other => panic!("{other:02x?}"),
        }
        assert_eq!(dump(b.app.device()), before_nan);
    }
    assert_eq!(refusals, 8);
    // flash untouched by all of it, and what is stored boots the values of
    // before the attacks
    assert_eq!(b.app.stores(), 0);
    assert!(b.app.pipeline().config_ok());
    let f = b.app.into_store().into_flash();
    assert_eq!(f.bytes(), snapshot.bytes());
    assert_eq!(f.steps(), snapshot.steps(), "no program or erase step");
    let b = Board::boot(f);
    assert_eq!(*b.app.pipeline().params(), params);
    assert_eq!(b.app.device().nmt_state(), NmtState::PreOperational);
}
