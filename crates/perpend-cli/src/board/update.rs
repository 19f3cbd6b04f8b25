//! The virtual board's side of the field update: its flash fake
//! ([`perpend_board::program::RamProgram`], the same store and verification
//! code the firmware runs, trusting the test key `keys/test-only.pk`) and
//! the restart the real board makes after 0x1F51 "start": the bootloader
//! swaps the verified image in, the application comes up again from the
//! same parameter storage (calibration kept) and confirms the image
//! (`mark_booted`) once it runs. With `--fault update:no-confirm` the new
//! image hangs at start instead: nothing is sent, and after
//! [`WATCHDOG_US`] the watchdog resets the board and the bootloader rolls
//! back to the old image.
//!
//! Limits: the "images" are a signed payload of a few bytes (the version
//! in the trailer is what the host sees); no power cut inside the swap.

use perpend_board::app::App;
use perpend_board::image;
use perpend_board::program::{build_version, RamProgram};
use perpend_board::storage::{host_store, HostFlash, SeqStore};

/// The application type of the virtual board (defined here, beside its
/// flash fake, so that this module does not import `node`).
pub type HostApp = App<SeqStore<HostFlash>>;

/// The largest image the virtual board takes \[bytes\]: the planned ACTIVE
/// partition (docs/firmware.md; the DFU partition is one page larger).
pub const DFU_BYTES: usize = 220 * 1024;
/// How long a new image that never confirms itself hangs before the
/// watchdog resets the board \[µs\].
pub const WATCHDOG_US: u64 = 500_000;

/// The payload of the image the virtual board runs from the factory.
const FACTORY_PAYLOAD: &[u8] = b"perpend virtual board factory image";

/// The flash fake of a new board: the factory image (this build's
/// version, signed with the test key) active, the DFU empty.
pub fn factory_program(product: u32) -> RamProgram {
    let mut p = RamProgram::new(DFU_BYTES);
    p.active_image = image::sign(FACTORY_PAYLOAD, product, build_version(), &image::TEST_SEED);
    p
}

/// A reset of the board: the bootloader acts on the flash fake
/// ([`RamProgram::reset`]: swap or rollback), then the application boots
/// again from the same parameter storage with the same serial number.
pub fn reboot(app: &mut HostApp, serial: u32) {
    let mut program = std::mem::take(app.program_mut());
    program.reset();
    let blank = App::with_serial(host_store(HostFlash::new()), serial);
    let store = std::mem::replace(app, blank).into_store();
    *app = App::with_serial(store, serial);
    app.set_program(program);
}
