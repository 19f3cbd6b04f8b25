//! The MCU's program store: CiA 302-3 program download (0x1F50) into
//! embassy-boot's DFU partition through its `BlockingFirmwareUpdater`, the
//! swap marked (`mark_updated`) and confirmed (`mark_booted`) in its STATE
//! partition. Generic over `embedded_storage` NOR flashes, so the host
//! tests run it (and embassy-boot's real bootloader) on a flash fake.
//!
//! Downloaded parts (889 bytes per SDO block, any length) are collected in
//! a one-page buffer ([`DFU_PAGE`]) and written one whole page at a time:
//! `write_firmware` erases a page the first time it is written, so every
//! page is written in one call. The last page is padded with 0xFF.
//! [`crate::program::serve`] verifies the image ([`crate::image::verify`],
//! reading it back here) before it asks for the swap, so only a signed
//! image for this board is ever marked; embassy-boot is used without its
//! own signature feature (its `mark_updated` exists only then).
//!
//! Limits: parts must come in order (as the SDO server delivers them); an
//! image is at most the ACTIVE size given to [`DfuProgram::new`]; writing
//! is refused while an image is on trial (embassy-boot's `verify_booted`).
//! "clear" forgets the download without erasing (the next download erases
//! page by page; nothing unverified is ever marked).

use crate::image::ImageError;
use crate::program::{ProgramError, ProgramStore};
use embassy_boot::{BlockingFirmwareUpdater, FirmwareUpdaterConfig, FirmwareUpdaterError, State};
use embedded_storage::nor_flash::NorFlash;

/// Bytes written to the DFU partition per step (one STM32G4 page).
pub const DFU_PAGE: usize = 2048;
/// Largest STATE write size supported (the G4 writes 8 bytes).
const ALIGN: usize = 8;

/// The DFU and STATE partitions with embassy-boot's updater over them;
/// the page buffer is lent (the firmware's is a static: the store is
/// small enough to be moved, issue 50 item 6).
pub struct DfuProgram<'p, DFU, STATE> {
    dfu: DFU,
    state: STATE,
    aligned: [u8; ALIGN],
    page: &'p mut [u8; DFU_PAGE],
    /// Bytes received of the current download.
    received: u32,
    /// The whole download is in flash (`finish`).
    finished: bool,
    capacity: u32,
    key: [u8; 32],
    active: u32,
}

impl<'p, DFU: NorFlash, STATE: NorFlash> DfuProgram<'p, DFU, STATE> {
    /// A store over `dfu` and `state` accepting images of up to `capacity`
    /// bytes (the ACTIVE partition), verified against `key`; `active` is
    /// the 0x1F56 of the running image; `page` is its page buffer.
    pub fn new(
        dfu: DFU,
        state: STATE,
        page: &'p mut [u8; DFU_PAGE],
        capacity: u32,
        key: [u8; 32],
        active: u32,
    ) -> Self {
        const {
            assert!(STATE::WRITE_SIZE <= ALIGN);
            assert!(DFU_PAGE.is_multiple_of(DFU::ERASE_SIZE));
            assert!(DFU_PAGE.is_multiple_of(DFU::WRITE_SIZE));
        }
        page.fill(0xFF);
        Self {
            dfu,
            state,
            aligned: [0; ALIGN],
            page,
            received: 0,
            finished: false,
            capacity,
            key,
            active,
        }
    }

    /// embassy-boot's updater over the two partitions (built per call: it
    /// borrows them; its "last erased page" memory is not needed, every
    /// page is written in one call).
    fn updater(&mut self) -> BlockingFirmwareUpdater<'_, &mut DFU, &mut STATE> {
        let config = FirmwareUpdaterConfig {
            dfu: &mut self.dfu,
            state: &mut self.state,
        };
        BlockingFirmwareUpdater::new(config, &mut self.aligned[..STATE::WRITE_SIZE])
    }

    /// The bootloader state in STATE (`Boot`: confirmed, `Swap`: marked or
    /// on trial, `Revert`: an image was swapped back).
    ///
    /// # Errors
    /// STATE could not be read.
    pub fn boot_state(&mut self) -> Result<State, ProgramError> {
        self.updater().get_state().map_err(updater_error)
    }

    /// The partitions back (tests: the flash as left).
    pub fn into_parts(self) -> (DFU, STATE) {
        (self.dfu, self.state)
    }

    /// Writes the buffered page ending at `received` (padded with 0xFF).
    /// The page is lent to the updater in place (a copy of it cost 2 KiB
    /// of stack, issue 50 item 6).
    fn flush(&mut self) -> Result<(), ProgramError> {
        let fill = self.received as usize % DFU_PAGE;
        let at = self.received as usize - if fill == 0 { DFU_PAGE } else { fill };
        let Self {
            dfu,
            state,
            aligned,
            page,
            ..
        } = self;
        let config = FirmwareUpdaterConfig { dfu, state };
        let mut u = BlockingFirmwareUpdater::new(config, &mut aligned[..STATE::WRITE_SIZE]);
        let r = u.write_firmware(at, &page[..]);
        page.fill(0xFF);
        r.map_err(updater_error)
    }
}

/// The 0x1F57 side of an embassy-boot error.
fn updater_error(e: FirmwareUpdaterError) -> ProgramError {
    match e {
        FirmwareUpdaterError::BadState => ProgramError::Refused,
        _ => ProgramError::WriteFailed,
    }
}

impl<DFU: NorFlash, STATE: NorFlash> ProgramStore for DfuProgram<'_, DFU, STATE> {
    fn write(&mut self, offset: u32, data: &[u8]) -> Result<(), ProgramError> {
        if offset == 0 {
            self.received = 0;
            self.finished = false;
            self.page.fill(0xFF);
            if self.boot_state()? == State::Swap {
                // On trial or marked: only a confirmed image writes DFU.
                return Err(ProgramError::Refused);
            }
        }
        let end = offset.checked_add(data.len() as u32);
        if offset != self.received || self.finished || end.is_none_or(|e| e > self.capacity) {
            return Err(ProgramError::TooLarge);
        }
        let mut rest = data;
        while !rest.is_empty() {
            let fill = self.received as usize % DFU_PAGE;
            let n = rest.len().min(DFU_PAGE - fill);
            self.page[fill..fill + n].copy_from_slice(&rest[..n]);
            self.received += n as u32;
            rest = &rest[n..];
            if fill + n == DFU_PAGE {
                self.flush()?;
            }
        }
        Ok(())
    }

    fn finish(&mut self, len: u32) -> Result<(), ProgramError> {
        if self.received != len || self.finished {
            return Err(ProgramError::WriteFailed);
        }
        if !(self.received as usize).is_multiple_of(DFU_PAGE) {
            self.flush()?;
        }
        self.finished = true;
        Ok(())
    }

    fn read(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), ProgramError> {
        let end = offset.checked_add(buf.len() as u32);
        if !self.finished || end.is_none_or(|e| e > self.received) {
            return Err(ProgramError::Image(ImageError::Read));
        }
        self.updater()
            .read_dfu(offset, buf)
            .map_err(|_| ProgramError::Image(ImageError::Read))
    }

    fn clear(&mut self) -> Result<(), ProgramError> {
        self.received = 0;
        self.finished = false;
        Ok(())
    }

    fn mark_updated(&mut self) -> Result<(), ProgramError> {
        if !self.finished {
            return Err(ProgramError::Refused);
        }
        self.updater().mark_updated().map_err(updater_error)
    }

    fn mark_booted(&mut self) -> Result<(), ProgramError> {
        self.updater().mark_booted().map_err(updater_error)
    }

    fn on_trial(&mut self) -> bool {
        // After a swap the bootloader leaves the SWAP magic in STATE until
        // `mark_booted` (embassy-boot 0.7 boot_loader.rs: a SWAP magic at
        // the next start means "revert"). An unreadable STATE: not on
        // trial (no deadline; the bootloader decides at the next reset).
        matches!(self.boot_state(), Ok(State::Swap))
    }

    fn active(&self) -> u32 {
        self.active
    }

    fn public_key(&self) -> [u8; 32] {
        self.key
    }
}
