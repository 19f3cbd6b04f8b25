//! CiA 302-3 program download, application side: the parts of 0x1F50
//! program data ([`perpend_can::Request::ProgramData`]) go to a
//! [`ProgramStore`], 0x1F51 program control
//! ([`perpend_can::Request::ProgramControl`]) acts on it, and 0x1F56
//! (application software identification) and 0x1F57 (flash status, CiA
//! 302-3 codes of [`perpend_can::od`]) report it.
//!
//! [`RamProgram`] is a store in RAM for the host (the virtual board and
//! tests) that can misbehave on request: refuse a part, or tear it (write
//! half, then fail). On the MCU [`BoardProgram`] is [`NoProgram`] (every
//! download refused, 0x1F57 "flash secured") until the embassy-boot DFU
//! partition is wired in; it costs no RAM.
//!
//! Identification (0x1F56) of a complete program: its CRC-16-CCITT
//! (polynomial 0x1021, initial 0, as the SDO block CRC) in bits 0..15 and
//! its length in KiB, rounded up, in bits 16..31. Limits: one program
//! (sub 1); "start", "stop" and "reset" only change the reported state.

use perpend_can::od::{
    FLASH_ADDRESS_ERROR, FLASH_BUSY, FLASH_NO_PROGRAM, FLASH_OK, FLASH_SECURED, FLASH_WRITE_ERROR,
    PROGRAM_CLEAR, PROGRAM_START,
};
use perpend_can::{Device, Request};

/// Why a program store refused an operation; each maps to a 0x1F57 code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProgramError {
    /// The program does not fit the store (0x1F57 general address error).
    TooLarge,
    /// The store writes nothing now (0x1F57 flash secured).
    Refused,
    /// A write failed part-way (0x1F57 flash write error).
    WriteFailed,
}

impl ProgramError {
    /// The 0x1F57 flash status code.
    pub const fn flash_status(self) -> u32 {
        match self {
            ProgramError::TooLarge => FLASH_ADDRESS_ERROR,
            ProgramError::Refused => FLASH_SECURED,
            ProgramError::WriteFailed => FLASH_WRITE_ERROR,
        }
    }
}

/// Where the downloaded program goes.
pub trait ProgramStore {
    /// Writes `data` at byte `offset`; parts come in order, a part at
    /// offset 0 starts a new program.
    ///
    /// # Errors
    /// The part was not (or not wholly) written.
    fn write(&mut self, offset: u32, data: &[u8]) -> Result<(), ProgramError>;
    /// The program is complete (`len` bytes): its identification (0x1F56).
    ///
    /// # Errors
    /// The program cannot be made valid.
    fn finish(&mut self, len: u32) -> Result<u32, ProgramError>;
    /// Erases the program (0x1F51 "clear").
    ///
    /// # Errors
    /// The erase failed.
    fn clear(&mut self) -> Result<(), ProgramError>;
}

/// The store of the firmware until the DFU partition is wired in: refuses.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoProgram;

impl ProgramStore for NoProgram {
    fn write(&mut self, _offset: u32, _data: &[u8]) -> Result<(), ProgramError> {
        Err(ProgramError::Refused)
    }
    fn finish(&mut self, _len: u32) -> Result<u32, ProgramError> {
        Err(ProgramError::Refused)
    }
    fn clear(&mut self) -> Result<(), ProgramError> {
        Err(ProgramError::Refused)
    }
}

/// A program store in RAM (host only) with injectable faults.
#[cfg(any(test, feature = "std"))]
#[derive(Debug, Clone, Default)]
pub struct RamProgram {
    /// The bytes written.
    pub image: std::vec::Vec<u8>,
    /// Largest program \[bytes\].
    pub capacity: usize,
    /// Refuse the part at this offset.
    pub refuse_at: Option<u32>,
    /// Tear the part at this offset: half of it written, then a failure.
    pub tear_at: Option<u32>,
}

#[cfg(any(test, feature = "std"))]
impl RamProgram {
    /// An empty store of `capacity` bytes.
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity,
            ..Self::default()
        }
    }
}

#[cfg(any(test, feature = "std"))]
impl ProgramStore for RamProgram {
    fn write(&mut self, offset: u32, data: &[u8]) -> Result<(), ProgramError> {
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
    fn finish(&mut self, len: u32) -> Result<u32, ProgramError> {
        if self.image.len() != len as usize {
            return Err(ProgramError::WriteFailed);
        }
        Ok(identification(&self.image))
    }
    fn clear(&mut self) -> Result<(), ProgramError> {
        self.image.clear();
        Ok(())
    }
}

/// 0x1F56 of a program: CRC-16-CCITT in bits 0..15, length in KiB
/// (rounded up, saturated) in bits 16..31.
pub fn identification(image: &[u8]) -> u32 {
    let kib = image.len().div_ceil(1024).min(0xFFFF) as u32;
    (kib << 16) | u32::from(perpend_can::sdo_block::crc16_ccitt(image, 0))
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
    /// 0x1F56: identification of the valid program (0: none).
    pub identification: u32,
    /// 0x1F57: flash status.
    pub flash_status: u32,
    /// 0x1F51 "start" was accepted.
    pub running: bool,
}

impl Default for ProgramState {
    fn default() -> Self {
        Self {
            identification: 0,
            flash_status: FLASH_NO_PROGRAM,
            running: false,
        }
    }
}

/// Carries out `req` if it is a program request: `Some(ok)` (then call
/// `Device::finish_request(ok)`), `None` for any other request. 0x1F56 and
/// 0x1F57 are updated on `dev`.
pub fn serve<P: ProgramStore>(
    store: &mut P,
    state: &mut ProgramState,
    dev: &mut Device,
    req: Request,
) -> Option<bool> {
    let r: Result<u32, u32> = match req {
        Request::ProgramData { offset, len, last } => {
            if offset == 0 {
                *state = ProgramState::default();
            }
            let written = store.write(offset, dev.program_part());
            match written.and_then(|()| {
                last.then(|| store.finish(offset + u32::from(len)))
                    .transpose()
            }) {
                Ok(Some(id)) => {
                    state.identification = id;
                    Ok(FLASH_OK)
                }
                Ok(None) => Ok(FLASH_BUSY),
                Err(e) => Err(e.flash_status()),
            }
        }
        Request::ProgramControl(PROGRAM_CLEAR) => match store.clear() {
            Ok(()) => {
                *state = ProgramState::default();
                Ok(FLASH_NO_PROGRAM)
            }
            Err(e) => Err(e.flash_status()),
        },
        // Nothing valid to start.
        Request::ProgramControl(PROGRAM_START) if state.identification == 0 => {
            Err(FLASH_NO_PROGRAM)
        }
        Request::ProgramControl(cmd) => {
            state.running = cmd == PROGRAM_START;
            Ok(state.flash_status)
        }
        _ => return None,
    };
    let ok = r.is_ok();
    state.flash_status = r.unwrap_or_else(|status| status);
    publish(state, dev);
    Some(ok)
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

    fn image(n: usize) -> Vec<u8> {
        (0..n).map(|i| (i * 13 + 5) as u8).collect()
    }

    #[test]
    fn segmented_download_then_start_and_clear() {
        let mut rig = Rig::new(8192);
        assert_eq!(rig.read(0x1F57), 0, "before the application publishes");
        let img = image(3000);
        rig.download(&img).unwrap();
        assert_eq!(rig.store.image, img);
        assert_eq!(rig.read(0x1F56), identification(&img));
        assert_eq!(rig.read(0x1F56) >> 16, 3, "3000 bytes: 3 KiB");
        assert_eq!(rig.read(0x1F57), FLASH_OK);
        assert_eq!(rig.control(PROGRAM_START)[0], 0x60);
        assert!(rig.state.running);
        assert_eq!(rig.control(PROGRAM_STOP)[0], 0x60);
        assert!(!rig.state.running);
        assert_eq!(rig.control(PROGRAM_CLEAR)[0], 0x60);
        assert!(rig.store.image.is_empty());
        assert_eq!(rig.read(0x1F57), FLASH_NO_PROGRAM);
        // Nothing to start now.
        let r = rig.control(PROGRAM_START);
        assert_eq!(u32::from_le_bytes([r[4], r[5], r[6], r[7]]), 0x0800_0020);
    }

    #[test]
    fn refused_torn_and_oversize_programs_report_their_flash_status() {
        let img = image(2000);
        let mut rig = Rig::new(8192);
        rig.store.refuse_at = Some(0);
        assert_eq!(rig.download(&img), Err(0x0800_0020));
        assert_eq!(rig.read(0x1F57), perpend_can::od::FLASH_SECURED);
        let mut rig = Rig::new(8192);
        rig.store.tear_at = Some(889);
        assert_eq!(rig.download(&img), Err(0x0800_0020));
        assert_eq!(rig.read(0x1F57), perpend_can::od::FLASH_WRITE_ERROR);
        assert_eq!(rig.read(0x1F56), 0, "no valid program");
        assert_eq!(rig.store.image.len(), 889 + 889 / 2, "the torn part");
        let mut rig = Rig::new(1000);
        assert_eq!(rig.download(&img), Err(0x0800_0020));
        assert_eq!(rig.read(0x1F57), perpend_can::od::FLASH_ADDRESS_ERROR);
        // The MCU's store refuses everything.
        assert_eq!(NoProgram.write(0, &[1]), Err(ProgramError::Refused));
    }
}
