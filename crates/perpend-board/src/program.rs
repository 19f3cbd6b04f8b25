//! CiA 302-3 program download, application side: the parts of 0x1F50
//! program data ([`perpend_can::Request::ProgramData`]) go to a
//! [`ProgramStore`] (the DFU partition), 0x1F51 program control
//! ([`perpend_can::Request::ProgramControl`]) acts on it, and 0x1F56
//! (application software identification of the ACTIVE image) and 0x1F57
//! (flash status, CiA 302-3 codes of [`perpend_can::od`]) report it.
//!
//! A downloaded image is verified ([`crate::image::verify`]: embassy-boot's
//! ed25519 signature, product code, SHA-256) when its last part arrives; a
//! refused image raises EMCY [`EMCY_PROGRAM_REFUSED`] and sets 0x1F57, and
//! "start" is then refused: only a verified image is ever marked for the
//! bootloader's swap, the active image is never written.
//!
//! [`RamProgram`] is a store in RAM for the host (the virtual board and
//! tests) with the bootloader's part modelled (swap at reset, rollback of
//! an image that did not confirm itself) and faults on request: refuse a
//! part, or tear it (write half, then fail). On the MCU [`BoardProgram`] is
//! [`NoProgram`] (every download refused, 0x1F57 "flash secured"); the
//! firmware gives the App its embassy-boot DFU partition instead
//! (`crate::dfu::DfuProgram`, `App::with_program`).
//!
//! Limits: one program (sub 1); "stop" and "reset" only change the
//! reported state.

use crate::image::{self, ImageError, Trust};
use perpend_can::od::{
    FLASH_ADDRESS_ERROR, FLASH_BUSY, FLASH_FORMAT_ERROR, FLASH_FORMAT_UNKNOWN, FLASH_NO_PROGRAM,
    FLASH_OK, FLASH_SECURED, FLASH_WRITE_ERROR, PROGRAM_CLEAR, PROGRAM_START,
};
use perpend_can::status::error_register;
use perpend_can::{Device, Request};

/// EMCY of a refused image (CiA 301 0x6200 "user software"); manufacturer
/// bytes 0-1: the 0x1F57 code, byte 2: [`ImageError::code`].
pub const EMCY_PROGRAM_REFUSED: u16 = 0x6200;
/// 0x1F57, manufacturer-specific (CiA 302-3 codes 64..127): the image is
/// for another product code.
pub const FLASH_WRONG_PRODUCT: u32 = 64 << 1;
/// 0x1F57, manufacturer-specific: the signature does not verify.
pub const FLASH_BAD_SIGNATURE: u32 = 65 << 1;
/// 0x1F57, manufacturer-specific: the image is older than the running one
/// (versions only go up; `image::FLAG_ALLOW_DOWNGRADE` overrides).
pub const FLASH_DOWNGRADE: u32 = 66 << 1;

/// Why a program store refused an operation; each maps to a 0x1F57 code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProgramError {
    /// The program does not fit the store (0x1F57 general address error).
    TooLarge,
    /// The store writes nothing now (0x1F57 flash secured).
    Refused,
    /// A write failed part-way (0x1F57 flash write error).
    WriteFailed,
    /// The image is refused ([`crate::image::verify`]).
    Image(ImageError),
}

impl ProgramError {
    /// The 0x1F57 flash status code.
    pub const fn flash_status(self) -> u32 {
        match self {
            ProgramError::TooLarge => FLASH_ADDRESS_ERROR,
            ProgramError::Refused => FLASH_SECURED,
            ProgramError::WriteFailed | ProgramError::Image(ImageError::Read) => FLASH_WRITE_ERROR,
            ProgramError::Image(ImageError::Unsigned) => FLASH_FORMAT_UNKNOWN,
            ProgramError::Image(ImageError::Truncated | ImageError::BadHash) => FLASH_FORMAT_ERROR,
            ProgramError::Image(ImageError::WrongProduct) => FLASH_WRONG_PRODUCT,
            ProgramError::Image(ImageError::BadSignature | ImageError::BadKey) => {
                FLASH_BAD_SIGNATURE
            }
            ProgramError::Image(ImageError::Downgrade) => FLASH_DOWNGRADE,
        }
    }
}

/// Where the downloaded program goes (the DFU partition) and the
/// bootloader state beside it.
pub trait ProgramStore {
    /// Writes `data` at byte `offset`; parts come in order, a part at
    /// offset 0 starts a new program.
    ///
    /// # Errors
    /// The part was not (or not wholly) written.
    fn write(&mut self, offset: u32, data: &[u8]) -> Result<(), ProgramError>;
    /// The program is complete (`len` bytes).
    ///
    /// # Errors
    /// Not `len` bytes were written.
    fn finish(&mut self, len: u32) -> Result<(), ProgramError>;
    /// Reads the downloaded program back.
    ///
    /// # Errors
    /// Outside what was written, or the read failed.
    fn read(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), ProgramError>;
    /// Erases the program (0x1F51 "clear").
    ///
    /// # Errors
    /// The erase failed.
    fn clear(&mut self) -> Result<(), ProgramError>;
    /// Asks the bootloader to swap the (verified) program in at the next
    /// reset (embassy-boot `mark_updated`).
    ///
    /// # Errors
    /// The state could not be written.
    fn mark_updated(&mut self) -> Result<(), ProgramError>;
    /// The running image has come up completely: no rollback at the next
    /// reset (embassy-boot `mark_booted`).
    ///
    /// # Errors
    /// The state could not be written.
    fn mark_booted(&mut self) -> Result<(), ProgramError>;
    /// Whether the running image is on trial: swapped in by the
    /// bootloader and not confirmed (embassy-boot STATE still says
    /// `Swap`). Asked once at boot (`confirm.rs`, the trial deadline).
    fn on_trial(&mut self) -> bool;
    /// 0x1F56 of the ACTIVE (running) image ([`image::Identity::identification`]).
    fn active(&self) -> u32;
    /// The ed25519 public key images must verify against.
    fn public_key(&self) -> [u8; 32];
}

/// The store of the firmware until the DFU partition is wired in: refuses.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoProgram;

impl ProgramStore for NoProgram {
    fn write(&mut self, _offset: u32, _data: &[u8]) -> Result<(), ProgramError> {
        Err(ProgramError::Refused)
    }
    fn finish(&mut self, _len: u32) -> Result<(), ProgramError> {
        Err(ProgramError::Refused)
    }
    fn read(&mut self, _offset: u32, _buf: &mut [u8]) -> Result<(), ProgramError> {
        Err(ProgramError::Refused)
    }
    fn clear(&mut self) -> Result<(), ProgramError> {
        Err(ProgramError::Refused)
    }
    fn mark_updated(&mut self) -> Result<(), ProgramError> {
        Err(ProgramError::Refused)
    }
    fn mark_booted(&mut self) -> Result<(), ProgramError> {
        Ok(())
    }
    fn on_trial(&mut self) -> bool {
        false
    }
    fn active(&self) -> u32 {
        build_version()
    }
    fn public_key(&self) -> [u8; 32] {
        [0; 32]
    }
}

/// The version of this build (`CARGO_PKG_VERSION`) as an
/// [`image::Identity::version`].
pub const fn build_version() -> u32 {
    (version_part(env!("CARGO_PKG_VERSION_MAJOR")) << 16)
        | (version_part(env!("CARGO_PKG_VERSION_MINOR")) << 8)
        | version_part(env!("CARGO_PKG_VERSION_PATCH"))
}

/// One part of a version, saturated to a byte.
const fn version_part(s: &str) -> u32 {
    match u32::from_str_radix(s, 10) {
        Ok(v) if v < 256 => v,
        _ => 255,
    }
}

/// The bootloader's state in [`RamProgram`] (embassy-boot's STATE
/// partition: `Boot`, `Swap` requested, swapped and on trial).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BootState {
    /// The active image is confirmed.
    #[default]
    Boot,
    /// `mark_updated`: swap at the next reset.
    SwapPending,
    /// Swapped; rolled back at the next reset unless `mark_booted`.
    Trial,
}

/// A program store in RAM (host only) with the bootloader modelled and
/// injectable faults.
#[cfg(any(test, feature = "std"))]
#[derive(Debug, Clone, Default)]
pub struct RamProgram {
    /// The DFU partition: the bytes written.
    pub image: std::vec::Vec<u8>,
    /// The ACTIVE partition: the running signed image.
    pub active_image: std::vec::Vec<u8>,
    /// Largest program \[bytes\] (the DFU partition).
    pub capacity: usize,
    /// Refuse the part at this offset.
    pub refuse_at: Option<u32>,
    /// Tear the part at this offset: half of it written, then a failure.
    pub tear_at: Option<u32>,
    /// The public key of the bootloader.
    pub key: [u8; 32],
    /// The bootloader state.
    pub boot: BootState,
}

#[cfg(any(test, feature = "std"))]
impl RamProgram {
    /// An empty store of `capacity` bytes trusting the test key.
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity,
            key: image::public_key(&image::TEST_SEED),
            ..Self::default()
        }
    }

    /// What the bootloader does at a reset: swap a marked image in, or
    /// swap back an image on trial that did not confirm itself (rollback).
    /// Returns the new state.
    pub fn reset(&mut self) -> BootState {
        self.boot = match self.boot {
            BootState::SwapPending => {
                std::mem::swap(&mut self.image, &mut self.active_image);
                BootState::Trial
            }
            BootState::Trial => {
                std::mem::swap(&mut self.image, &mut self.active_image);
                BootState::Boot
            }
            BootState::Boot => BootState::Boot,
        };
        self.boot
    }
}

#[cfg(any(test, feature = "std"))]
impl ProgramStore for RamProgram {
    fn write(&mut self, offset: u32, data: &[u8]) -> Result<(), ProgramError> {
        if self.boot != BootState::Boot {
            // embassy-boot: only a confirmed image may write the DFU.
            return Err(ProgramError::Refused);
        }
        if offset == 0 {
            self.image.clear();
        }
        if self.refuse_at == Some(offset) {
            return Err(ProgramError::Refused);
        }
        if offset as usize != self.image.len() || self.image.len() + data.len() > self.capacity {
            return Err(ProgramError::TooLarge);
        }
        if self.tear_at == Some(offset) {
            self.image.extend_from_slice(&data[..data.len() / 2]);
            return Err(ProgramError::WriteFailed);
        }
        self.image.extend_from_slice(data);
        Ok(())
    }
    fn finish(&mut self, len: u32) -> Result<(), ProgramError> {
        if self.image.len() != len as usize {
            return Err(ProgramError::WriteFailed);
        }
        Ok(())
    }
    fn read(&mut self, offset: u32, buf: &mut [u8]) -> Result<(), ProgramError> {
        let o = offset as usize;
        let src = o
            .checked_add(buf.len())
            .and_then(|end| self.image.get(o..end))
            .ok_or(ProgramError::Image(ImageError::Read))?;
        buf.copy_from_slice(src);
        Ok(())
    }
    fn clear(&mut self) -> Result<(), ProgramError> {
        self.image.clear();
        Ok(())
    }
    fn mark_updated(&mut self) -> Result<(), ProgramError> {
        if self.boot != BootState::Boot {
            return Err(ProgramError::Refused);
        }
        self.boot = BootState::SwapPending;
        Ok(())
    }
    fn mark_booted(&mut self) -> Result<(), ProgramError> {
        if self.boot == BootState::Trial {
            self.boot = BootState::Boot;
        }
        Ok(())
    }
    fn on_trial(&mut self) -> bool {
        self.boot == BootState::Trial
    }
    fn active(&self) -> u32 {
        trailer_identification(&self.active_image)
    }
    fn public_key(&self) -> [u8; 32] {
        self.key
    }
}

/// 0x1F56 of a signed image from its trailer (0: no trailer). The image
/// was verified before it became active; this only reads it.
pub fn trailer_identification(img: &[u8]) -> u32 {
    let end = img.len().saturating_sub(image::SIGNATURE_LEN);
    img.get(end.saturating_sub(image::TRAILER_LEN)..end)
        .and_then(|t| <&[u8; image::TRAILER_LEN]>::try_from(t).ok())
        .and_then(|t| image::Identity::from_bytes(t).ok())
        .map_or(0, |id| id.identification())
}

/// The store of this build: [`RamProgram`] (256 KiB) on the host,
/// [`NoProgram`] on the MCU.
#[cfg(any(test, feature = "std"))]
pub type BoardProgram = RamProgram;
/// The store of this build: [`RamProgram`] (256 KiB) on the host,
/// [`NoProgram`] on the MCU.
#[cfg(not(any(test, feature = "std")))]
pub type BoardProgram = NoProgram;

/// A new [`BoardProgram`].
pub fn board_program() -> BoardProgram {
    #[cfg(any(test, feature = "std"))]
    return RamProgram::new(256 * 1024);
    #[cfg(not(any(test, feature = "std")))]
    NoProgram
}

/// What the program side reports in 0x1F56 / 0x1F57.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProgramState {
    /// 0x1F56: identification of the ACTIVE image.
    pub identification: u32,
    /// 0x1F57: flash status.
    pub flash_status: u32,
    /// Identification of the verified image in the DFU partition (0: none).
    pub staged: u32,
    /// 0x1F51 "start" was accepted: the swap is marked.
    pub running: bool,
}

impl Default for ProgramState {
    fn default() -> Self {
        Self {
            identification: 0,
            flash_status: FLASH_NO_PROGRAM,
            staged: 0,
            running: false,
        }
    }
}

impl ProgramState {
    /// The state at boot of a store: its active image's identification.
    pub fn of<P: ProgramStore>(store: &P) -> Self {
        Self {
            identification: store.active(),
            ..Self::default()
        }
    }
}

/// Carries out `req` if it is a program request: `Some(ok)` (then call
/// `Device::finish_request(ok)`), `None` for any other request. 0x1F56 and
/// 0x1F57 are updated on `dev`; a refused image raises
/// [`EMCY_PROGRAM_REFUSED`].
pub fn serve<P: ProgramStore>(
    store: &mut P,
    state: &mut ProgramState,
    dev: &mut Device,
    req: Request,
) -> Option<bool> {
    let r: Result<u32, ProgramError> = match req {
        Request::ProgramData { offset, len, last } => {
            if offset == 0 {
                state.staged = 0;
                state.running = false;
                dev.clear_emcy(EMCY_PROGRAM_REFUSED);
            }
            let product = dev.defaults().identity.product_code;
            let part = store.write(offset, dev.program_part());
            part.and_then(|()| match last {
                true => check(store, offset + u32::from(len), product).map(|id| {
                    state.staged = id;
                    FLASH_OK
                }),
                false => Ok(FLASH_BUSY),
            })
        }
        Request::ProgramControl(PROGRAM_CLEAR) => store.clear().map(|()| {
            state.staged = 0;
            state.running = false;
            FLASH_NO_PROGRAM
        }),
        // Nothing verified to start.
        Request::ProgramControl(PROGRAM_START) if state.staged == 0 => {
            return Some(report(state, dev, Err(FLASH_NO_PROGRAM), 0));
        }
        Request::ProgramControl(PROGRAM_START) => store.mark_updated().map(|()| {
            state.running = true;
            state.flash_status
        }),
        Request::ProgramControl(_) => Ok(state.flash_status),
        _ => return None,
    };
    let code = match r {
        Err(ProgramError::Image(e)) => e.code(),
        _ => 0,
    };
    state.identification = store.active();
    Some(report(
        state,
        dev,
        r.map_err(ProgramError::flash_status),
        code,
    ))
}

/// Finishes and verifies a downloaded program of `len` bytes: its 0x1F56.
fn check<P: ProgramStore>(store: &mut P, len: u32, product: u32) -> Result<u32, ProgramError> {
    store.finish(len)?;
    let trust = Trust {
        public_key: store.public_key(),
        product,
    };
    let read = |o: u32, b: &mut [u8]| store.read(o, b).map_err(|_| ImageError::Read);
    let id = image::verify(read, len, &trust).map_err(ProgramError::Image)?;
    image::check_version(&id, store.active()).map_err(ProgramError::Image)?;
    Ok(id.identification())
}

/// Sets the flash status from `r`, raises the EMCY of a refused image
/// (`code` ≠ 0) and publishes; whether the request succeeded.
fn report(state: &mut ProgramState, dev: &mut Device, r: Result<u32, u32>, code: u8) -> bool {
    state.flash_status = r.unwrap_or_else(|status| status);
    if code != 0 {
        let s = (state.flash_status as u16).to_le_bytes();
        dev.signal_emcy(
            EMCY_PROGRAM_REFUSED,
            error_register::GENERIC,
            [s[0], s[1], code, 0, 0],
        );
    }
    publish(state, dev);
    r.is_ok()
}

/// Writes `state` to 0x1F56 / 0x1F57 (also after a reset node, which puts
/// them back to 0).
pub fn publish(state: &ProgramState, dev: &mut Device) {
    dev.set_program_status(state.identification, state.flash_status);
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use perpend_can::od::{FLASH_NO_PROGRAM, PROGRAM_STOP};
    use perpend_can::{Defaults, Frame};

    /// A device in pre-operational and the program side beside it.
    struct Rig {
        dev: Device,
        store: RamProgram,
        state: ProgramState,
        now: u64,
    }

    impl Rig {
        fn new(capacity: usize) -> Self {
            let mut dev = Device::new(5, &Defaults::nominal());
            dev.poll(0, &mut |_| {});
            Self {
                dev,
                store: RamProgram::new(capacity),
                state: ProgramState::default(),
                now: 0,
            }
        }
        /// One SDO request; pending program requests served at once.
        fn sdo(&mut self, req: [u8; 8]) -> Option<[u8; 8]> {
            self.now += 100;
            let mut out = Vec::new();
            self.dev
                .handle(&Frame::new(0x605, &req), self.now, &mut |f| out.push(f));
            if let Some(r) = self.dev.pending_request() {
                let ok = serve(&mut self.store, &mut self.state, &mut self.dev, r).unwrap();
                self.dev.finish_request(ok, &mut |f| out.push(f)).unwrap();
            }
            out.first().map(|f| f.data)
        }
        /// Segmented download of `data` to 0x1F50 sub 1: abort code or Ok.
        fn download(&mut self, data: &[u8]) -> Result<(), u32> {
            let l = (data.len() as u32).to_le_bytes();
            let mut r = self
                .sdo([0x21, 0x50, 0x1F, 1, l[0], l[1], l[2], l[3]])
                .unwrap();
            let mut t = 0u8;
            for (k, c) in data.chunks(7).enumerate() {
                if r[0] == 0x80 {
                    break;
                }
                let last = (k + 1) * 7 >= data.len();
                let mut f = [0u8; 8];
                f[0] = t | (((7 - c.len()) as u8) << 1) | u8::from(last);
                f[1..1 + c.len()].copy_from_slice(c);
                r = self.sdo(f).unwrap();
                t ^= 0x10;
            }
            if r[0] == 0x80 {
                return Err(u32::from_le_bytes([r[4], r[5], r[6], r[7]]));
            }
            Ok(())
        }
        fn read(&mut self, index: u16) -> u32 {
            let i = index.to_le_bytes();
            let r = self.sdo([0x40, i[0], i[1], 1, 0, 0, 0, 0]).unwrap();
            u32::from_le_bytes([r[4], r[5], r[6], r[7]])
        }
        fn control(&mut self, cmd: u8) -> [u8; 8] {
            self.sdo([0x2F, 0x51, 0x1F, 1, cmd, 0, 0, 0]).unwrap()
        }
    }

    const PRODUCT: u32 = 0x5045_5250;

    fn payload(n: usize) -> Vec<u8> {
        (0..n).map(|i| (i * 13 + 5) as u8).collect()
    }

    /// A signed image of `n` payload bytes for this board.
    fn signed(n: usize, version: u32) -> Vec<u8> {
        image::sign(&payload(n), PRODUCT, version, &image::TEST_SEED)
    }

    fn abort(r: [u8; 8]) -> u32 {
        u32::from_le_bytes([r[4], r[5], r[6], r[7]])
    }

    /// A rig whose active image is version 1.0.0.
    fn running_v1(capacity: usize) -> Rig {
        let mut rig = Rig::new(capacity);
        rig.store.active_image = signed(500, image::version(1, 0, 0));
        rig.state = ProgramState::of(&rig.store);
        publish(&rig.state, &mut rig.dev);
        assert_eq!(rig.read(0x1F56) & 0xFF_FFFF, 0x01_00_00);
        rig
    }

    #[test]
    fn a_signed_download_is_started_swapped_in_and_confirmed() {
        let mut rig = running_v1(8192);
        let v1 = rig.store.active_image.clone();
        let img = signed(3000, image::version(1, 1, 0));
        rig.download(&img).unwrap();
        assert_eq!(rig.store.image, img);
        assert_eq!(rig.read(0x1F57), FLASH_OK);
        assert_eq!(rig.read(0x1F56) & 0xFF_FFFF, 0x01_00_00, "still v1 active");
        assert_eq!(rig.control(PROGRAM_START)[0], 0x60);
        assert_eq!(rig.store.boot, BootState::SwapPending);
        assert_eq!(
            rig.store.active_image, v1,
            "nothing swapped before the reset"
        );
        assert_eq!(rig.store.reset(), BootState::Trial);
        assert_eq!(rig.store.active_image, img);
        assert_eq!(rig.store.active(), trailer_identification(&img));
        assert_eq!(rig.store.active() & 0xFF_FFFF, 0x01_01_00);
        rig.store.mark_booted().unwrap();
        assert_eq!(rig.store.reset(), BootState::Boot, "confirmed: stays");
        assert_eq!(rig.store.active_image, img);
    }

    #[test]
    fn an_image_that_does_not_confirm_is_rolled_back_at_the_next_reset() {
        let mut rig = running_v1(8192);
        let v1 = rig.store.active_image.clone();
        rig.download(&signed(2000, image::version(2, 0, 0)))
            .unwrap();
        assert_eq!(rig.control(PROGRAM_START)[0], 0x60);
        rig.store.reset();
        // No mark_booted: a DFU write is refused on trial, then rollback.
        assert_eq!(rig.store.write(0, &[1]), Err(ProgramError::Refused));
        assert_eq!(rig.store.reset(), BootState::Boot);
        assert_eq!(rig.store.active_image, v1);
    }

    /// Downloads `img`, expects the refusal `status` with EMCY, START
    /// refused, and the active image untouched.
    fn refused(img: &[u8], status: u32, code: ImageError) {
        let mut rig = running_v1(8192);
        let v1 = rig.store.active_image.clone();
        let id = rig.read(0x1F56);
        assert_eq!(rig.download(img), Err(0x0800_0020));
        assert_eq!(rig.read(0x1F57), status, "{code:?}");
        assert!(rig.dev.emcy_active(EMCY_PROGRAM_REFUSED), "{code:?}");
        assert_eq!(rig.read(0x1F56), id, "the active identification");
        assert_eq!(abort(rig.control(PROGRAM_START)), 0x0800_0020);
        assert_eq!(rig.store.boot, BootState::Boot, "{code:?}: no swap");
        rig.store.reset();
        assert_eq!(rig.store.active_image, v1, "{code:?}");
        // A good image afterwards clears the EMCY and is accepted.
        rig.download(&signed(100, image::version(1, 0, 7))).unwrap();
        assert!(!rig.dev.emcy_active(EMCY_PROGRAM_REFUSED));
    }

    #[test]
    fn a_wrong_signature_is_refused() {
        let mut img = signed(1500, 9);
        img[10] ^= 0x80;
        refused(&img, FLASH_BAD_SIGNATURE, ImageError::BadSignature);
        let stranger = image::sign(&payload(1500), PRODUCT, 9, &[3u8; 32]);
        refused(&stranger, FLASH_BAD_SIGNATURE, ImageError::BadSignature);
    }

    #[test]
    fn an_unsigned_or_truncated_image_is_refused() {
        refused(&payload(1500), FLASH_FORMAT_UNKNOWN, ImageError::Unsigned);
        let img = signed(1500, 9);
        refused(
            &img[..img.len() - 30],
            FLASH_FORMAT_UNKNOWN,
            ImageError::Unsigned,
        );
        refused(&img[..100], FLASH_FORMAT_ERROR, ImageError::Truncated);
    }

    #[test]
    fn an_older_image_is_refused_unless_signed_to_allow_it() {
        // running v1.0.0
        refused(
            &signed(1500, image::version(0, 9, 0)),
            FLASH_DOWNGRADE,
            ImageError::Downgrade,
        );
        let mut rig = running_v1(8192);
        let old = image::sign_with_flags(
            &payload(1500),
            PRODUCT,
            image::version(0, 9, 0),
            image::FLAG_ALLOW_DOWNGRADE,
            &image::TEST_SEED,
        );
        rig.download(&old).unwrap();
        assert_eq!(rig.control(PROGRAM_START)[0], 0x60);
    }

    #[test]
    fn an_image_for_another_board_is_refused() {
        let img = image::sign(&payload(1500), PRODUCT ^ 1, 9, &image::TEST_SEED);
        refused(&img, FLASH_WRONG_PRODUCT, ImageError::WrongProduct);
    }

    #[test]
    fn start_without_a_program_and_clear() {
        let mut rig = running_v1(8192);
        assert_eq!(abort(rig.control(PROGRAM_START)), 0x0800_0020);
        assert_eq!(rig.read(0x1F57), FLASH_NO_PROGRAM);
        rig.download(&signed(100, image::version(1, 0, 1))).unwrap();
        assert_eq!(rig.control(PROGRAM_STOP)[0], 0x60);
        assert_eq!(rig.control(PROGRAM_CLEAR)[0], 0x60);
        assert!(rig.store.image.is_empty());
        assert_eq!(abort(rig.control(PROGRAM_START)), 0x0800_0020);
    }

    #[test]
    fn refused_torn_and_oversize_programs_report_their_flash_status() {
        let img = signed(2000, 1);
        let mut rig = running_v1(8192);
        rig.store.refuse_at = Some(0);
        assert_eq!(rig.download(&img), Err(0x0800_0020));
        assert_eq!(rig.read(0x1F57), perpend_can::od::FLASH_SECURED);
        let mut rig = running_v1(8192);
        rig.store.tear_at = Some(889);
        assert_eq!(rig.download(&img), Err(0x0800_0020));
        assert_eq!(rig.read(0x1F57), perpend_can::od::FLASH_WRITE_ERROR);
        assert_eq!(rig.store.image.len(), 889 + 889 / 2, "the torn part");
        assert_eq!(abort(rig.control(PROGRAM_START)), 0x0800_0020);
        let mut rig = running_v1(1000);
        assert_eq!(rig.download(&img), Err(0x0800_0020));
        assert_eq!(rig.read(0x1F57), perpend_can::od::FLASH_ADDRESS_ERROR);
        assert_eq!(abort(rig.control(PROGRAM_START)), 0x0800_0020);
        // The MCU's store refuses everything.
        assert_eq!(NoProgram.write(0, &[1]), Err(ProgramError::Refused));
        assert_eq!(NoProgram.active(), build_version());
    }
}
