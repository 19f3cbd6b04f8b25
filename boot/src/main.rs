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

/// The public key images must verify against (32 bytes, RFC 8032), at
/// 0x0800_7FE0 (`.boot_key`, memory.x): the application reads it there.
#[used]
#[unsafe(link_section = ".boot_key")]
pub static PUBLIC_KEY: [u8; 32] = *include_bytes!(concat!(env!("OUT_DIR"), "/public_key.bin"));

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

#[entry]
fn main() -> ! {
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
