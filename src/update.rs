//! The field update's program store on the board: embassy-boot's DFU and
//! STATE partitions ([`crate::flash::Region`]) under
//! `perpend_board::dfu::DfuProgram`, the public key the bootloader holds,
//! and the 0x1F56 identification of the running image.
//!
//! * **Key**: the 32 bytes at [`KEY_ADDR`], the bootloader's `.boot_key`
//!   (boot/memory.x): the key is built into the write-protected
//!   bootloader, never into the application. Without a bootloader the
//!   bytes are erased flash (0xFF), not an ed25519 point: every download
//!   is refused (`ImageError::BadKey`, 0x1F57 signature code).
//! * **Identification**: the signed image is the binary, then its
//!   identity trailer and signature (`perpend_board::image`); the binary
//!   ends where the linker put the last initial value of `.data`
//!   (`__sidata + (__edata - __sdata)`), so the trailer of the running
//!   image is read there. An image flashed unsigned (probe-rs) has none:
//!   0x1F56 is then this build's version with hash byte 0.
//!
//! Limits: not run on silicon.

use perpend_board::dfu::{DfuProgram, DFU_PAGE};
use perpend_board::image::{SIGNATURE_LEN, TRAILER_LEN};
use perpend_board::program::{build_version, trailer_identification};
use static_cell::ConstStaticCell;

use crate::flash::{Region, DFU, STATE};

/// Where the application starts (ACTIVE, src/memory.x FLASH).
const ACTIVE_ORIGIN: u32 = 0x0800_9000;
/// The ACTIVE partition's size: the largest image [bytes].
pub const ACTIVE_LEN: u32 = 220 * 1024;
/// The bootloader's public key (boot/memory.x BOOTKEY).
const KEY_ADDR: u32 = 0x0800_7FE0;

/// The program store of this board.
pub type BoardDfu = DfuProgram<'static, Region, Region>;

/// The program store's page buffer (a static: 2 KiB the store would
/// otherwise carry through `setup`'s frame, issue 50 item 6).
/// Zero here (`.bss`, not 2 KiB of initial values in flash): the store
/// fills it with 0xFF.
static PAGE: ConstStaticCell<[u8; DFU_PAGE]> = ConstStaticCell::new([0; DFU_PAGE]);

/// The store over the DFU and STATE partitions; `enabled` = the flash
/// layout check at boot passed (otherwise every flash access is refused).
/// Called once (the page buffer is taken).
pub fn program(enabled: bool) -> BoardDfu {
    DfuProgram::new(
        Region::new(DFU, enabled),
        Region::new(STATE, enabled),
        PAGE.take(),
        ACTIVE_LEN,
        public_key(),
        identification(),
    )
}

/// The public key in the bootloader.
fn public_key() -> [u8; 32] {
    // SAFETY: 32 bytes of bank 1 flash, always readable.
    unsafe { (KEY_ADDR as *const [u8; 32]).read_volatile() }
}

/// 0x1F56 of the running image (see the module docs).
fn identification() -> u32 {
    unsafe extern "C" {
        static __sidata: u8;
        static __sdata: u8;
        static __edata: u8;
    }
    // Linker symbols: only their addresses are taken.
    let (sidata, sdata, edata) = (
        core::ptr::addr_of!(__sidata) as u32,
        core::ptr::addr_of!(__sdata) as u32,
        core::ptr::addr_of!(__edata) as u32,
    );
    let end = sidata + (edata - sdata);
    let len = (end - ACTIVE_ORIGIN) as usize + TRAILER_LEN + SIGNATURE_LEN;
    if len > ACTIVE_LEN as usize {
        return build_version();
    }
    // SAFETY: inside ACTIVE (checked above), readable flash.
    let img = unsafe { core::slice::from_raw_parts(ACTIVE_ORIGIN as *const u8, len) };
    match trailer_identification(img) {
        0 => build_version(),
        id => id,
    }
}
