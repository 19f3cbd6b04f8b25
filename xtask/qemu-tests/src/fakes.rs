//! A fake of the flash ECC registers for the target tests (the model of
//! RM0440 §3.7.7 that the host tests of perpend-board use, in no_std
//! form). The FDCAN fake is perpend-board's own (`fdcan_fake.rs`).

use heapless::Vec;
use perpend_board::ecc::{EccFlags, EccRegs, MAX_FAULTS};
use perpend_board::storage::WORD;

/// Flash ECC: one double word with a single error, up to two with a
/// double error; ECCC/ECCD set only when both were clear (RM0440 §3.7.7),
/// the NMI records double-error offsets.
pub struct FakeEcc {
    /// Offset of the double word with a single error.
    pub single_at: Option<u32>,
    /// Offsets of the double words with a double error.
    pub double_at: [Option<u32>; 2],
    flags: EccFlags,
    /// ACR.DCEN.
    pub dcache_on: bool,
    faults: Vec<u32, MAX_FAULTS>,
}

impl Default for FakeEcc {
    fn default() -> Self {
        Self {
            single_at: None,
            double_at: [None; 2],
            flags: EccFlags::default(),
            dcache_on: true,
            faults: Vec::new(),
        }
    }
}

impl EccRegs for FakeEcc {
    fn flags(&mut self) -> EccFlags {
        self.flags
    }
    fn clear_flags(&mut self) {
        self.flags = EccFlags::default();
    }
    fn dcache_enabled(&mut self) -> bool {
        self.dcache_on
    }
    fn set_dcache(&mut self, on: bool) {
        self.dcache_on = on;
    }
    fn reset_dcache(&mut self) {}
    fn load(&mut self, offset: u32, bytes: &mut [u8]) {
        bytes.fill(0x5A);
        let word = offset - offset % WORD as u32;
        let armed = self.flags == EccFlags::default();
        if Some(word) == self.single_at && armed {
            self.flags.corrected = true;
        }
        if self.double_at.contains(&Some(word)) {
            if armed {
                self.flags.detected = true;
            }
            let _ = self.faults.push(word);
        }
    }
    fn take_faults(&mut self) -> Option<Vec<u32, MAX_FAULTS>> {
        Some(core::mem::take(&mut self.faults))
    }
}
