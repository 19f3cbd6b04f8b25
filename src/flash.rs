//! The parameter pages of flash bank 2 as a `NorFlash` for
//! `perpend_board::storage` ([`BoardFlash`]), the NMI handler that turns an
//! ECC double error in those pages into a read error, and the supply
//! monitor (PVD) that gates every store.
//!
//! Why not embassy-stm32 0.6's `Flash`: its blocking page erase runs the
//! whole erase (≈ 22 ms, up to 40 ms per RM0440/datasheet) inside
//! `critical_section::with`, i.e. with interrupts disabled, and each double
//! word program (≈ 82 µs) too. The FDCAN receive interrupt could not run,
//! and only the controller's 3-deep Rx FIFO 0 would hold the frames
//! arriving meanwhile. Here the register sequence of RM0440 §5.3.7/§5.3.8
//! is issued with interrupts enabled and BSY is polled with interrupts
//! enabled. That is safe because code and vectors are in bank 1 and the
//! storage in bank 2 with DBANK = 1 (checked at boot): read-while-write
//! (RM0440 §5.3.4), so the CPU keeps fetching from bank 1 while bank 2 is
//! programmed or erased, and the FDCAN interrupt keeps emptying the FIFO
//! into RAM ([`crate::can_rx`]). Nothing else touches the flash
//! controller.
//!
//! ECC (RM0440 §5.3.9): reading a double word whose programming was cut
//! sets FLASH_ECCR.ECCD and raises the NMI. [`NonMaskableInt`] checks that
//! the failing address is inside [`STORAGE`] (bank 2, BK_ECC = 1), clears
//! ECCC/ECCD (write 1) and records the offset (up to
//! `perpend_board::ecc::MAX_FAULTS` per read). [`BoardFlash::read`] runs
//! `perpend_board::ecc::guarded_read`: ECCC/ECCD cleared before the read
//! and after each single-bit correction (ECCD is set only when both were
//! clear, §3.7.7), the data cache off and reset around it (§3.3.2: a re-read
//! must not come from the cache), each recorded double word substituted
//! with `ECC_FILL` and counted ([`FlashHealth::take_read_faults`], EMCY
//! 0x6300). More faults than the log holds fail the read with
//! [`BoardFlashError::Ecc`], which `perpend_board::storage::EccGuard`
//! re-reads word by word. Any other NMI (ECC elsewhere, clock security)
//! stays fatal: the handler loops and the IWDG resets.
//!
//! Limits: not run on silicon. ECCR.ADDR_ECC is taken as the byte offset
//! inside the bank (RM0440 §5.7.8); the handler also requires that a read
//! of the storage is in progress, so an error elsewhere is never excused.

use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use embassy_stm32::pac;
use perpend_board::ecc::{self, EccFlags, EccRegs, MAX_FAULTS};
use perpend_board::storage::nor_flash::{
    ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};
use perpend_board::storage::{EccAddress, FlashHealth, PAGE, WORD};

/// Storage range (flash offsets): the last four 2 KiB pages of bank 2,
/// 0x0807E000..0x08080000, outside FLASH in memory.x.
pub const STORAGE: core::ops::Range<u32> = 0x7_E000..0x8_0000;
/// Flash base address.
const BASE: u32 = 0x0800_0000;
/// Bank size in dual-bank mode [bytes].
const BANK: u32 = 0x4_0000;

/// A storage read is in progress (the NMI handler excuses ECC errors only
/// then).
static READING: AtomicBool = AtomicBool::new(false);
/// A read of a field-update partition ([`Region`]) is in progress: an ECC
/// double error there (a double word torn by a power cut) is excused and
/// the data taken as read, as embassy-boot expects of a torn STATE word.
static REGION_READING: AtomicBool = AtomicBool::new(false);
/// Offsets of the double errors excused during the current read.
static ECC_LOG: [AtomicU32; MAX_FAULTS] = [const { AtomicU32::new(0) }; MAX_FAULTS];
/// Number of distinct offsets in [`ECC_LOG`] (`MAX_FAULTS + 1`: more).
static ECC_N: AtomicU32 = AtomicU32::new(0);

/// Records a double error at `off` once (NMI context).
fn record_fault(off: u32) {
    let n = ECC_N.load(Ordering::SeqCst) as usize;
    if ECC_LOG[..n.min(MAX_FAULTS)]
        .iter()
        .any(|a| a.load(Ordering::SeqCst) == off)
    {
        return;
    }
    if let Some(slot) = ECC_LOG.get(n) {
        slot.store(off, Ordering::SeqCst);
    }
    ECC_N.store((n + 1).min(MAX_FAULTS + 1) as u32, Ordering::SeqCst);
}

/// The flash controller and the NMI's log for `ecc::guarded_read`.
struct EccHw;

impl EccRegs for EccHw {
    fn flags(&mut self) -> EccFlags {
        let e = pac::FLASH.eccr().read();
        EccFlags {
            corrected: e.eccc(),
            detected: e.eccd(),
        }
    }
    fn clear_flags(&mut self) {
        // Write 1 to clear; ECCIE and the read-only fields are kept.
        pac::FLASH.eccr().modify(|w| {
            w.set_eccc(true);
            w.set_eccd(true);
        });
    }
    fn dcache_enabled(&mut self) -> bool {
        pac::FLASH.acr().read().dcen()
    }
    fn set_dcache(&mut self, on: bool) {
        pac::FLASH.acr().modify(|w| w.set_dcen(on));
    }
    fn reset_dcache(&mut self) {
        pac::FLASH.acr().modify(|w| w.set_dcrst(true));
        pac::FLASH.acr().modify(|w| w.set_dcrst(false));
    }
    fn load(&mut self, offset: u32, bytes: &mut [u8]) {
        READING.store(true, Ordering::SeqCst);
        for (i, b) in bytes.iter_mut().enumerate() {
            // SAFETY: inside STORAGE (checked by the caller), readable
            // flash (an ECC error raises the NMI, handled below, and the
            // load completes).
            *b = unsafe { ((BASE + offset + i as u32) as *const u8).read_volatile() };
        }
        // A pending NMI of the last load is taken before the flag drops.
        cortex_m::asm::dsb();
        cortex_m::asm::isb();
        READING.store(false, Ordering::SeqCst);
    }
    fn take_faults(&mut self) -> Option<heapless::Vec<u32, MAX_FAULTS>> {
        let n = ECC_N.swap(0, Ordering::SeqCst) as usize;
        (n <= MAX_FAULTS).then(|| {
            ECC_LOG[..n]
                .iter()
                .map(|a| a.load(Ordering::SeqCst))
                .collect()
        })
    }
}

/// Errors of [`BoardFlash`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, defmt::Format)]
pub enum BoardFlashError {
    /// Outside [`STORAGE`] or not aligned.
    Bounds,
    /// ECC double error reading the double word at this offset.
    Ecc(u32),
    /// The controller reported PROGERR/WRPERR/PGAERR/SIZERR/PGSERR (SR).
    Program(u32),
}

impl NorFlashError for BoardFlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            BoardFlashError::Bounds => NorFlashErrorKind::OutOfBounds,
            _ => NorFlashErrorKind::Other,
        }
    }
}

impl EccAddress for BoardFlashError {
    fn ecc_address(&self) -> Option<u32> {
        match self {
            BoardFlashError::Ecc(a) => Some(*a),
            _ => None,
        }
    }
}

/// The storage pages of bank 2 (offsets are absolute flash offsets, as
/// [`STORAGE`]).
pub struct BoardFlash {
    /// The flash layout was checked (dual bank, 512 KiB): otherwise every
    /// operation fails ([`BoardFlashError::Bounds`]) and the board boots
    /// factory defaults without touching the flash.
    enabled: bool,
    /// Double words substituted since the last `take_read_faults`.
    faults: u32,
}

impl BoardFlash {
    /// The driver; takes the FLASH peripheral so nothing else uses it.
    /// `enabled` = the layout check at boot passed.
    pub fn new(
        _flash: embassy_stm32::Peri<'static, embassy_stm32::peripherals::FLASH>,
        enabled: bool,
    ) -> Self {
        Self { enabled, faults: 0 }
    }

    fn check_on(&self, offset: u32, len: usize, align: u32) -> Result<(), BoardFlashError> {
        if !self.enabled {
            return Err(BoardFlashError::Bounds);
        }
        Self::check(offset, len, align)
    }

    fn check(offset: u32, len: usize, align: u32) -> Result<(), BoardFlashError> {
        let end = offset
            .checked_add(len as u32)
            .ok_or(BoardFlashError::Bounds)?;
        if offset < STORAGE.start || end > STORAGE.end || !offset.is_multiple_of(align) {
            return Err(BoardFlashError::Bounds);
        }
        Ok(())
    }

    /// Unlocks the controller and disables the data cache for the
    /// operation (as embassy-stm32's G4 driver does); returns whether it was
    /// enabled.
    fn unlock() -> bool {
        let dcen = pac::FLASH.acr().read().dcen();
        pac::FLASH.acr().modify(|w| w.set_dcen(false));
        wait_busy();
        let f = pac::FLASH;
        if f.cr().read().lock() {
            f.keyr().write_value(0x4567_0123);
            f.keyr().write_value(0xCDEF_89AB);
        }
        // Clear old error flags (write 1 to clear).
        f.sr().modify(|_| {});
        dcen
    }

    /// Locks the controller; resets the data cache (a line of an erased or
    /// programmed page may be stale; DCRST may only be written with the
    /// cache disabled, RM0440 §5.7.1) and re-enables it if it was.
    fn lock(dcen: bool) {
        pac::FLASH.cr().modify(|w| {
            w.set_pg(false);
            w.set_per(false);
            w.set_lock(true);
        });
        if dcen {
            pac::FLASH.acr().modify(|w| w.set_dcrst(true));
            pac::FLASH.acr().modify(|w| w.set_dcrst(false));
            pac::FLASH.acr().modify(|w| w.set_dcen(true));
        }
    }

    /// Waits for the end of an operation with interrupts enabled, then
    /// returns its result (RM0440 §5.3.7 step 5).
    fn finish() -> Result<(), BoardFlashError> {
        wait_busy();
        let sr = pac::FLASH.sr().read();
        // OPERR, PROGERR..PGSERR, MISERR, FASTERR
        let err = sr.0 & 0x0000_03FA;
        // Clear EOP and the error flags (write 1 to clear).
        pac::FLASH.sr().write_value(sr);
        if err != 0 {
            Err(BoardFlashError::Program(err))
        } else {
            Ok(())
        }
    }
}

fn wait_busy() {
    while pac::FLASH.sr().read().bsy() {}
}

impl ErrorType for BoardFlash {
    type Error = BoardFlashError;
}

impl ReadNorFlash for BoardFlash {
    const READ_SIZE: usize = 1;

    async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.check_on(offset, bytes.len(), 1)?;
        match ecc::guarded_read(&mut EccHw, offset, bytes) {
            Ok(r) => {
                self.faults = self.faults.saturating_add(r.substituted);
                Ok(())
            }
            // Too many to log: EccGuard reads word by word.
            Err(_) => Err(BoardFlashError::Ecc(offset & !(WORD as u32 - 1))),
        }
    }

    fn capacity(&self) -> usize {
        STORAGE.end as usize
    }
}

impl NorFlash for BoardFlash {
    const WRITE_SIZE: usize = WORD;
    const ERASE_SIZE: usize = PAGE;

    async fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        self.check_on(from, to.saturating_sub(from) as usize, PAGE as u32)?;
        erase_pages(from, to)
    }

    async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        self.check_on(offset, bytes.len(), WORD as u32)?;
        program(offset, bytes)
    }
}

/// Erases the pages `from..to` (flash offsets, page-aligned, checked by
/// the caller), interrupts enabled (RM0440 §5.3.7).
fn erase_pages(from: u32, to: u32) -> Result<(), BoardFlashError> {
    let dcen = BoardFlash::unlock();
    let mut r = Ok(());
    for page in (from..to).step_by(PAGE) {
        // RM0440 §5.3.7 page erase: BKER, PNB, PER, then STRT.
        pac::FLASH.cr().modify(|w| {
            w.set_per(true);
            w.set_bker(page >= BANK);
            w.set_pnb(((page % BANK) / PAGE as u32) as u8);
        });
        pac::FLASH.cr().modify(|w| w.set_strt(true));
        r = BoardFlash::finish();
        pac::FLASH.cr().modify(|w| w.set_per(false));
        if r.is_err() {
            break;
        }
    }
    BoardFlash::lock(dcen);
    r
}

/// Programs `bytes` (whole double words) at flash offset `offset`
/// (8-aligned, erased, checked by the caller), interrupts enabled
/// (RM0440 §5.3.8).
fn program(offset: u32, bytes: &[u8]) -> Result<(), BoardFlashError> {
    if !bytes.len().is_multiple_of(WORD) {
        return Err(BoardFlashError::Bounds);
    }
    let dcen = BoardFlash::unlock();
    pac::FLASH.cr().modify(|w| w.set_pg(true));
    let mut r = Ok(());
    for (k, dw) in bytes.chunks_exact(WORD).enumerate() {
        let at = (BASE + offset) as usize + k * WORD;
        let lo = u32::from_le_bytes([dw[0], dw[1], dw[2], dw[3]]);
        let hi = u32::from_le_bytes([dw[4], dw[5], dw[6], dw[7]]);
        // SAFETY: a double word of the unlocked storage pages; the
        // second write starts the programming (RM0440 §5.3.8).
        unsafe {
            (at as *mut u32).write_volatile(lo);
            ((at + 4) as *mut u32).write_volatile(hi);
        }
        r = BoardFlash::finish();
        if r.is_err() {
            break;
        }
    }
    BoardFlash::lock(dcen);
    r
}

impl FlashHealth for BoardFlash {
    fn take_read_faults(&mut self) -> u32 {
        core::mem::take(&mut self.faults)
    }
    fn supply_ok(&mut self) -> bool {
        // PWR_SR2.PVDO = 1: VDD below the PVD threshold (RM0440 §6.4.12).
        !pac::PWR.sr2().read().pvdo()
    }
}

/// The DFU partition (bank 2, 0x0804_0000..0x0807_7800; embassy-boot's
/// download area, src/memory.x) as flash offsets.
pub const DFU: core::ops::Range<u32> = 0x4_0000..0x7_7800;
/// The STATE partition (bank 1, 0x0800_8000..0x0800_9000).
pub const STATE: core::ops::Range<u32> = 0x8000..0x9000;

/// A partition of the field update (`DFU` or `STATE`) as a blocking
/// `NorFlash` for `perpend_board::dfu::DfuProgram` (embassy-boot's
/// updater): offsets from the partition start, the same register sequence
/// as [`BoardFlash`] (interrupts enabled). DFU is in bank 2 (read-while-
/// write: no fetch stall); writing STATE (bank 1, two small writes and a
/// two-page erase per `mark_updated`/`mark_booted`) stalls the CPU's
/// fetches for the ≈ 45 ms of the erase. Reads are plain loads; an ECC
/// double error during one (a torn double word) is excused by the NMI
/// handler and the data taken as read.
///
/// It shares the flash controller with [`BoardFlash`] without owning the
/// peripheral: only the main loop uses either, one operation at a time.
pub struct Region {
    range: core::ops::Range<u32>,
    /// The flash layout check at boot passed.
    enabled: bool,
}

impl Region {
    /// The partition `range` (flash offsets, page-aligned, outside
    /// [`STORAGE`]); `enabled` = the layout check at boot passed.
    pub const fn new(range: core::ops::Range<u32>, enabled: bool) -> Self {
        Self { range, enabled }
    }

    /// The flash offset of `offset..offset + len`, if inside.
    fn at(&self, offset: u32, len: usize, align: u32) -> Result<u32, BoardFlashError> {
        let start = self.range.start.checked_add(offset);
        let end = start.and_then(|s| s.checked_add(len as u32));
        match (start, end) {
            (Some(s), Some(e))
                if self.enabled && e <= self.range.end && s.is_multiple_of(align) =>
            {
                Ok(s)
            }
            _ => Err(BoardFlashError::Bounds),
        }
    }
}

impl embedded_storage::nor_flash::ErrorType for Region {
    type Error = BoardFlashError;
}

impl embedded_storage::nor_flash::ReadNorFlash for Region {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        let at = self.at(offset, bytes.len(), 1)?;
        REGION_READING.store(true, Ordering::SeqCst);
        for (i, b) in bytes.iter_mut().enumerate() {
            // SAFETY: inside the partition (checked above), readable flash
            // (an ECC double error raises the NMI, excused below).
            *b = unsafe { ((BASE + at + i as u32) as *const u8).read_volatile() };
        }
        cortex_m::asm::dsb();
        cortex_m::asm::isb();
        REGION_READING.store(false, Ordering::SeqCst);
        Ok(())
    }

    fn capacity(&self) -> usize {
        (self.range.end - self.range.start) as usize
    }
}

impl embedded_storage::nor_flash::NorFlash for Region {
    const WRITE_SIZE: usize = WORD;
    const ERASE_SIZE: usize = PAGE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        let at = self.at(from, to.saturating_sub(from) as usize, PAGE as u32)?;
        erase_pages(at, at + (to - from))
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        let at = self.at(offset, bytes.len(), WORD as u32)?;
        program(at, bytes)
    }
}

/// Enables the supply monitor (PVD) at its highest threshold, PLS = 6
/// (VPVD6 ≈ 2.9 V rising / 2.8 V falling, datasheet table 30): programming
/// is refused below it. Must run after `embassy_stm32::init` (PWR clock
/// on).
pub fn enable_pvd() {
    pac::PWR.cr2().modify(|w| {
        w.set_pls(6);
        w.set_pvde(true);
    });
}

/// Storage offset of an ECC error from FLASH_ECCR, if it is inside
/// [`STORAGE`] (bank 2 in dual-bank mode).
fn ecc_offset(eccr: pac::flash::regs::Eccr) -> Option<u32> {
    if !eccr.eccd() || eccr.sysf_ecc() {
        return None;
    }
    let off = if eccr.bk_ecc() { BANK } else { 0 } + eccr.addr_ecc();
    STORAGE.contains(&off).then_some(off & !(WORD as u32 - 1))
}

/// NMI: an ECC double error while reading the storage is cleared and
/// handed to [`BoardFlash::read`]; anything else stops here (the IWDG
/// resets the board).
#[cortex_m_rt::exception]
unsafe fn NonMaskableInt() {
    let eccr = pac::FLASH.eccr().read();
    match ecc_offset(eccr) {
        Some(off) if READING.load(Ordering::SeqCst) => {
            // ECCD is cleared by writing 1 (keep ECCIE, clear ECCC too).
            pac::FLASH.eccr().write_value(eccr);
            record_fault(off);
        }
        None if eccr.eccd() && REGION_READING.load(Ordering::SeqCst) => {
            pac::FLASH.eccr().write_value(eccr);
        }
        _ => loop {
            cortex_m::asm::nop();
        },
    }
}
