//! Register reads and writes behind `perpend_board::health` and
//! `perpend_board::bootctl`: reset cause, factory calibration words, flash
//! layout and option bytes, debugger freeze of the IWDG, the IWDG
//! hand-over from the bootloader, the ROM-loader request (TAMP_BKP0R) and
//! the bootloader's build flags, the DWT cycle counter, stack painting and
//! the MPU stack guard.
//!
//! Addresses (RM0440 / STM32G474 datasheet): VREFINT_CAL 0x1FFF75AA, TS_CAL1
//! 0x1FFF75A8 (30 °C), TS_CAL2 0x1FFF75CA (130 °C), all at VREF+ = 3.0 V;
//! FLASH_SIZE 0x1FFF75E0 (KiB). RCC_CSR reset flags are cleared by RMVF
//! (§7.4.29); DBGMCU_APB1FZR1.DBG_IWDG_STOP freezes the IWDG while the core
//! is halted (§46.16.4).
//!
//! Stack guard: the firmware is linked with flip-link, so the stack grows
//! down from just below `.data`/`.bss` (`_stack_start`) towards the bottom
//! of RAM (`_stack_end` = 0x20000000, set by flip-link): an overflow can
//! no longer reach static data. MPU region 0
//! makes the [`GUARD`] bytes (8 KiB, size-aligned) above `_stack_end`
//! inaccessible (AP = 000, XN), so an overflow faults at once (MemManage,
//! then the IWDG resets the board, reported as a watchdog reset) instead of
//! running below RAM (0x1FFF_xxxx: system memory and option bytes, whose
//! writes are not guaranteed to fault). The guard is larger than any frame the stack
//! can hold below the main task's: a 32-byte guard could be stepped over
//! by a frame with a ~2 KiB buffer (the storage's item buffer), whose
//! writes then land below the guard without touching it. `cargo xtask
//! size` reads every function's frame from the linked image (prologues)
//! and fails when one below the main task is at or above [`GUARD`]
//! (`App::store_now` held the device copy, its image and the item buffer,
//! 9,304 B; now split: `staged_params` without a device copy,
//! `save_with_tail`; every frame is below 4 KiB, issue 50); a
//! compile-time check keeps those buffers below [`GUARD`] too. The
//! stack below the boot-time SP is painted ([`health::STACK_PAINT`]); the
//! high-water mark is published in 0x200B sub 3.

use core::sync::atomic::{AtomicUsize, Ordering};

use cortex_m::peripheral::{DCB, DWT};
use embassy_stm32::pac;
use perpend_board::bootctl::{self, BackupRegister, BootInfo, IwdgSetting, RomLoaderPolicy};
use perpend_board::health::{self, HealthError, ResetFlags};

const VREFINT_CAL: *const u16 = 0x1FFF_75AA as *const u16;
const TS_CAL1: *const u16 = 0x1FFF_75A8 as *const u16;
const TS_CAL2: *const u16 = 0x1FFF_75CA as *const u16;
const FLASH_SIZE_KIB: *const u16 = 0x1FFF_75E0 as *const u16;
/// Flash the storage range needs [KiB] (its end, 0x0808_0000).
pub const FLASH_NEED_KIB: u16 = 512;

/// Size of the MPU stack guard [bytes] (a power of two, ≥ 32).
pub const GUARD: usize = 8192;
/// The buffers of the store path, all of them as if in one frame: the
/// image (`App::store_now`), the staged object values (`staged_params`,
/// no device copy since issue 50), the item buffer and the record
/// (`save_with_tail`). `cargo xtask size` checks the real frames.
const STORE_FRAME_BUFFERS: usize = 4 * perpend_can::od::ENTRIES
    + perpend_can::IMAGE_LEN
    + perpend_board::storage::MAX_ITEM
    + core::mem::size_of::<perpend_core::params::Params>();
const _: () = assert!(GUARD.is_power_of_two() && GUARD >= 32);
const _: () = assert!(
    STORE_FRAME_BUFFERS < GUARD,
    "stack guard smaller than a frame"
);

extern "C" {
    static mut _stack_end: u32;
    static mut _stack_start: u32;
}

/// Reads and clears the reset flags (RCC_CSR, RMVF).
pub fn take_reset_flags() -> ResetFlags {
    let csr = pac::RCC.csr().read();
    pac::RCC.csr().modify(|w| w.set_rmvf(true));
    ResetFlags::from_csr(csr.0)
}

/// Freezes the IWDG while the core is halted by a debugger.
pub fn freeze_iwdg_in_debug() {
    pac::DBGMCU.apb1lfzr().modify(|w| w.set_iwdg(true));
}

/// The flash layout the storage and read-while-write need.
pub fn check_flash() -> Result<(), HealthError> {
    // SAFETY: the flash size word is in system memory, always readable.
    let size = unsafe { FLASH_SIZE_KIB.read_volatile() };
    health::check_flash(pac::FLASH.optr().read().dbank(), size, FLASH_NEED_KIB)
}

/// Flash size from the size register [KiB].
pub fn flash_size_kib() -> u16 {
    // SAFETY: as in `check_flash`.
    unsafe { FLASH_SIZE_KIB.read_volatile() }
}

/// Factory calibration: (VREFINT_CAL, TS_CAL1, TS_CAL2).
pub fn factory_cal() -> (u16, u16, u16) {
    // SAFETY: calibration words in system memory, always readable.
    unsafe {
        (
            VREFINT_CAL.read_volatile(),
            TS_CAL1.read_volatile(),
            TS_CAL2.read_volatile(),
        )
    }
}

/// Starts the DWT cycle counter.
pub fn start_cycle_counter() {
    // SAFETY: only this module touches DCB/DWT, once at boot.
    let mut p = unsafe { cortex_m::Peripherals::steal() };
    p.DCB.enable_trace();
    p.DWT.enable_cycle_counter();
    let _ = DCB::is_debugger_attached();
}

/// The cycle counter.
pub fn cycles() -> u32 {
    DWT::cycle_count()
}

fn stack_bounds() -> (usize, usize) {
    // Linker symbols; only their addresses are used.
    (
        core::ptr::addr_of!(_stack_end) as usize,
        core::ptr::addr_of!(_stack_start) as usize,
    )
}

/// Paints the free stack below the current SP (minus a margin) and arms
/// the MPU guard at its bottom.
pub fn paint_and_guard_stack() {
    let (bottom, _) = stack_bounds();
    let sp = cortex_m::register::msp::read() as usize;
    let base = guard_base(bottom);
    let mut p = base + GUARD;
    while p + 4 <= sp.saturating_sub(256) {
        // SAFETY: between the end of the static data and the live stack:
        // unused RAM.
        unsafe { (p as *mut u32).write_volatile(health::STACK_PAINT) };
        p += 4;
    }
    guard(base);
}

/// The guard's base: `bottom` rounded up to the guard size (an MPU region
/// is aligned to its size).
fn guard_base(bottom: usize) -> usize {
    (bottom + GUARD - 1) & !(GUARD - 1)
}

/// Lowest stack address found used so far (0: not scanned yet).
static LOW: AtomicUsize = AtomicUsize::new(0);
/// Words below the last mark scanned on each later call (2 KiB).
const WINDOW_WORDS: usize = 512;

/// Stack used so far [bytes] (from the painted region). The first call
/// scans the whole painted region (≈ 85 KiB, ≈ 0.4 ms); later calls only
/// the 2 KiB below the mark found, ≈ 10 µs (a frame that leaves more than
/// 2 KiB of its locals untouched below the mark is missed until the next
/// boot's first scan).
pub fn stack_used() -> usize {
    let (bottom, top) = stack_bounds();
    let start = guard_base(bottom) + GUARD; // above the guard
    let (low, end) = match LOW.load(Ordering::Relaxed) {
        0 => (start, top),
        l => (l.saturating_sub(4 * WINDOW_WORDS).max(start), l),
    };
    let words = (end - low) / 4;
    // SAFETY: reads of RAM between the guard and the top of the stack.
    let it = (0..words).map(|k| unsafe { ((low + 4 * k) as *const u32).read_volatile() });
    let mark = end - health::stack_used(it);
    LOW.store(mark, Ordering::Relaxed);
    top - mark
}

/// MPU region 0: [`GUARD`] bytes at `base` (size-aligned), no access, XN;
/// default map for everything else (PRIVDEFENA); MemManage enabled.
fn guard(base: usize) {
    // SAFETY: boot time, before any task runs; the region is unused RAM.
    unsafe {
        let p = cortex_m::Peripherals::steal();
        p.MPU.rnr.write(0);
        p.MPU.rbar.write(base as u32 & !(GUARD as u32 - 1));
        // XN (28), AP = 000 (26:24), SIZE = log2(GUARD) - 1, ENABLE.
        let size = GUARD.trailing_zeros() - 1;
        p.MPU.rasr.write((1 << 28) | (size << 1) | 1);
        // PRIVDEFENA (2) | ENABLE (0)
        p.MPU.ctrl.write((1 << 2) | 1);
        let mut scb = p.SCB;
        scb.enable(cortex_m::peripheral::scb::Exception::MemoryManagement);
        cortex_m::asm::dsb();
        cortex_m::asm::isb();
    }
}

/// TAMP_BKP0R, where the ROM-loader request lives
/// (`perpend_board::bootctl`: kept over the system reset, read and cleared
/// by perpend-boot before anything else). Not a RAM word: the
/// bootloader's start-up zeroes its `.bss`, which covered the word the
/// application used before (issue 50 item 1).
struct Tamp;

impl BackupRegister for Tamp {
    fn read(&mut self) -> u32 {
        pac::TAMP.bkpr(bootctl::ROM_LOADER_BKP).read().bkp()
    }
    fn write(&mut self, value: u32) {
        pac::TAMP
            .bkpr(bootctl::ROM_LOADER_BKP)
            .write(|w| w.set_bkp(value));
    }
}

/// The bootloader's build flags (`.boot_info` at
/// [`bootctl::BOOT_INFO_ADDR`]); `None` without a bootloader.
pub fn boot_info() -> Option<BootInfo> {
    // SAFETY: 8 bytes of bank 1 flash, always readable.
    let w = unsafe { (bootctl::BOOT_INFO_ADDR as *const [u32; 2]).read_volatile() };
    BootInfo::from_words(w)
}

/// What the bootloader allows for the ROM loader (refused without one).
pub fn rom_loader_policy() -> RomLoaderPolicy {
    boot_info().map(BootInfo::policy).unwrap_or_default()
}

/// Resets into the ROM loader through perpend-boot (field update,
/// docs/bring-up.md §7.2): the request into TAMP_BKP0R (RTC/TAMP APB clock
/// and backup-domain write access, PWR_CR1.DBP, RM0440 §6.4.1), then a
/// system reset. Returns only when the bootloader's policy refuses it.
pub fn reset_into_bootloader() -> Result<core::convert::Infallible, bootctl::BootCtlError> {
    pac::RCC.apb1enr1().modify(|w| {
        w.set_pwren(true);
        w.set_rtcapben(true);
    });
    pac::PWR.cr1().modify(|w| w.set_dbp(true));
    while !pac::PWR.cr1().read().dbp() {}
    let r = bootctl::request_rom_loader(&mut Tamp, rom_loader_policy());
    pac::PWR.cr1().modify(|w| w.set_dbp(false));
    r?;
    cortex_m::asm::dsb();
    cortex_m::peripheral::SCB::sys_reset()
}

/// FLASH_OPTR (RM0440 §3.7.8).
pub fn optr() -> u32 {
    pac::FLASH.optr().read().0
}

/// The IWDG registers for `perpend_board::bootctl::handover`.
struct IwdgRegs;

impl bootctl::IwdgRegs for IwdgRegs {
    fn key(&mut self, key: u16) {
        pac::IWDG
            .kr()
            .write(|w| w.set_key(pac::iwdg::vals::Key::from_bits(key)));
    }
    fn set_prescaler(&mut self, pr: u8) {
        pac::IWDG
            .pr()
            .write(|w| w.set_pr(pac::iwdg::vals::Pr::from_bits(pr)));
    }
    fn set_reload(&mut self, rl: u16) {
        pac::IWDG.rlr().write(|w| w.set_rl(rl));
    }
    fn busy(&mut self) -> bool {
        pac::IWDG.sr().read().0 & 0b111 != 0
    }
}

/// The independent watchdog once the application has it: taken over from
/// the bootloader's 8 s with a reload (`bootctl::handover`), then petted.
pub struct Watchdog(());

impl Watchdog {
    /// Hands the IWDG over to `timeout_us` and reloads it: the full
    /// timeout from now (issue 50 item 2).
    ///
    /// # Errors
    /// As `bootctl::handover` (the counter is reloaded in any case).
    pub fn take_over(timeout_us: u32) -> (Self, Result<(), bootctl::BootCtlError>) {
        let r = IwdgSetting::for_timeout_us(timeout_us)
            .and_then(|s| bootctl::handover(&mut IwdgRegs, s));
        (Self(()), r)
    }

    /// Reloads the counter (IWDG_KR = 0xAAAA).
    pub fn pet(&mut self) {
        bootctl::IwdgRegs::key(&mut IwdgRegs, bootctl::KEY_RELOAD);
    }
}

/// The clocks of the NUCLEO-G474RE (the firmware's and the HIL tests').
pub fn config() -> embassy_stm32::Config {
    let mut c = embassy_stm32::Config::default();
    // NUCLEO-G474RE: 24 MHz crystal (X3). SYSCLK = 24 / 6 * 85 / 2 = 170 MHz.
    c.rcc.hse = Some(embassy_stm32::rcc::Hse {
        freq: embassy_stm32::time::Hertz(perpend_board::bittiming::FDCAN_KERNEL_HZ),
        mode: embassy_stm32::rcc::HseMode::Oscillator,
    });
    c.rcc.pll = Some(embassy_stm32::rcc::Pll {
        source: embassy_stm32::rcc::PllSource::HSE,
        prediv: embassy_stm32::rcc::PllPreDiv::DIV6,
        mul: embassy_stm32::rcc::PllMul::MUL85,
        divp: None,
        divq: None,
        divr: Some(embassy_stm32::rcc::PllRDiv::DIV2),
    });
    c.rcc.sys = embassy_stm32::rcc::Sysclk::PLL1_R;
    c.rcc.boost = true;
    // FDCAN from HSE: the kernel clock of perpend_board::bittiming.
    c.rcc.mux.fdcansel = embassy_stm32::rcc::mux::Fdcansel::HSE;
    // ADC from SYSCLK (the driver divides by 4: 42.5 MHz ≤ 60 MHz).
    c.rcc.mux.adc12sel = embassy_stm32::rcc::mux::Adcsel::SYS;
    c
}
