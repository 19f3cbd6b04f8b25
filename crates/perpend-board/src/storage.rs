//! Parameter storage: the [`Params`] record in flash through
//! `sequential-storage`'s map, boot-time loading with factory fallback, and
//! a fault-injecting flash for the host.
//!
//! ## Layout and atomicity
//!
//! The record is one map item (key [`PARAMS_KEY`]) in a range of flash
//! pages (on the board the last four 2 KiB pages of bank 2). A store
//! appends a new item; `sequential-storage` writes the item header, then
//! the data, and an item counts only when its header and data CRCs check,
//! so a power loss during a store leaves the previous item as the newest
//! valid one: old or new, never a mix. Full pages are migrated and erased
//! by the crate (it keeps one page free for that). `remove_item` is never
//! used: the STM32G4 flash cannot rewrite a programmed double word, which
//! removal needs. On top of the crate's CRCs, [`Params::decode`] checks its
//! own CRC-32, version and every value.
//!
//! The item is the record ([`RECORD_LEN`] = 493 bytes) followed by the
//! CANopen device's image (`perpend_can::IMAGE_LEN`, see `crate::app`):
//! more than half a page, so each page holds one item and, with four
//! pages (one kept free), every store after the third erases a page
//! (about 10 000 erase cycles per STM32G4 page: some 40 000 stores).
//! [`MAX_ITEM`] is what one page holds; a compile-time check keeps the
//! board's item within it.
//!
//! ## Record versions
//!
//! A record of an older layout (version 1, [`V1_RECORD_LEN`] bytes, before
//! the linearity table) still loads: [`Params::decode_with_len`] migrates
//! it (inactive tables) and says where it ends, so the bytes after it are
//! found at its own length. It boots as [`Boot::Stored`]; the next store
//! writes the current version.
//!
//! ## Boot
//!
//! [`load`] returns the stored parameters, or [`Params::factory`] with the
//! reason ([`Boot`]) when the record is missing, corrupt or unreadable; the
//! board then sets the "uncalibrated" status bit. It never panics.
//!
//! The map API is async (it is written for async flash drivers); the
//! [`ParamStore`] trait the application uses is blocking, and [`SeqStore`]
//! runs the futures with `embassy_futures::block_on`. With a blocking flash
//! driver (the STM32 one behind an async adapter, or [`FaultFlash`]) the
//! futures never pend, so this costs nothing.
//!
//! ## Flash faults (ECC) and the supply
//!
//! On the STM32G4 a double word whose programming (or page erase) was cut
//! by a power loss may hold an ECC double error; reading it raises the NMI
//! with FLASH_ECCR.ECCD (RM0440 §5.3.9). The firmware's NMI handler clears
//! ECCD for an address inside the storage range and its flash driver then
//! returns an error whose [`EccAddress::ecc_address`] is that address.
//! [`EccGuard`] sits between that driver and `sequential-storage`: it reads
//! such a range again word by word and hands every unreadable double word
//! up as [`ECC_FILL`] (a programmed, non-erased pattern), which the crate's
//! CRCs reject like any torn item: the previous record, or factory
//! defaults, is loaded, and [`ParamStore::take_read_faults`] tells the
//! application (EMCY 0x6300). The bad word is not erased at once (its page
//! may also hold the previous record); the crate erases the page when its
//! ring reaches it. [`FaultFlash::with_ecc`] models the cut: the torn double
//! word (and some words of a cut erase) fail every read until erased.
//!
//! [`FlashHealth::supply_ok`] is asked before every store: with the supply
//! below the PVD threshold (the firmware reads PWR_SR2.PVDO) nothing is
//! written and the store fails with [`StoreError::LowSupply`].

use core::ops::Range;

/// The `NorFlash` traits the storage is written against (re-exported for
/// the firmware's flash driver).
pub use embedded_storage_async::nor_flash;

use embassy_futures::block_on;
use embedded_storage_async::nor_flash::{
    ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};
use perpend_core::params::{Params, RECORD_LEN, V1_RECORD_LEN};
use sequential_storage::cache::{Cache, Uncached};
use sequential_storage::map::{MapConfig, MapStorage};

/// Map key of the parameter record.
pub const PARAMS_KEY: u8 = 1;

/// `sequential-storage`'s item header [bytes]: data CRC, length, length
/// CRC (one [`WORD`] on this flash).
const ITEM_HEADER: usize = 8;

/// Largest stored item: the [`Params`] record plus a tail (the CANopen
/// device's persistence image) [bytes]. What one page holds: a page less
/// the crate's two page-state words, the item header and the one-byte key.
pub const MAX_ITEM: usize = PAGE - 2 * WORD - ITEM_HEADER - 1;

// The board's item (the current record and the device image) fits, and a
// version-1 record is shorter than the current one.
const _: () = assert!(RECORD_LEN + perpend_can::IMAGE_LEN <= MAX_ITEM);
const _: () = assert!(V1_RECORD_LEN < RECORD_LEN);

/// Work buffer size: key + largest item (a multiple of 32 bytes, the
/// largest flash word the crate supports).
pub const BUF_LEN: usize = (1 + MAX_ITEM).div_ceil(32) * 32;

/// The item a restore (0x1011) stores instead of erasing: on the next boot
/// it reads as [`Boot::Missing`] (the map cannot remove an item on this
/// flash, see the module docs).
pub const TOMBSTONE: &[u8] = b"PPNDnone";

/// Why a store or load failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StoreError {
    /// The flash driver reported an error (including a power cut in
    /// [`FaultFlash`]).
    Flash,
    /// `sequential-storage` found the storage corrupted beyond its own
    /// repair.
    Corrupted,
    /// The storage is full (cannot happen with one fixed-size item and at
    /// least two pages; reported rather than assumed).
    Full,
    /// The record does not fit the work buffer or a flash page, or the
    /// range is not a valid map range.
    TooBig,
    /// Any other error of the storage crate (logic bug, serialization).
    Other,
    /// The supply monitor reports a voltage below its threshold: the store
    /// was not started (nothing written).
    LowSupply,
    /// The storage was found corrupted and is being erased one page per
    /// [`ParamStore::recovery_step`]; store again once it reports
    /// [`Recovery::Done`].
    Recovering,
}

/// The state of the corrupt-storage recovery ([`ParamStore::recovery_step`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Recovery {
    /// No recovery is running.
    Idle,
    /// One page was erased; more follow.
    Running,
    /// The last page was erased: the range is empty, a store can follow.
    Done,
    /// A page erase failed; the recovery stopped (the next store that
    /// finds the range corrupted starts it again).
    Failed(StoreError),
}

impl<E> From<sequential_storage::Error<E>> for StoreError {
    fn from(e: sequential_storage::Error<E>) -> Self {
        match e {
            sequential_storage::Error::Storage { .. } => StoreError::Flash,
            sequential_storage::Error::Corrupted { .. } => StoreError::Corrupted,
            sequential_storage::Error::FullStorage => StoreError::Full,
            sequential_storage::Error::ItemTooBig
            | sequential_storage::Error::BufferTooBig
            | sequential_storage::Error::BufferTooSmall(_) => StoreError::TooBig,
            _ => StoreError::Other,
        }
    }
}

/// Blocking access to the stored parameter record.
pub trait ParamStore {
    /// Copies the newest stored record into `out`; returns its length, or
    /// `None` when nothing is stored.
    ///
    /// # Errors
    /// [`StoreError`] when the flash cannot be read.
    fn load(&mut self, out: &mut [u8]) -> Result<Option<usize>, StoreError>;

    /// Stores `record` as the newest record.
    ///
    /// # Errors
    /// [`StoreError`]; after an error [`ParamStore::load`] returns the
    /// previous record or the new one (when the cut came after the new
    /// record was complete), never a mix.
    fn store(&mut self, record: &[u8]) -> Result<(), StoreError>;

    /// Number of unreadable (ECC) double words met since the last call,
    /// each read back as [`ECC_FILL`]; 0 for a store without such faults.
    fn take_read_faults(&mut self) -> u32 {
        0
    }

    /// Runs one bounded step (one page erase) of a running recovery from a
    /// corrupted range (see [`StoreError::Recovering`]); [`Recovery::Idle`]
    /// when none runs.
    fn recovery_step(&mut self) -> Recovery {
        Recovery::Idle
    }
}

/// What the board's flash reports beyond `NorFlash`: unreadable words met
/// and the supply monitor. Defaults: no faults, supply good.
pub trait FlashHealth {
    /// Number of unreadable (ECC) double words substituted since the last
    /// call.
    fn take_read_faults(&mut self) -> u32 {
        0
    }
    /// Whether the supply allows programming (the PVD reports no low
    /// voltage).
    fn supply_ok(&mut self) -> bool {
        true
    }
}

/// A flash error that may be an ECC double error at a known address.
pub trait EccAddress {
    /// The flash offset of the unreadable double word, if this error is an
    /// ECC double error.
    fn ecc_address(&self) -> Option<u32>;
}

/// What [`EccGuard`] hands up for an unreadable double word: programmed
/// (not 0xFF, so never taken for erased space) and rejected by the CRCs.
pub const ECC_FILL: u8 = 0x00;

/// A `NorFlash` adapter that turns ECC double errors on reads into
/// [`ECC_FILL`] words and counts them (see the module docs).
#[derive(Debug, Clone)]
pub struct EccGuard<F> {
    inner: F,
    faults: u32,
    last: Option<u32>,
}

impl<F> EccGuard<F> {
    /// Wraps `inner`.
    pub const fn new(inner: F) -> Self {
        Self {
            inner,
            faults: 0,
            last: None,
        }
    }
    /// The wrapped flash.
    pub fn inner_mut(&mut self) -> &mut F {
        &mut self.inner
    }
    /// Gives the wrapped flash back.
    pub fn into_inner(self) -> F {
        self.inner
    }
    /// Offset of the last unreadable double word met, if any.
    pub fn last_fault(&self) -> Option<u32> {
        self.last
    }
}

impl<F: ErrorType> ErrorType for EccGuard<F> {
    type Error = F::Error;
}

impl<F: ReadNorFlash> EccGuard<F>
where
    F::Error: EccAddress,
{
    /// Reads `bytes` at `offset` one double word at a time, substituting
    /// the unreadable ones.
    async fn read_words(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), F::Error> {
        let mut done = 0usize;
        while done < bytes.len() {
            let at = offset as usize + done;
            let word_end = (at / WORD + 1) * WORD;
            let n = (word_end - at).min(bytes.len() - done);
            let dst = &mut bytes[done..done + n];
            match self.inner.read(at as u32, dst).await {
                Ok(()) => {}
                Err(e) => match e.ecc_address() {
                    Some(a) => {
                        dst.fill(ECC_FILL);
                        self.faults = self.faults.saturating_add(1);
                        self.last = Some(a);
                    }
                    None => return Err(e),
                },
            }
            done += n;
        }
        Ok(())
    }
}

impl<F: ReadNorFlash> ReadNorFlash for EccGuard<F>
where
    F::Error: EccAddress,
{
    const READ_SIZE: usize = F::READ_SIZE;

    async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        match self.inner.read(offset, bytes).await {
            Err(e) if e.ecc_address().is_some() => self.read_words(offset, bytes).await,
            r => r,
        }
    }

    fn capacity(&self) -> usize {
        self.inner.capacity()
    }
}

impl<F: NorFlash> NorFlash for EccGuard<F>
where
    F::Error: EccAddress,
{
    const WRITE_SIZE: usize = F::WRITE_SIZE;
    const ERASE_SIZE: usize = F::ERASE_SIZE;

    async fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        self.inner.erase(from, to).await
    }

    async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        self.inner.write(offset, bytes).await
    }
}

impl<F: FlashHealth> FlashHealth for EccGuard<F> {
    fn take_read_faults(&mut self) -> u32 {
        core::mem::take(&mut self.faults).saturating_add(self.inner.take_read_faults())
    }
    fn supply_ok(&mut self) -> bool {
        self.inner.supply_ok()
    }
}

/// [`ParamStore`] over any `NorFlash` through `sequential-storage`'s map;
/// `B` is its item buffer: its own (the default) or a lent one
/// ([`SeqStore::with_buffer`]; the firmware's is a static, so that the
/// store is small enough to be moved: issue 50 item 6).
pub struct SeqStore<F: NorFlash, B: AsMut<[u8]> = [u8; BUF_LEN]> {
    map: MapStorage<u8, F, Cache<Uncached, Uncached, Uncached, u8>>,
    buf: B,
    /// Next page to erase of a running recovery.
    recovery: Option<u32>,
}

impl<F: NorFlash> SeqStore<F> {
    /// A store on `range` (page aligned, at least two pages) of `flash`.
    ///
    /// # Errors
    /// [`StoreError::TooBig`] when the range is not page aligned or too
    /// small (the crate's `MapConfigError`).
    pub fn new(flash: F, range: Range<u32>) -> Result<Self, StoreError> {
        let cfg = MapConfig::try_new(range).map_err(|_| StoreError::TooBig)?;
        Ok(Self::with_config(flash, cfg))
    }

    /// A store with a map configuration checked by the caller (e.g. in a
    /// `const` block, where `MapConfig::new` fails at compile time).
    pub const fn with_config(flash: F, cfg: MapConfig<F>) -> Self {
        Self {
            map: MapStorage::new(flash, cfg, Cache::new_uncached()),
            buf: [0; BUF_LEN],
            recovery: None,
        }
    }
}

impl<F: NorFlash, B: AsMut<[u8]>> SeqStore<F, B> {
    /// [`SeqStore::new`] with the item buffer `buf` (at least
    /// [`BUF_LEN`] bytes, else [`StoreError::TooBig`]).
    ///
    /// # Errors
    /// As [`SeqStore::new`]; a buffer shorter than [`BUF_LEN`].
    pub fn with_buffer(flash: F, range: Range<u32>, mut buf: B) -> Result<Self, StoreError> {
        let cfg = MapConfig::try_new(range).map_err(|_| StoreError::TooBig)?;
        if buf.as_mut().len() < BUF_LEN {
            return Err(StoreError::TooBig);
        }
        Ok(Self {
            map: MapStorage::new(flash, cfg, Cache::new_uncached()),
            buf,
            recovery: None,
        })
    }

    /// The flash (tests: inspect a fake flash).
    pub fn flash_mut(&mut self) -> &mut F {
        self.map.flash()
    }

    /// Gives the flash back.
    pub fn into_flash(self) -> F {
        self.map.destroy().0
    }

    /// Erases the whole range at once (every step of a recovery in a row;
    /// the firmware never blocks that long, it runs
    /// [`ParamStore::recovery_step`] once per tick).
    ///
    /// # Errors
    /// [`StoreError::Flash`].
    pub fn erase_all(&mut self) -> Result<(), StoreError> {
        self.start_recovery();
        loop {
            match self.step() {
                Recovery::Running => {}
                Recovery::Failed(e) => return Err(e),
                Recovery::Idle | Recovery::Done => return Ok(()),
            }
        }
    }

    /// Starts the page-by-page erase of the whole range (what a store that
    /// finds the range corrupted does).
    pub fn start_recovery(&mut self) {
        self.recovery = Some(self.map.flash_range().start);
    }

    /// One page erase of a running recovery.
    fn step(&mut self) -> Recovery {
        let Some(page) = self.recovery else {
            return Recovery::Idle;
        };
        let end = self.map.flash_range().end;
        let next = page.saturating_add(PAGE as u32).min(end);
        if block_on(self.map.flash().erase(page, next)).is_err() {
            self.recovery = None;
            return Recovery::Failed(StoreError::Flash);
        }
        self.recovery = (next < end).then_some(next);
        if self.recovery.is_some() {
            Recovery::Running
        } else {
            Recovery::Done
        }
    }
}

impl<F: NorFlash + FlashHealth, B: AsMut<[u8]>> ParamStore for SeqStore<F, B> {
    fn take_read_faults(&mut self) -> u32 {
        self.map.flash().take_read_faults()
    }

    fn load(&mut self, out: &mut [u8]) -> Result<Option<usize>, StoreError> {
        let item: Option<&[u8]> = block_on(self.map.fetch_item(self.buf.as_mut(), &PARAMS_KEY))?;
        match item {
            None => Ok(None),
            Some(v) => {
                let dst = out.get_mut(..v.len()).ok_or(StoreError::TooBig)?;
                dst.copy_from_slice(v);
                Ok(Some(v.len()))
            }
        }
    }

    fn recovery_step(&mut self) -> Recovery {
        self.step()
    }

    fn store(&mut self, record: &[u8]) -> Result<(), StoreError> {
        if self.recovery.is_some() {
            return Err(StoreError::Recovering);
        }
        if !self.map.flash().supply_ok() {
            return Err(StoreError::LowSupply);
        }
        let r = block_on(self.map.store_item(self.buf.as_mut(), &PARAMS_KEY, &record));
        match r.map_err(StoreError::from) {
            // The crate could not repair the range: nothing in it is
            // readable anyway, so start afresh, one page per step (four
            // page erases in a row would block > 100 ms, longer than the
            // firmware's receive ring covers).
            Err(StoreError::Corrupted) => {
                self.start_recovery();
                Err(StoreError::Recovering)
            }
            other => other,
        }
    }
}

/// Where the boot parameters came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Boot {
    /// A valid stored record.
    Stored,
    /// Nothing stored (or a restore tombstone): factory defaults.
    Missing,
    /// A record was found but rejected by [`Params::decode`]: factory
    /// defaults. The payload is the decoder's error.
    Rejected(perpend_core::Error),
    /// The flash could not be read: factory defaults.
    Unreadable(StoreError),
}

/// Loads the parameters at boot: the stored record, or factory defaults
/// with the reason. Never fails.
pub fn load<S: ParamStore + ?Sized>(store: &mut S) -> (Params, Boot) {
    let (p, boot, _) = load_with_tail(store, &mut []);
    (p, boot)
}

/// As [`load`], and copies the bytes stored after the record (see
/// [`save_with_tail`]) into `tail`; returns their number (0 unless
/// [`Boot::Stored`]). A tail longer than `tail` is [`Boot::Rejected`] with
/// [`perpend_core::Error::BufferTooSmall`].
#[inline(never)] // its 2 KiB buffer stays out of the caller's frame
pub fn load_with_tail<S: ParamStore + ?Sized>(
    store: &mut S,
    tail: &mut [u8],
) -> (Params, Boot, usize) {
    let mut buf = [0u8; MAX_ITEM];
    let n = match store.load(&mut buf) {
        Ok(Some(n)) => n,
        Ok(None) => return (Params::factory(), Boot::Missing, 0),
        Err(e) => return (Params::factory(), Boot::Unreadable(e), 0),
    };
    let item = buf.get(..n).unwrap_or(&[]);
    if item == TOMBSTONE {
        return (Params::factory(), Boot::Missing, 0);
    }
    // The tail starts where the record ends: RECORD_LEN for the current
    // version, V1_RECORD_LEN for a record of the firmware before the
    // linearity table (see the module docs, "Record versions").
    let (p, len) = match Params::decode_with_len(item) {
        Ok(x) => x,
        Err(e) => return (Params::factory(), Boot::Rejected(e), 0),
    };
    let rest = item.get(len..).unwrap_or(&[]);
    match tail.get_mut(..rest.len()) {
        Some(dst) => {
            dst.copy_from_slice(rest);
            (p, Boot::Stored, rest.len())
        }
        None => (
            Params::factory(),
            Boot::Rejected(perpend_core::Error::BufferTooSmall),
            0,
        ),
    }
}

/// Why [`save`] failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SaveError {
    /// The parameters are invalid; nothing was written.
    Invalid(perpend_core::Error),
    /// The store failed.
    Store(StoreError),
}

/// Encodes and stores `params`.
///
/// # Errors
/// As [`save_with_tail`].
pub fn save<S: ParamStore + ?Sized>(store: &mut S, params: &Params) -> Result<(), SaveError> {
    save_with_tail(store, params, &[])
}

/// Encodes `params` and stores it followed by `tail` as one item, so both
/// change together or not at all.
///
/// # Errors
/// [`SaveError::Invalid`] when the parameters do not validate or the item
/// exceeds [`MAX_ITEM`] (nothing is written), [`SaveError::Store`] from the
/// flash.
#[inline(never)] // its 2 KiB buffer stays out of the caller's frame
pub fn save_with_tail<S: ParamStore + ?Sized>(
    store: &mut S,
    params: &Params,
    tail: &[u8],
) -> Result<(), SaveError> {
    let mut buf = [0u8; MAX_ITEM];
    let n = params.encode(&mut buf).map_err(SaveError::Invalid)?;
    let dst = buf
        .get_mut(n..n + tail.len())
        .ok_or(SaveError::Invalid(perpend_core::Error::BufferTooSmall))?;
    dst.copy_from_slice(tail);
    store
        .store(buf.get(..n + tail.len()).unwrap_or(&[]))
        .map_err(SaveError::Store)
}

/// Makes the next boot use factory defaults by storing [`TOMBSTONE`].
///
/// # Errors
/// [`StoreError`] from the flash (the old record then stays).
pub fn clear<S: ParamStore + ?Sized>(store: &mut S) -> Result<(), StoreError> {
    store.store(TOMBSTONE)
}

/// Errors of [`FaultFlash`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FlashFault {
    /// The power was cut (injected); every operation fails until
    /// [`FaultFlash::power_on`].
    PowerLoss,
    /// Programming a double word that is not erased (the STM32 PROGERR).
    NotErased,
    /// Address or length not aligned to the operation's granularity.
    NotAligned,
    /// Outside the flash.
    OutOfBounds,
    /// ECC double error reading the double word at this offset (a torn
    /// word of [`FaultFlash::with_ecc`]).
    Ecc(u32),
}

impl EccAddress for FlashFault {
    fn ecc_address(&self) -> Option<u32> {
        match self {
            FlashFault::Ecc(a) => Some(*a),
            _ => None,
        }
    }
}

impl NorFlashError for FlashFault {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            FlashFault::NotAligned => NorFlashErrorKind::NotAligned,
            FlashFault::OutOfBounds => NorFlashErrorKind::OutOfBounds,
            FlashFault::PowerLoss | FlashFault::NotErased | FlashFault::Ecc(_) => {
                NorFlashErrorKind::Other
            }
        }
    }
}

/// Double-word size of the STM32G4 flash [bytes].
pub const WORD: usize = 8;
/// Page size of the STM32G4 flash in dual-bank mode [bytes].
pub const PAGE: usize = 2048;

/// An in-memory NOR flash that behaves like the STM32G4's (8-byte program
/// granularity, each double word programmable once per erase, 2 KiB pages,
/// erased state 0xFF) and injects faults: a power cut at any chosen step (a
/// step is one double-word program or one page erase; the step that is cut
/// leaves a torn word or a half-erased page), and bit flips.
///
/// With [`FaultFlash::with_ecc`] a torn double word is unreadable (ECC
/// double error, [`FlashFault::Ecc`]) until its page is erased, as on the
/// STM32G4; [`FaultFlash::set_low_supply`] models the PVD.
///
/// `SIZE` is the capacity in bytes (a multiple of [`PAGE`]).
#[derive(Debug, Clone)]
pub struct FaultFlash<const SIZE: usize> {
    data: [u8; SIZE],
    cut_after: Option<u32>,
    dead: bool,
    steps: u32,
    erases: u32,
    rng: u32,
    ecc: bool,
    /// Offsets of unreadable double words ([`FaultFlash::with_ecc`]).
    bad: heapless::Vec<u32, MAX_BAD_WORDS>,
    low_supply: bool,
}

/// Most unreadable double words [`FaultFlash`] keeps track of (more torn
/// words than that are kept as garbage only).
pub const MAX_BAD_WORDS: usize = 64;

impl<const SIZE: usize> FlashHealth for FaultFlash<SIZE> {
    fn supply_ok(&mut self) -> bool {
        !self.low_supply
    }
}

impl<const SIZE: usize> Default for FaultFlash<SIZE> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const SIZE: usize> FaultFlash<SIZE> {
    /// An erased flash without faults.
    pub const fn new() -> Self {
        Self {
            data: [0xFF; SIZE],
            cut_after: None,
            dead: false,
            steps: 0,
            erases: 0,
            rng: 0x2545_F491,
            ecc: false,
            bad: heapless::Vec::new(),
            low_supply: false,
        }
    }

    /// This flash with ECC modelling: a torn double word fails every read
    /// with [`FlashFault::Ecc`] until its page is erased.
    pub fn with_ecc(mut self) -> Self {
        self.ecc = true;
        self
    }

    /// Sets the supply monitor's "low voltage" output (PVDO).
    pub fn set_low_supply(&mut self, low: bool) {
        self.low_supply = low;
    }

    /// Offsets of the double words that are unreadable now.
    pub fn bad_words(&self) -> &[u32] {
        &self.bad
    }

    fn mark_bad(&mut self, at: usize) {
        if self.ecc && !self.bad.contains(&(at as u32)) {
            // Beyond the capacity the word stays readable garbage.
            let _ = self.bad.push(at as u32);
        }
    }

    /// Schedules a power cut: the next `n` steps complete, step `n + 1` is
    /// torn, and every operation after it fails with
    /// [`FlashFault::PowerLoss`].
    pub fn cut_power_after(&mut self, n: u32) {
        self.cut_after = Some(n);
    }

    /// Restores power (a reboot); no further cut is scheduled.
    pub fn power_on(&mut self) {
        self.dead = false;
        self.cut_after = None;
    }

    /// Whether the power is cut.
    pub fn is_dead(&self) -> bool {
        self.dead
    }

    /// Number of steps (double-word programs and page erases) so far.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// Number of page erases so far (also counted in [`FaultFlash::steps`]).
    pub fn erases(&self) -> u32 {
        self.erases
    }

    /// The raw contents.
    pub fn bytes(&self) -> &[u8] {
        &self.data
    }

    /// Flips bit `bit` (0..8) of byte `addr` (bit rot, a stray write).
    pub fn flip(&mut self, addr: usize, bit: u8) {
        if let Some(b) = self.data.get_mut(addr) {
            *b ^= 1 << (bit & 7);
        }
    }

    fn next_rand(&mut self) -> u32 {
        // xorshift32: deterministic garbage for torn words.
        let mut x = self.rng;
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        self.rng = x;
        x
    }

    /// Accounts one step; returns true when this step is the torn one.
    fn step(&mut self) -> Result<bool, FlashFault> {
        if self.dead {
            return Err(FlashFault::PowerLoss);
        }
        self.steps += 1;
        match self.cut_after {
            Some(0) => {
                self.dead = true;
                self.cut_after = None;
                Ok(true)
            }
            Some(n) => {
                self.cut_after = Some(n - 1);
                Ok(false)
            }
            None => Ok(false),
        }
    }

    fn range(offset: u32, len: usize, align: usize) -> Result<Range<usize>, FlashFault> {
        let start = offset as usize;
        if !start.is_multiple_of(align) || !len.is_multiple_of(align) {
            return Err(FlashFault::NotAligned);
        }
        let end = start.checked_add(len).ok_or(FlashFault::OutOfBounds)?;
        if end > SIZE {
            return Err(FlashFault::OutOfBounds);
        }
        Ok(start..end)
    }

    fn program(&mut self, offset: u32, bytes: &[u8]) -> Result<(), FlashFault> {
        let r = Self::range(offset, bytes.len(), WORD)?;
        for (k, chunk) in bytes.chunks(WORD).enumerate() {
            let at = r.start + k * WORD;
            if self.data[at..at + WORD].iter().any(|&b| b != 0xFF)
                || self.bad.contains(&(at as u32))
            {
                return Err(FlashFault::NotErased);
            }
            if self.step()? {
                // Torn: some of the bits that should go to 0 did.
                for (i, b) in chunk.iter().enumerate() {
                    let keep = self.next_rand() as u8;
                    self.data[at + i] &= *b | keep;
                }
                self.mark_bad(at);
                return Err(FlashFault::PowerLoss);
            }
            self.data[at..at + WORD].copy_from_slice(chunk);
        }
        Ok(())
    }

    fn erase_pages(&mut self, from: u32, to: u32) -> Result<(), FlashFault> {
        if to < from {
            return Err(FlashFault::OutOfBounds);
        }
        let r = Self::range(from, (to - from) as usize, PAGE)?;
        for page in r.step_by(PAGE) {
            self.erases += 1;
            if self.step()? {
                // A cut erase leaves a mixture of erased and old words.
                // With ECC modelling a quarter of the words are left
                // half-erased: unreadable.
                self.bad
                    .retain(|&b| !(page..page + PAGE).contains(&(b as usize)));
                for w in (page..page + PAGE).step_by(WORD) {
                    let r = self.next_rand();
                    if r & 1 == 0 {
                        self.data[w..w + WORD].fill(0xFF);
                    } else if r & 6 == 0 {
                        self.mark_bad(w);
                    }
                }
                return Err(FlashFault::PowerLoss);
            }
            self.data[page..page + PAGE].fill(0xFF);
            self.bad
                .retain(|&b| !(page..page + PAGE).contains(&(b as usize)));
        }
        Ok(())
    }
}

impl<const SIZE: usize> ErrorType for FaultFlash<SIZE> {
    type Error = FlashFault;
}

impl<const SIZE: usize> ReadNorFlash for FaultFlash<SIZE> {
    const READ_SIZE: usize = 1;

    async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        if self.dead {
            return Err(FlashFault::PowerLoss);
        }
        let r = Self::range(offset, bytes.len(), 1)?;
        if let Some(&b) = self
            .bad
            .iter()
            .find(|&&b| (b as usize) < r.end && b as usize + WORD > r.start)
        {
            return Err(FlashFault::Ecc(b));
        }
        bytes.copy_from_slice(&self.data[r]);
        Ok(())
    }

    fn capacity(&self) -> usize {
        SIZE
    }
}

impl<const SIZE: usize> NorFlash for FaultFlash<SIZE> {
    const WRITE_SIZE: usize = WORD;
    const ERASE_SIZE: usize = PAGE;

    async fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        self.erase_pages(from, to)
    }

    async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        self.program(offset, bytes)
    }
}

/// The host's stand-in for the board's storage: four 2 KiB pages, as on
/// the board.
pub type HostFlash = FaultFlash<{ 4 * PAGE }>;

/// The board's storage stack on the host: [`EccGuard`] over a
/// [`HostFlash`] (use [`FaultFlash::with_ecc`] to model ECC errors).
pub type EccHostFlash = EccGuard<HostFlash>;

/// A [`SeqStore`] over a whole [`EccHostFlash`], as the firmware builds it.
pub fn ecc_host_store(flash: HostFlash) -> SeqStore<EccHostFlash> {
    SeqStore::with_config(
        EccGuard::new(flash),
        const { MapConfig::new(0..(4 * PAGE) as u32) },
    )
}

/// A [`SeqStore`] over a whole [`HostFlash`] (the range is checked at
/// compile time).
pub fn host_store(flash: HostFlash) -> SeqStore<HostFlash> {
    SeqStore::with_config(flash, const { MapConfig::new(0..(4 * PAGE) as u32) })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use perpend_core::params::Transfer;

    fn params(k: u32) -> Params {
        let mut p = Params::factory();
        p.stamp = 1000 + k;
        p.head.sensors[k as usize % 4].zero.x += 0.001 * k as f32;
        p.transfer[1] = Transfer::voltage(0.3, 10.0, 60.0 + k as f32);
        p
    }

    /// The recovery from a corrupted range erases one page per step (no
    /// programming), refuses stores while it runs, then the range stores
    /// again.
    #[test]
    fn recovery_is_split_into_single_page_steps() {
        let mut s = host_store(HostFlash::new());
        save(&mut s, &params(1)).unwrap();
        s.start_recovery();
        assert_eq!(
            save(&mut s, &params(2)),
            Err(SaveError::Store(StoreError::Recovering))
        );
        let mut steps = 0;
        loop {
            let (e0, s0) = (s.flash_mut().erases(), s.flash_mut().steps());
            let r = s.recovery_step();
            steps += 1;
            assert_eq!(s.flash_mut().erases() - e0, 1, "step {steps}");
            assert_eq!(s.flash_mut().steps() - s0, 1, "step {steps}");
            match r {
                Recovery::Running => assert!(steps < 4),
                Recovery::Done => break,
                other => assert_eq!(other, Recovery::Done),
            }
        }
        assert_eq!(steps, 4);
        assert_eq!(s.recovery_step(), Recovery::Idle);
        assert_eq!(load(&mut s).1, Boot::Missing);
        save(&mut s, &params(2)).unwrap();
        assert_eq!(load(&mut s), (params(2), Boot::Stored));
    }

    #[test]
    fn missing_then_stored() {
        let mut s = host_store(HostFlash::new());
        assert_eq!(load(&mut s), (Params::factory(), Boot::Missing));
        save(&mut s, &params(1)).unwrap();
        assert_eq!(load(&mut s), (params(1), Boot::Stored));
        // survives a "reboot": a new store over the same flash
        let mut s2 = host_store(s.into_flash());
        assert_eq!(load(&mut s2), (params(1), Boot::Stored));
    }

    /// A store over a lent buffer (the firmware's static) reads and
    /// writes what one with its own buffer does; a short buffer is
    /// refused.
    #[test]
    fn a_lent_buffer_stores_as_an_own_one() {
        let range = 0..(4 * PAGE) as u32;
        let mut buf = [0u8; BUF_LEN];
        let mut s = SeqStore::with_buffer(HostFlash::new(), range.clone(), &mut buf).unwrap();
        assert_eq!(load(&mut s).1, Boot::Missing);
        save(&mut s, &params(3)).unwrap();
        let mut own = host_store(s.into_flash());
        assert_eq!(load(&mut own), (params(3), Boot::Stored));
        let mut short = [0u8; BUF_LEN - 1];
        assert!(matches!(
            SeqStore::with_buffer(HostFlash::new(), range, &mut short[..]),
            Err(StoreError::TooBig)
        ));
    }

    #[test]
    fn many_stores_wrap_the_pages() {
        let mut s = host_store(HostFlash::new());
        for k in 0..40 {
            save(&mut s, &params(k)).unwrap();
            assert_eq!(load(&mut s).0, params(k));
        }
        // 40 records of 62 words do not fit 4 pages: pages were erased
        // and reused
        assert!(s.into_flash().steps() > 40 * (RECORD_LEN / WORD) as u32);
    }

    #[test]
    fn tail_and_tombstone() {
        let mut s = host_store(HostFlash::new());
        let tail: Vec<u8> = (0..500u32).map(|k| k as u8).collect();
        save_with_tail(&mut s, &params(4), &tail).unwrap();
        let mut got = [0u8; 600];
        let (p, boot, n) = load_with_tail(&mut s, &mut got);
        assert_eq!((p, boot, n), (params(4), Boot::Stored, 500));
        assert_eq!(&got[..n], &tail[..]);
        // a tail that does not fit the caller's buffer is a rejection
        let (p, boot, n) = load_with_tail(&mut s, &mut got[..10]);
        assert_eq!(
            (p, boot, n),
            (
                Params::factory(),
                Boot::Rejected(perpend_core::Error::BufferTooSmall),
                0
            )
        );
        // too big to store: nothing written
        let huge = [0u8; MAX_ITEM];
        assert_eq!(
            save_with_tail(&mut s, &params(5), &huge),
            Err(SaveError::Invalid(perpend_core::Error::BufferTooSmall))
        );
        // restore: the tombstone boots factory defaults
        clear(&mut s).unwrap();
        assert_eq!(load(&mut s), (Params::factory(), Boot::Missing));
        save(&mut s, &params(6)).unwrap();
        assert_eq!(load(&mut s), (params(6), Boot::Stored));
    }

    #[test]
    fn invalid_params_are_not_written() {
        let mut s = host_store(HostFlash::new());
        let mut p = Params::factory();
        p.can.node_id = 0;
        assert_eq!(
            save(&mut s, &p),
            Err(SaveError::Invalid(perpend_core::Error::OutOfRange(
                "node id"
            )))
        );
        assert_eq!(s.into_flash().steps(), 0);
    }

    #[test]
    fn fake_flash_enforces_the_g4_rules() {
        let mut f = HostFlash::new();
        block_on(f.write(0, &[0u8; 8])).unwrap();
        assert_eq!(block_on(f.write(0, &[0u8; 8])), Err(FlashFault::NotErased));
        assert_eq!(block_on(f.write(4, &[0u8; 8])), Err(FlashFault::NotAligned));
        assert_eq!(
            block_on(f.write((4 * PAGE) as u32, &[0u8; 8])),
            Err(FlashFault::OutOfBounds)
        );
        assert_eq!(block_on(f.erase(0, 100)), Err(FlashFault::NotAligned));
        block_on(f.erase(0, PAGE as u32)).unwrap();
        block_on(f.write(0, &[0u8; 8])).unwrap();
        // a cut: the next step is torn, then everything fails
        f.cut_power_after(0);
        assert_eq!(block_on(f.write(8, &[0u8; 8])), Err(FlashFault::PowerLoss));
        let mut b = [0u8; 8];
        assert_eq!(block_on(f.read(0, &mut b)), Err(FlashFault::PowerLoss));
        f.power_on();
        block_on(f.read(0, &mut b)).unwrap();
    }

    /// Stores `before` records (each followed by a tail of `tail_len`
    /// bytes), then a new one with the power cut at every step of that
    /// store; after each cut a reboot must load the old or the new record
    /// with its own tail (or factory defaults when there was none), and a
    /// further store must work. Returns the number of steps and erases of
    /// the store.
    fn power_loss_at_every_step(before: u32, tail_len: usize) -> (u32, u32) {
        let tail =
            |k: u32| -> Vec<u8> { (0..tail_len).map(|i| (i as u32 * 7 + k) as u8).collect() };
        let mut s = host_store(HostFlash::new());
        for k in 0..before {
            save_with_tail(&mut s, &params(k), &tail(k)).unwrap();
        }
        let base = s.into_flash();
        let old = before.checked_sub(1);
        let new = before;
        // Steps of an uninterrupted store from this state.
        let mut probe = host_store(base.clone());
        save_with_tail(&mut probe, &params(new), &tail(new)).unwrap();
        let probe = probe.into_flash();
        let total = probe.steps() - base.steps();
        let erases = probe.erases() - base.erases();
        assert!(total > 0);
        let mut got = [0u8; MAX_ITEM];
        for cut in 0..total {
            let mut f = base.clone();
            f.cut_power_after(cut);
            let mut s = host_store(f);
            let r = save_with_tail(&mut s, &params(new), &tail(new));
            assert_eq!(r, Err(SaveError::Store(StoreError::Flash)), "cut {cut}");
            let mut f = s.into_flash();
            assert!(f.is_dead());
            f.power_on();
            let mut s = host_store(f);
            let (p, boot, n) = load_with_tail(&mut s, &mut got);
            let ctx = format!("before {before}, cut {cut}/{total}: {boot:?}");
            if p == params(new) {
                assert_eq!((boot, &got[..n]), (Boot::Stored, &tail(new)[..]), "{ctx}");
            } else if let Some(o) = old {
                assert_eq!(p, params(o), "{ctx}");
                assert_eq!((boot, &got[..n]), (Boot::Stored, &tail(o)[..]), "{ctx}");
            } else {
                assert_eq!((p, boot), (Params::factory(), Boot::Missing), "{ctx}");
            }
            // the storage is still usable
            let next = params(before + 1);
            save(&mut s, &next).unwrap();
            assert_eq!(load(&mut s), (next, Boot::Stored), "cut {cut}");
        }
        (total, erases)
    }

    #[test]
    fn power_loss_during_first_store() {
        let (steps, _) = power_loss_at_every_step(0, 0);
        assert!(steps >= (RECORD_LEN / WORD) as u32);
    }

    #[test]
    fn power_loss_at_every_step_of_every_fill_level() {
        // 1..24 earlier stores: the new store lands at every position in a
        // page, crosses page boundaries and triggers erases (four records
        // fit a 2 KiB page; the crate keeps one page free, so the stores
        // after the 12th, 16th and 20th erase a page).
        let mut erasing = 0;
        for before in 1..24 {
            let (steps, erases) = power_loss_at_every_step(before, 0);
            assert!(steps >= (RECORD_LEN / WORD) as u32);
            if erases > 0 {
                erasing += 1;
            }
        }
        assert!(erasing >= 2, "{erasing} stores erased a page");
    }

    #[test]
    fn power_loss_with_board_sized_items() {
        // The board stores the record plus the CANopen image (1253 bytes
        // with the linearity tables): one item per page, so every store
        // after the third erases a page.
        let mut erasing = 0;
        for before in 0..8 {
            let (_, erases) = power_loss_at_every_step(before, perpend_can::IMAGE_LEN);
            if erases > 0 {
                erasing += 1;
            }
        }
        assert!(erasing >= 4, "{erasing} stores erased a page");
    }

    /// An item of exactly [`MAX_ITEM`] bytes stores and loads again and
    /// again (each store wraps to a fresh page); one byte more is refused
    /// before anything is written, and the map could not store it anyway.
    #[test]
    fn largest_item_fits_a_page() {
        let tail: Vec<u8> = (0..MAX_ITEM - RECORD_LEN).map(|k| (k * 13) as u8).collect();
        let mut s = host_store(HostFlash::new());
        let mut got = [0u8; MAX_ITEM];
        for k in 0..6 {
            save_with_tail(&mut s, &params(k), &tail).unwrap();
            let (p, boot, n) = load_with_tail(&mut s, &mut got);
            assert_eq!((p, boot, n), (params(k), Boot::Stored, tail.len()));
            assert_eq!(&got[..n], &tail[..]);
        }
        let steps = s.into_flash().steps();
        let mut s = host_store(HostFlash::new());
        let longer = [0u8; MAX_ITEM - RECORD_LEN + 1];
        assert_eq!(
            save_with_tail(&mut s, &params(0), &longer),
            Err(SaveError::Invalid(perpend_core::Error::BufferTooSmall))
        );
        assert_eq!(s.map.flash().steps(), 0);
        // and the map itself cannot place one byte more in a page
        assert!(s.store(&[0x5A; MAX_ITEM + 1]).is_err());
        assert_eq!(load(&mut s), (Params::factory(), Boot::Missing));
        assert!(steps > 6 * (MAX_ITEM / WORD) as u32);
    }

    /// A version-1 record (firmware before the linearity table) with a
    /// tail, as that firmware stored it: it loads with inactive tables and
    /// its tail is found at the version-1 length; the next save writes the
    /// current version with the same tail.
    #[test]
    fn v1_record_with_tail_migrates() {
        let mut p = params(7);
        p.head.sensors[3].ext.gain = 2e-3;
        let mut v2 = [0u8; RECORD_LEN];
        p.encode(&mut v2).unwrap();
        let v1 = perpend_core::params::record_as_v1(&v2);
        let tail: Vec<u8> = (0..300u32).map(|k| (k * 5 + 1) as u8).collect();
        let mut item = v1.to_vec();
        item.extend_from_slice(&tail);
        let mut s = host_store(HostFlash::new());
        s.store(&item).unwrap();
        let mut got = [0u8; MAX_ITEM];
        let (q, boot, n) = load_with_tail(&mut s, &mut got);
        assert_eq!((q, boot, &got[..n]), (p, Boot::Stored, &tail[..]));
        save_with_tail(&mut s, &q, &got[..n]).unwrap();
        let mut raw = [0u8; MAX_ITEM];
        let len = s.load(&mut raw).unwrap().unwrap();
        assert_eq!(len, RECORD_LEN + tail.len());
        assert_eq!(&raw[..RECORD_LEN], &v2[..]);
        assert_eq!(&raw[RECORD_LEN..len], &tail[..]);
    }

    #[test]
    fn bit_flips_fall_back_to_an_older_record_or_factory() {
        let mut s = host_store(HostFlash::new());
        save(&mut s, &params(1)).unwrap();
        save(&mut s, &params(2)).unwrap();
        let f = s.into_flash();
        // Flip bits all over the used part of the flash: the load must
        // return one of the records or factory defaults, never panic.
        let used = f.bytes().iter().rposition(|&b| b != 0xFF).unwrap() + 1;
        let mut outcomes = [0usize; 3];
        for addr in 0..used {
            for bit in [0u8, 5] {
                let mut g = f.clone();
                g.flip(addr, bit);
                let (p, boot) = load(&mut host_store(g));
                if p == params(2) {
                    outcomes[0] += 1;
                } else if p == params(1) {
                    outcomes[1] += 1;
                } else {
                    assert_eq!(p, Params::factory(), "addr {addr} bit {bit}");
                    assert_ne!(boot, Boot::Stored);
                    outcomes[2] += 1;
                }
            }
        }
        // flips in the newest record make it fall back
        assert!(outcomes[1] + outcomes[2] > 0, "{outcomes:?}");
    }

    #[test]
    fn garbage_flash_boots_with_factory_defaults() {
        let mut f = HostFlash::new();
        // A half-written page header and random words.
        block_on(f.write(0, &[0x12, 0x34, 0, 0, 0xAB, 0xCD, 0xEF, 0])).unwrap();
        block_on(f.write(2048, &[0; 8])).unwrap();
        block_on(f.write(4096 + 64, &[0x55; 16])).unwrap();
        let mut s = host_store(f);
        let (p, boot) = load(&mut s);
        assert_eq!(p, Params::factory());
        assert_ne!(boot, Boot::Stored);
        // and a store recovers the storage
        save(&mut s, &params(3)).unwrap();
        assert_eq!(load(&mut s), (params(3), Boot::Stored));
    }
}
