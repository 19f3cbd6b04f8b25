//! Tests of [`guarded_read`] against a fake flash with the STM32G4's ECC
//! flag rule (ECCD only after ECCC/ECCD were cleared) and a data cache
//! that serves re-reads without an ECC check.

use super::*;
use std::collections::HashMap;

#[derive(Clone, Copy)]
enum Fault {
    Single,
    Double,
}

#[derive(Default)]
struct FakeFlash {
    data: std::vec::Vec<u8>,
    faults: HashMap<u32, Fault>,
    flags: EccFlags,
    dcen: bool,
    cache: HashMap<u32, [u8; WORD]>,
    nmi: std::vec::Vec<u32>,
    dcache_resets: u32,
}

impl FakeFlash {
    fn new(faults: &[(u32, Fault)]) -> Self {
        Self {
            data: (0..256u32).map(|i| (i * 7 + 3) as u8).collect(),
            faults: faults.iter().copied().collect(),
            dcen: true,
            ..Self::default()
        }
    }

    /// The double word at `w` as the array delivers it (a double error
    /// returns flipped bits).
    fn word(&mut self, w: u32) -> [u8; WORD] {
        let mut v = [0u8; WORD];
        v.copy_from_slice(&self.data[w as usize..w as usize + WORD]);
        let clean = !self.flags.corrected && !self.flags.detected;
        match self.faults.get(&w) {
            Some(Fault::Single) if clean => self.flags.corrected = true,
            Some(Fault::Double) => {
                v[0] ^= 0x5A;
                if clean && !self.nmi.contains(&w) {
                    // ECCD and the NMI; the handler records the double
                    // word once and clears ECCD.
                    self.nmi.push(w);
                }
            }
            _ => {}
        }
        v
    }
}

impl EccRegs for FakeFlash {
    fn flags(&mut self) -> EccFlags {
        self.flags
    }
    fn clear_flags(&mut self) {
        self.flags = EccFlags::default();
    }
    fn dcache_enabled(&mut self) -> bool {
        self.dcen
    }
    fn set_dcache(&mut self, on: bool) {
        self.dcen = on;
    }
    fn reset_dcache(&mut self) {
        assert!(!self.dcen, "DCRST written with the data cache enabled");
        self.cache.clear();
        self.dcache_resets += 1;
    }
    fn load(&mut self, offset: u32, bytes: &mut [u8]) {
        for (i, b) in bytes.iter_mut().enumerate() {
            let a = offset + i as u32;
            let w = a & !(WORD as u32 - 1);
            let line = match self.cache.get(&w) {
                Some(l) if self.dcen => *l,
                _ => {
                    let l = self.word(w);
                    if self.dcen {
                        self.cache.insert(w, l);
                    }
                    l
                }
            };
            *b = line[(a - w) as usize];
        }
    }
    fn take_faults(&mut self) -> Option<heapless::Vec<u32, MAX_FAULTS>> {
        let v = std::mem::take(&mut self.nmi);
        heapless::Vec::from_slice(&v).ok()
    }
}

/// The old read: one pass, flags and cache as they are, the first NMI
/// offset as the error.
fn old_read(f: &mut FakeFlash, offset: u32, bytes: &mut [u8]) -> Result<(), u32> {
    f.load(offset, bytes);
    match f.take_faults() {
        Some(v) if !v.is_empty() => Err(v[0]),
        _ => Ok(()),
    }
}

const FAULTS: [(u32, Fault); 2] = [(0x10, Fault::Single), (0x40, Fault::Double)];

#[test]
fn old_read_misses_a_double_error_after_a_single_one() {
    let mut f = FakeFlash::new(&FAULTS);
    let mut buf = [0u8; 0x80];
    assert_eq!(old_read(&mut f, 0, &mut buf), Ok(()));
    assert_ne!(buf[0x40], f.data[0x40], "raw bytes came back with Ok");
}

#[test]
fn guarded_read_substitutes_a_double_error_after_a_single_one() {
    let mut f = FakeFlash::new(&FAULTS);
    // ECCC left set by an earlier read, as the old firmware left it.
    f.flags.corrected = true;
    let mut buf = [0u8; 0x80];
    let r = guarded_read(&mut f, 0, &mut buf).unwrap();
    assert_eq!(r.substituted, 1);
    assert_eq!(r.corrected, 1);
    assert_eq!(r.first, Some(0x40));
    assert!(buf[0x40..0x48].iter().all(|&b| b == ECC_FILL));
    assert_eq!(&buf[..0x40], &f.data[..0x40]);
    assert_eq!(&buf[0x48..], &f.data[0x48..0x80]);
}

#[test]
fn old_reread_comes_from_the_cache_guarded_one_does_not() {
    let mut f = FakeFlash::new(&FAULTS[1..]);
    let mut buf = [0u8; 0x80];
    assert_eq!(old_read(&mut f, 0, &mut buf), Err(0x40));
    // The old guard read the failing word again: served by the cache.
    f.clear_flags();
    let mut w = [0u8; WORD];
    assert_eq!(old_read(&mut f, 0x40, &mut w), Ok(()));
    let r = guarded_read(&mut f, 0x40, &mut w).unwrap();
    assert_eq!(r.substituted, 1);
    assert_eq!(w, [ECC_FILL; WORD]);
    assert!(f.dcen, "the data cache was not re-enabled");
    assert!(f.dcache_resets >= 1);
}

#[test]
fn part_of_a_failing_word_inside_the_read_is_filled() {
    let mut f = FakeFlash::new(&FAULTS[1..]);
    let mut buf = [0u8; 8];
    let r = guarded_read(&mut f, 0x44, &mut buf).unwrap();
    assert_eq!(r.substituted, 1);
    assert_eq!(buf[..4], [ECC_FILL; 4]);
    assert_eq!(buf[4..], f.data[0x48..0x4C]);
}

#[test]
fn too_many_double_errors_fail_the_read() {
    let many: std::vec::Vec<(u32, Fault)> = (0..=MAX_FAULTS as u32)
        .map(|k| (k * 8, Fault::Double))
        .collect();
    let mut f = FakeFlash::new(&many);
    let mut buf = [0u8; 64];
    assert_eq!(
        guarded_read(&mut f, 0, &mut buf),
        Err(EccReadError::TooMany)
    );
    assert!(f.dcen);
}
