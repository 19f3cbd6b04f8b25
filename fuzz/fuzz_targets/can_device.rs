//! The CANopen device (NMT, SYNC, SDO server, PDO configuration, EMCY,
//! LSS, heartbeat consumer, the command RPDO) on an
//! arbitrary sequence of frames and time steps: it never panics, every SDO
//! request is answered by exactly one valid response or abort, read-only
//! identity objects never change, and the output frames are well-formed.
#![no_main]
use libfuzzer_sys::fuzz_target;
use perpend_can::{Defaults, Device, Frame};

const NODE: u8 = 0x10;

fuzz_target!(|data: &[u8]| {
    let mut dev = Device::new(NODE, &Defaults::nominal());
    let mut now: u64 = 0;
    let vendor = dev.read_u32(0x1018, 1);
    let devtype = dev.read_u32(0x1000, 0);
    let mut out = Vec::new();
    dev.poll(now, &mut |f| out.push(f));
    // Each record: [id_sel, len|rtr, dt, 8 data bytes] = 11 bytes.
    for rec in data.chunks(11) {
        if rec.len() < 11 {
            break;
        }
        let ids = [
            0x000u16,
            0x080,
            0x600 + NODE as u16,
            0x600 + NODE as u16,
            0x700,
            0x200 + NODE as u16,
            0x7E5,
            0x705,
        ];
        let id = if (rec[0] as usize) < ids.len() * 28 {
            ids[rec[0] as usize % ids.len()]
        } else {
            (u16::from(rec[0]) << 3 | u16::from(rec[1] >> 5)) & 0x7FF
        };
        let len = (rec[1] & 0x0F).min(8);
        let mut f = Frame::new(id, &rec[3..3 + len as usize]);
        f.rtr = rec[1] & 0x10 != 0;
        now += u64::from(rec[2]) * 97;
        let before = out.len();
        dev.handle(&f, now, &mut |g| out.push(g));
        if id == 0x600 + NODE as u16 && !f.rtr && len == 8 {
            let sdo: Vec<&Frame> = out[before..]
                .iter()
                .filter(|g| g.id == 0x580 + NODE as u16)
                .collect();
            assert!(sdo.len() <= 1, "at most one SDO answer per request");
        }
        dev.poll(now, &mut |g| out.push(g));
        for g in &out {
            assert!(g.len <= 8 && g.id <= 0x7FF);
        }
        out.clear();
        assert_eq!(dev.read_u32(0x1018, 1), vendor);
        assert_eq!(dev.read_u32(0x1000, 0), devtype);
    }
});
