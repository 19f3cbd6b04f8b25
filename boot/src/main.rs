//! perpend-boot: the field-update bootloader of the sensor board
//! (STM32G474RE), embassy-boot-stm32 with the layout of `memory.x`
//! (docs/firmware.md "Field update: memory layout").
//!
//! At every reset: starts the independent watchdog (8 s; a running one,
//! left by the application, is reprogrammed to 8 s and fed before every
//! flash operation, so the page swap of up to ≈ 10 s is never cut by it),
//! then `BootLoader::prepare` (embassy-boot): a marked image in DFU is
//! swapped into ACTIVE page by page (power-fail safe: progress in STATE),
//! an image on trial that did not confirm itself (`mark_booted`) is
//! swapped back, then it jumps to ACTIVE. The watchdog stays running: an
//! application that panics or hangs before it feeds the watchdog resets
//! the board, and the bootloader reverts it.
//!
//! The bootloader does not verify signatures: the application verifies a
//! downloaded image (`perpend_board::image::verify`) against the public
//! key stored here, at [`PUBLIC_KEY`]'s fixed address 0x0800_7FE0
//! (`BOOTKEY` in memory.x), before it marks the image for the swap. The
//! key is built in from `keys/test-only.pk` (TEST KEY) or the file named
//! by `PERPEND_PUBLIC_KEY` (build.rs); the bootloader pages are
//! write-protected after the first flash, so the key cannot be changed
//! over CAN.
//!
//! Before any of that (issue 50, `perpend_board::bootctl`):
//!
//! * **ROM-loader request**: TAMP_BKP0R is read and cleared with the
//!   clocks in their reset state; a request the policy allows
//!   ([`POLICY`]: a `test-key` build, or the `rom-loader` provisioning
//!   flag) remaps system memory to 0 (SYSCFG_MEMRMP.MEM_MODE = 01, RM0440
//!   §9.1.1), sets VTOR to 0 (its reset value; this code never moved it)
//!   and jumps to the ROM loader at 0x1FFF_0000 (AN2606). The IWDG is not
//!   running yet (a system reset stops it unless the IWDG_SW option byte
//!   starts it in hardware). A refused request is logged and ignored.
//! * **Option bytes**: FLASH_OPTR (RM0440 §3.7.8) must be DBANK = 1 and
//!   BFB2 = 0. embassy-stm32 0.6's flash driver panics on DBANK = 0 (the
//!   board then reset for ever without a word); now the bootloader logs
//!   the fault on RTT and starts the application without creating the
//!   flash driver (no swap, no rollback); the application refuses flash
//!   writes and sends EMCY 0x5000.
//!
//! An ECC double error in flash (a torn double word) is excused
//! ([`NonMaskableInt`]), as the power-cut tests model it.
//!
//! Limits: not run on silicon. A panic of the bootloader itself (a flash
//! error during the swap) ends in `udf` → HardFault → system reset; the
//! swap resumes at the next start.

#![no_std]
#![no_main]

use core::cell::RefCell;

use cortex_m_rt::{entry, exception};
use defmt_rtt as _;
use embassy_boot_stm32::{BootLoader, BootLoaderConfig, State};
use embassy_stm32::flash::{Flash, BANK1_REGION};
use embassy_stm32::pac;
use embassy_stm32::pac::iwdg::vals::{Key, Pr};
use embassy_sync::blocking_mutex::Mutex;
use embedded_storage::nor_flash::{ErrorType, NorFlash, ReadNorFlash};
use perpend_board::bootctl::{
    self, BackupRegister, BootInfo, BootPlan, RomLoader, RomLoaderPolicy, FLAG_ROM_LOADER,
    FLAG_TEST_KEY,
};

/// The public key images must verify against (32 bytes, RFC 8032), at
/// 0x0800_7FE0 (`.boot_key`, memory.x): the application reads it there.
#[used]
#[unsafe(link_section = ".boot_key")]
pub static PUBLIC_KEY: [u8; 32] = *include_bytes!(concat!(env!("OUT_DIR"), "/public_key.bin"));

/// Whether the ROM loader may be entered: a test-key build, or the
/// provisioning flag (feature `rom-loader`).
const POLICY: RomLoaderPolicy = RomLoaderPolicy {
    test_key: cfg!(perpend_test_key),
    provisioned: cfg!(feature = "rom-loader"),
};

/// The build flags at 0x0800_7FD8 (`.boot_info`, memory.x), which the
/// application reads to refuse 0x2500 = bootloader when [`POLICY`] does.
#[used]
#[unsafe(link_section = ".boot_info")]
pub static BOOT_INFO: [u32; 2] = BootInfo {
    flags: if POLICY.test_key { FLAG_TEST_KEY } else { 0 }
        | if POLICY.provisioned {
            FLAG_ROM_LOADER
        } else {
            0
        },
}
.words();

/// Bytes copied per step of the swap (one 2 KiB page).
const PAGE: usize = 2048;

/// IWDG prescaler /256 (PR = 6): 32 kHz LSI / 256 = 125 Hz.
const IWDG_PR: u8 = 6;
/// IWDG reload for 8 s at 125 Hz.
const IWDG_RELOAD: u16 = 1000;

/// Starts the IWDG (or keeps it running) with an 8 s timeout (RM0440
/// §42.3: start key, then unlock, prescaler, reload, wait for the update).
fn start_watchdog() {
    let w = pac::IWDG;
    w.kr().write(|k| k.set_key(Key::START));
    w.kr().write(|k| k.set_key(Key::ENABLE));
    w.pr().write(|r| r.set_pr(Pr::from_bits(IWDG_PR)));
    w.rlr().write(|r| r.set_rl(IWDG_RELOAD));
    while w.sr().read().0 != 0 {}
    feed();
}

/// Reloads the IWDG.
fn feed() {
    pac::IWDG.kr().write(|k| k.set_key(Key::RESET));
}

/// A flash region that feeds the watchdog before every operation.
struct Fed<F>(F);

impl<F: ErrorType> ErrorType for Fed<F> {
    type Error = F::Error;
}

impl<F: ReadNorFlash> ReadNorFlash for Fed<F> {
    const READ_SIZE: usize = F::READ_SIZE;
    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.0.read(offset, bytes)
    }
    fn capacity(&self) -> usize {
        self.0.capacity()
    }
}

impl<F: NorFlash> NorFlash for Fed<F> {
    const WRITE_SIZE: usize = F::WRITE_SIZE;
    const ERASE_SIZE: usize = F::ERASE_SIZE;
    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        feed();
        self.0.erase(from, to)
    }
    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        feed();
        self.0.write(offset, bytes)
    }
}

/// TAMP_BKP0R, the ROM-loader request (kept over a system reset).
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

/// Takes the ROM-loader request: the TAMP APB clock and the backup-domain
/// write access (PWR_CR1.DBP, RM0440 §6.4.1) only for this, then back.
fn rom_loader_request() -> RomLoader {
    pac::RCC.apb1enr1().modify(|w| {
        w.set_pwren(true);
        w.set_rtcapben(true);
    });
    pac::PWR.cr1().modify(|w| w.set_dbp(true));
    while !pac::PWR.cr1().read().dbp() {}
    let r = bootctl::take_rom_loader_request(&mut Tamp, POLICY);
    pac::PWR.cr1().modify(|w| w.set_dbp(false));
    pac::RCC.apb1enr1().modify(|w| w.set_rtcapben(false));
    r
}

/// Jumps to the STM32 ROM loader (AN2606 "jump to the bootloader from
/// application code"): system memory mapped at 0, VTOR 0.
fn enter_rom_loader() -> ! {
    pac::RCC.apb2enr().modify(|w| w.set_syscfgen(true));
    pac::SYSCFG.memrmp().modify(|w| w.set_mem_mode(1));
    // SAFETY: reset state, nothing else runs; system memory holds the ROM
    // loader's vector table (mapped at 0 and at 0x1FFF_0000).
    unsafe {
        let p = cortex_m::Peripherals::steal();
        p.SCB.vtor.write(0);
        cortex_m::asm::dsb();
        cortex_m::asm::isb();
        cortex_m::asm::bootload(0x1FFF_0000 as *const u32)
    }
}

/// Starts ACTIVE without any flash operation (wrong option bytes).
fn start_active_only() -> ! {
    // ACTIVE: __bootloader_active_start in memory.x.
    let active = BANK1_REGION.base() + 0x9000;
    // SAFETY: as `BootLoader::load` (embassy-boot-stm32): VTOR to the
    // application's vector table, then its stack pointer and reset vector.
    unsafe {
        let mut p = cortex_m::Peripherals::steal();
        p.SCB.invalidate_icache();
        p.SCB.vtor.write(active);
        cortex_m::asm::bootload(active as *const u32)
    }
}

#[entry]
fn main() -> ! {
    match rom_loader_request() {
        RomLoader::Enter => enter_rom_loader(),
        RomLoader::Refused => defmt::warn!(
            "perpend-boot: ROM-loader request refused (release build without the provisioning flag)"
        ),
        RomLoader::None => {}
    }
    let optr = pac::FLASH.optr().read().0;
    if let BootPlan::StartOnly(e) = bootctl::boot_plan(optr) {
        // No embassy flash driver: it panics on DBANK = 0.
        let what = match e {
            bootctl::BootCtlError::SingleBank => "DBANK = 0 (single bank)",
            bootctl::BootCtlError::BootFromBank2 => "BFB2 = 1 (boot from bank 2)",
            _ => "unexpected",
        };
        defmt::error!(
            "perpend-boot: option bytes FLASH_OPTR {=u32:#010x}: {=str}; need DBANK = 1, BFB2 = 0 (docs/bring-up.md §2): no update, starting the application",
            optr,
            what
        );
        start_watchdog();
        start_active_only();
    }
    if POLICY.test_key {
        defmt::warn!("perpend-boot: TEST KEY build (keys/test-only.pk): never ship");
    }
    let p = embassy_stm32::init(Default::default());
    start_watchdog();
    let layout = Flash::new_blocking(p.FLASH).into_blocking_regions();
    // STATE and ACTIVE in bank 1, DFU in bank 2 (dual-bank mode).
    let bank1 = Mutex::new(RefCell::new(Fed(layout.bank1_region)));
    let bank2 = Mutex::new(RefCell::new(Fed(layout.bank2_region)));
    let config = BootLoaderConfig::from_linkerfile_blocking(&bank1, &bank2, &bank1);
    let active = config.active.offset();
    let bl = BootLoader::prepare::<_, _, _, PAGE>(config);
    match bl.state {
        State::Swap => defmt::info!("perpend-boot: new image swapped in, on trial"),
        State::Revert => defmt::info!("perpend-boot: unconfirmed image swapped back"),
        _ => {}
    }
    feed();
    // SAFETY: ACTIVE holds a cortex-m-rt image (vector table first).
    unsafe { bl.load(BANK1_REGION.base() + active) }
}

/// NMI: an ECC double error (RM0440 §5.3.9), which a double word whose
/// programming a power cut tore can raise when it is read, is cleared and
/// the read goes on with the data as read: embassy-boot takes a torn
/// progress word as "not done" (redoes that page copy) or "done" (the copy
/// before it had completed), a torn magic as no request. Without this the
/// bootloader would stop at that read at every start. Any other NMI resets.
#[exception]
unsafe fn NonMaskableInt() {
    let eccr = pac::FLASH.eccr().read();
    if eccr.eccd() {
        // ECCD and ECCC are cleared by writing 1; ECCIE is kept.
        pac::FLASH.eccr().write_value(eccr);
    } else {
        cortex_m::peripheral::SCB::sys_reset();
    }
}

/// A fault: reset (the swap resumes from its progress in STATE).
#[exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    cortex_m::peripheral::SCB::sys_reset()
}

#[panic_handler]
fn panic(_info: &core::panic::PanicInfo) -> ! {
    cortex_m::peripheral::SCB::sys_reset()
}
