//! Host tests of the field update on embassy-boot's real code: the
//! download through [`crate::dfu::DfuProgram`] (embassy-boot's
//! `BlockingFirmwareUpdater`) and the swap, rollback and confirmation by
//! embassy-boot's `BootLoader::prepare_boot`, on a NOR flash fake with the
//! STM32G4 geometry (2 KiB pages, 8-byte writes, a written double word may
//! only be overwritten with zeros, RM0440 PROGERR) and a power cut after
//! the k-th erase/write, for every k, atomic or tearing the k-th
//! operation (half done, the rest garbage).
//!
//! The layout is the board's, scaled down (8 ACTIVE pages instead of 110):
//! STATE 2 pages, ACTIVE 8, DFU 9 (ACTIVE + 1), parameters 4 pages.

#![allow(clippy::unwrap_used)]

use core::cell::RefCell;

use embassy_boot::{BootLoader, BootLoaderConfig, State};
use embedded_storage::nor_flash::{
    ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};
use sha2::{Digest, Sha256};

use crate::dfu::{DfuProgram, DFU_PAGE};
use crate::image;
use crate::program::{ProgramError, ProgramStore};

const PAGE: usize = 2048;
const WORD: usize = 8;
const STATE_AT: usize = 0;
const STATE_LEN: usize = 2 * PAGE;
const ACTIVE_AT: usize = STATE_AT + STATE_LEN;
const ACTIVE_LEN: usize = 8 * PAGE;
const DFU_AT: usize = ACTIVE_AT + ACTIVE_LEN;
const DFU_LEN: usize = ACTIVE_LEN + PAGE;
const PARAMS_AT: usize = DFU_AT + DFU_LEN;
const PARAMS_LEN: usize = 4 * PAGE;
const SIZE: usize = PARAMS_AT + PARAMS_LEN;
const PRODUCT: u32 = 0x5045_5250;

/// How the power cut ends the k-th operation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Cut {
    /// The k-th operation completes, nothing after it runs.
    After,
    /// The k-th operation is half done, the rest of its range garbage.
    Torn,
}

/// The flash fake: one memory for every partition, an operation counter
/// and the power cut.
struct Nor {
    mem: Vec<u8>,
    ops: u32,
    cut: Option<(u32, Cut)>,
    /// The power is off (after the cut) until [`Nor::power_on`].
    off: bool,
    /// Erase/write operations inside the parameter pages.
    params_touched: u32,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fault {
    PowerOff,
    Bounds,
    /// A written double word overwritten with non-zero data.
    NotErased,
}

impl NorFlashError for Fault {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            Fault::Bounds => NorFlashErrorKind::OutOfBounds,
            _ => NorFlashErrorKind::Other,
        }
    }
}

impl Nor {
    fn new() -> Self {
        Self {
            mem: vec![0xFF; SIZE],
            ops: 0,
            cut: None,
            off: false,
            params_touched: 0,
        }
    }

    fn power_on(&mut self) {
        self.off = false;
        self.cut = None;
    }

    /// Counts an operation on `range`; what the cut leaves of it.
    fn begin(&mut self, range: core::ops::Range<usize>) -> Result<Option<Cut>, Fault> {
        if self.off {
            return Err(Fault::PowerOff);
        }
        if range.start < PARAMS_AT + PARAMS_LEN && range.end > PARAMS_AT {
            self.params_touched += 1;
        }
        self.ops += 1;
        Ok(match self.cut {
            Some((k, how)) if k == self.ops => {
                self.off = true;
                Some(how)
            }
            _ => None,
        })
    }

    fn garbage(&mut self, range: core::ops::Range<usize>) {
        for (i, b) in self.mem[range].iter_mut().enumerate() {
            *b ^= 0x5A ^ (i as u8);
        }
    }

    fn erase(&mut self, from: usize, to: usize) -> Result<(), Fault> {
        let cut = self.begin(from..to)?;
        let mid = from + ((to - from) / PAGE / 2) * PAGE;
        let end = if cut == Some(Cut::Torn) { mid } else { to };
        self.mem[from..end].fill(0xFF);
        match cut {
            Some(Cut::Torn) => {
                self.mem[mid..mid + PAGE / 2].fill(0xFF);
                self.garbage(mid + PAGE / 2..mid + PAGE);
                Err(Fault::PowerOff)
            }
            Some(Cut::After) => Err(Fault::PowerOff),
            None => Ok(()),
        }
    }

    fn write(&mut self, at: usize, data: &[u8]) -> Result<(), Fault> {
        let cut = self.begin(at..at + data.len())?;
        let words = data.len() / WORD;
        let n = if cut == Some(Cut::Torn) {
            words / 2
        } else {
            words
        };
        for (w, d) in data.chunks_exact(WORD).take(n).enumerate() {
            let o = at + w * WORD;
            let erased = self.mem[o..o + WORD].iter().all(|&b| b == 0xFF);
            if !erased && d.iter().any(|&b| b != 0) {
                return Err(Fault::NotErased);
            }
            for (m, &b) in self.mem[o..o + WORD].iter_mut().zip(d) {
                *m &= b;
            }
        }
        match cut {
            Some(Cut::Torn) => {
                let o = at + n * WORD;
                self.garbage(o..o + WORD.min(data.len() - n * WORD));
                Err(Fault::PowerOff)
            }
            Some(Cut::After) => Err(Fault::PowerOff),
            None => Ok(()),
        }
    }

    fn hash(&self, at: usize, len: usize) -> [u8; 32] {
        Sha256::digest(&self.mem[at..at + len]).into()
    }
}

/// A partition of the fake (offsets from its start).
struct Part<'a> {
    nor: &'a RefCell<Nor>,
    at: usize,
    len: usize,
}

impl ErrorType for Part<'_> {
    type Error = Fault;
}

impl Part<'_> {
    fn check(&self, offset: u32, len: usize) -> Result<usize, Fault> {
        let o = offset as usize;
        if o + len > self.len {
            return Err(Fault::Bounds);
        }
        Ok(self.at + o)
    }
}

impl ReadNorFlash for Part<'_> {
    const READ_SIZE: usize = 1;
    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Fault> {
        let a = self.check(offset, bytes.len())?;
        let nor = self.nor.borrow();
        if nor.off {
            return Err(Fault::PowerOff);
        }
        bytes.copy_from_slice(&nor.mem[a..a + bytes.len()]);
        Ok(())
    }
    fn capacity(&self) -> usize {
        self.len
    }
}

impl NorFlash for Part<'_> {
    const WRITE_SIZE: usize = WORD;
    const ERASE_SIZE: usize = PAGE;
    fn erase(&mut self, from: u32, to: u32) -> Result<(), Fault> {
        let a = self.check(from, (to - from) as usize)?;
        self.nor.borrow_mut().erase(a, a + (to - from) as usize)
    }
    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Fault> {
        let a = self.check(offset, bytes.len())?;
        self.nor.borrow_mut().write(a, bytes)
    }
}

fn part(nor: &RefCell<Nor>, at: usize, len: usize) -> Part<'_> {
    Part { nor, at, len }
}

/// The application's store on the fake.
fn store(nor: &RefCell<Nor>) -> DfuProgram<'static, Part<'_>, Part<'_>> {
    let key = image::public_key(&image::TEST_SEED);
    DfuProgram::new(
        part(nor, DFU_AT, DFU_LEN),
        part(nor, STATE_AT, STATE_LEN),
        Box::leak(Box::new([0xFF; DFU_PAGE])),
        ACTIVE_LEN as u32,
        key,
        1,
    )
}

/// One start of the bootloader (embassy-boot's `prepare_boot` with the
/// real bootloader's one-page buffer).
fn prepare(nor: &RefCell<Nor>) -> Result<State, embassy_boot::BootError> {
    let config = BootLoaderConfig {
        active: part(nor, ACTIVE_AT, ACTIVE_LEN),
        dfu: part(nor, DFU_AT, DFU_LEN),
        state: part(nor, STATE_AT, STATE_LEN),
    };
    let mut buf = [0u8; PAGE];
    BootLoader::new(config).prepare_boot(&mut buf)
}

/// Starts the bootloader until it gets through (each failed start is the
/// power cut; the power comes back for the next).
fn boot(nor: &RefCell<Nor>) -> State {
    for _ in 0..3 {
        match prepare(nor) {
            Ok(s) => return s,
            Err(_) => nor.borrow_mut().power_on(),
        }
    }
    panic!("the bootloader does not get through after a power cut")
}

/// Downloads `img` as the SDO server delivers it (889-byte parts).
fn download(s: &mut impl ProgramStore, img: &[u8]) -> Result<(), ProgramError> {
    for (k, part) in img.chunks(889).enumerate() {
        s.write((k * 889) as u32, part)?;
    }
    s.finish(img.len() as u32)
}

/// A flash with a confirmed old image in ACTIVE, parameters written, and a
/// signed new image downloaded, verified and marked: the hashes of the
/// old ACTIVE, the new one (DFU's first ACTIVE bytes) and the parameters.
fn updated_board(nor: &RefCell<Nor>) -> ([u8; 32], [u8; 32], [u8; 32]) {
    {
        let mut n = nor.borrow_mut();
        for (i, b) in n.mem[ACTIVE_AT..ACTIVE_AT + ACTIVE_LEN]
            .iter_mut()
            .enumerate()
        {
            *b = (i * 7 + 3) as u8;
        }
        for (i, b) in n.mem[PARAMS_AT..SIZE].iter_mut().enumerate() {
            *b = (i * 11) as u8;
        }
    }
    let img = image::sign(
        &(0..11_000).map(|i| (i * 5 + 1) as u8).collect::<Vec<u8>>(),
        PRODUCT,
        image::version(2, 0, 0),
        &image::TEST_SEED,
    );
    let mut s = store(nor);
    s.mark_booted().unwrap();
    download(&mut s, &img).unwrap();
    let trust = image::Trust {
        public_key: s.public_key(),
        product: PRODUCT,
    };
    let read = |o: u32, b: &mut [u8]| s.read(o, b).map_err(|_| image::ImageError::Read);
    image::verify(read, img.len() as u32, &trust).unwrap();
    s.mark_updated().unwrap();
    let n = nor.borrow();
    assert_eq!(&n.mem[DFU_AT..DFU_AT + img.len()], &img[..]);
    (
        n.hash(ACTIVE_AT, ACTIVE_LEN),
        n.hash(DFU_AT, ACTIVE_LEN),
        n.hash(PARAMS_AT, PARAMS_LEN),
    )
}

fn active(nor: &RefCell<Nor>) -> [u8; 32] {
    nor.borrow().hash(ACTIVE_AT, ACTIVE_LEN)
}

#[test]
fn a_download_is_swapped_in_confirmed_and_kept() {
    let nor = RefCell::new(Nor::new());
    let (old, new, params) = updated_board(&nor);
    assert_ne!(old, new);
    assert_eq!(boot(&nor), State::Swap);
    assert_eq!(active(&nor), new);
    let mut s = store(&nor);
    assert_eq!(s.boot_state(), Ok(State::Swap), "on trial");
    assert_eq!(s.write(0, &[0; 889]), Err(ProgramError::Refused));
    s.mark_booted().unwrap();
    assert_eq!(s.boot_state(), Ok(State::Boot));
    assert_eq!(boot(&nor), State::Boot);
    assert_eq!(active(&nor), new, "confirmed: kept");
    assert_eq!(nor.borrow().hash(PARAMS_AT, PARAMS_LEN), params);
    assert_eq!(nor.borrow().params_touched, 0);
}

#[test]
fn a_new_image_that_never_confirms_is_reverted() {
    let nor = RefCell::new(Nor::new());
    let (old, new, _) = updated_board(&nor);
    assert_eq!(boot(&nor), State::Swap);
    assert_eq!(active(&nor), new);
    // Panics, hangs (watchdog) or loses power before `mark_booted`.
    assert_eq!(boot(&nor), State::Swap, "reverting");
    assert_eq!(active(&nor), old);
    assert_eq!(boot(&nor), State::Revert, "stays reverted");
    assert_eq!(active(&nor), old);
    // The old image confirms itself; a new download is allowed again.
    let mut s = store(&nor);
    s.mark_booted().unwrap();
    assert_eq!(s.write(0, &[0; 889]), Ok(()));
}

#[test]
fn unfinished_or_oversize_downloads_are_never_marked() {
    let nor = RefCell::new(Nor::new());
    let mut s = store(&nor);
    s.write(0, &[1; 889]).unwrap();
    assert_eq!(s.mark_updated(), Err(ProgramError::Refused), "not finished");
    assert_eq!(s.finish(900), Err(ProgramError::WriteFailed));
    assert_eq!(s.write(5, &[1; 8]), Err(ProgramError::TooLarge), "a gap");
    let big = vec![0u8; ACTIVE_LEN + 1];
    assert_eq!(download(&mut s, &big), Err(ProgramError::TooLarge));
    assert_eq!(
        s.read(0, &mut [0; 4]),
        Err(ProgramError::Image(image::ImageError::Read))
    );
    assert_eq!(s.boot_state(), Ok(State::Boot));
}

/// The update with the power cut at operation `k` (counted from the
/// first start of the bootloader after the mark) and the new image
/// confirming itself (`confirms`) or not. `None` when the scenario has
/// fewer than `k` operations.
fn cut_scenario(k: u32, how: Cut, confirms: bool) -> Option<()> {
    let nor = RefCell::new(Nor::new());
    let (old, new, params) = updated_board(&nor);
    {
        let mut n = nor.borrow_mut();
        n.ops = 0;
        n.cut = Some((k, how));
        n.params_touched = 0;
    }
    let ctx = format!("cut {how:?} at operation {k}, confirms {confirms}");
    boot(&nor);
    let first = active(&nor);
    assert!(
        first == new || first == old,
        "{ctx}: ACTIVE is neither image"
    );
    let mut s = store(&nor);
    // `None`: the cut ended `mark_booted` (done or not: either image may
    // run next).
    let confirmed = match confirms && first == new {
        true => s.mark_booted().is_ok().then_some(true),
        false => Some(false),
    };
    nor.borrow_mut().power_on();
    boot(&nor);
    let now = active(&nor);
    match confirmed {
        Some(true) => assert_eq!(now, new, "{ctx}: the confirmed image was reverted"),
        Some(false) if first == new => {
            assert_eq!(now, old, "{ctx}: an unconfirmed image stayed")
        }
        _ => {}
    }
    assert!(now == new || now == old, "{ctx}: ACTIVE is neither image");
    // Whatever runs now confirms itself and stays.
    let mut s = store(&nor);
    s.mark_booted().unwrap();
    assert_eq!(boot(&nor), State::Boot, "{ctx}");
    assert_eq!(active(&nor), now, "{ctx}: changed after the confirmation");
    let n = nor.borrow();
    assert_eq!(n.hash(PARAMS_AT, PARAMS_LEN), params, "{ctx}: parameters");
    assert_eq!(n.params_touched, 0, "{ctx}: parameter pages written");
    (n.cut.is_none() && n.ops >= k).then_some(())
}

/// Every cut position of both scenarios, both cut kinds.
fn every_cut(how: Cut, confirms: bool) -> u32 {
    let mut k = 1;
    while cut_scenario(k, how, confirms).is_some() {
        k += 1;
    }
    eprintln!("{how:?}, confirms {confirms}: {} cut positions", k - 1);
    k - 1
}

#[test]
fn a_power_cut_at_every_step_of_the_swap_and_revert_leaves_one_image() {
    let n = every_cut(Cut::After, false);
    // Swap and revert of 8 pages: an erase, a write and a progress write
    // per page copy, 4 copies per page, plus the STATE updates.
    assert!(n >= 8 * 4 * 3, "only {n} operations were cut");
}

#[test]
fn a_power_cut_at_every_step_of_the_swap_and_confirmation_leaves_one_image() {
    let n = every_cut(Cut::After, true);
    assert!(n >= 8 * 2 * 3, "only {n} operations were cut");
}

#[test]
fn a_torn_operation_at_every_step_leaves_one_image() {
    for confirms in [false, true] {
        let n = every_cut(Cut::Torn, confirms);
        assert!(n >= 8 * 2 * 3, "only {n} operations were cut");
    }
}
