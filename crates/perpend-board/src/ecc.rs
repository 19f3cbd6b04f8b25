//! A storage read that sees every ECC error (RM0440 §3.3.2, §3.7.7), over a
//! small trait of the flash controller ([`EccRegs`]) so that the host tests
//! it against a fake flash that raises single- then double-bit errors.
//!
//! Two traps of the STM32G4 flash made the old read return raw bytes with
//! `Ok` after a double error:
//!
//! * FLASH_ECCR.ECCD is set (and the NMI raised) only if ECCC and ECCD were
//!   cleared before: one single-bit correction, left flagged, hides every
//!   later double error for the rest of the boot. [`guarded_read`] clears
//!   both flags before the read and after every double word that shows
//!   ECCC (counting the correction).
//! * A re-read of the failing address can be served by the flash data
//!   cache without a new ECC check. [`guarded_read`] disables the data
//!   cache (ACR.DCEN = 0) for the read, resets it (DCRST, which may only be
//!   written with DCEN = 0) and restores DCEN afterwards.
//!
//! The firmware's NMI handler records the offset of each double error
//! (bank 2, storage range, a storage read in progress) and clears ECCD;
//! [`guarded_read`] substitutes each recorded double word with
//! [`ECC_FILL`] (which the storage's CRCs reject like a torn item) and
//! reports how many it substituted. Limits: at most [`MAX_FAULTS`] per
//! read are recorded; beyond that the read fails with
//! [`EccReadError::TooMany`] and the caller falls back to reading word by
//! word (`crate::storage::EccGuard`).

use crate::storage::{ECC_FILL, WORD};

/// Double errors one read records at most.
pub const MAX_FAULTS: usize = 4;

/// The ECC flags of FLASH_ECCR.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct EccFlags {
    /// ECCC: a single error was corrected.
    pub corrected: bool,
    /// ECCD: a double error was detected.
    pub detected: bool,
}

/// The flash controller as a storage read needs it.
pub trait EccRegs {
    /// ECCR.ECCC and ECCR.ECCD.
    fn flags(&mut self) -> EccFlags;
    /// Clears ECCC and ECCD (write 1).
    fn clear_flags(&mut self);
    /// ACR.DCEN.
    fn dcache_enabled(&mut self) -> bool;
    /// Writes ACR.DCEN.
    fn set_dcache(&mut self, on: bool);
    /// Pulses ACR.DCRST (DCEN is 0).
    fn reset_dcache(&mut self);
    /// Loads `bytes` from the flash at `offset` (a double error raises the
    /// NMI, which records the offset).
    fn load(&mut self, offset: u32, bytes: &mut [u8]);
    /// Takes the double-error offsets the NMI recorded since the last call
    /// (`None`: more than [`MAX_FAULTS`]).
    fn take_faults(&mut self) -> Option<heapless::Vec<u32, MAX_FAULTS>>;
}

/// What a [`guarded_read`] met.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct EccReport {
    /// Double words substituted with [`ECC_FILL`] (double errors).
    pub substituted: u32,
    /// Single errors corrected by the flash.
    pub corrected: u32,
    /// Offset of the first substituted double word.
    pub first: Option<u32>,
}

/// Why a [`guarded_read`] failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EccReadError {
    /// More than [`MAX_FAULTS`] double errors: the first one's offset is
    /// unknown; read again in smaller pieces.
    TooMany,
}

/// Reads `bytes` at `offset` with the ECC flags cleared and the data cache
/// bypassed (see the module docs).
///
/// # Errors
/// [`EccReadError::TooMany`].
pub fn guarded_read<R: EccRegs>(
    r: &mut R,
    offset: u32,
    bytes: &mut [u8],
) -> Result<EccReport, EccReadError> {
    let dcen = r.dcache_enabled();
    r.set_dcache(false);
    r.reset_dcache();
    r.clear_flags();
    let _ = r.take_faults();
    let mut report = EccReport::default();
    let mut done = 0usize;
    while done < bytes.len() {
        let at = offset as usize + done;
        let n = ((at / WORD + 1) * WORD - at).min(bytes.len() - done);
        r.load(at as u32, &mut bytes[done..done + n]);
        if r.flags().corrected {
            report.corrected = report.corrected.saturating_add(1);
            r.clear_flags();
        }
        done += n;
    }
    let faults = r.take_faults();
    r.set_dcache(dcen);
    for &a in faults.as_deref().ok_or(EccReadError::TooMany)? {
        substitute(offset, bytes, a);
        report.substituted = report.substituted.saturating_add(1);
        report.first = report.first.or(Some(a));
    }
    Ok(report)
}

/// Fills the part of the double word at `word` that lies in `bytes` (read
/// at `offset`) with [`ECC_FILL`].
fn substitute(offset: u32, bytes: &mut [u8], word: u32) {
    let start = (word as usize).saturating_sub(offset as usize);
    let end = (word as usize + WORD).saturating_sub(offset as usize);
    if let Some(dst) = bytes.get_mut(start.min(bytes.len())..end.min(bytes.len())) {
        dst.fill(ECC_FILL);
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
#[path = "ecc_tests.rs"]
mod tests;
