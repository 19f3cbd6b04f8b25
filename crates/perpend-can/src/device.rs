//! The CANopen device: NMT slave, heartbeat producer, SDO server, SYNC
//! consumer, TPDOs, EMCY producer and the parameter store, over the object
//! dictionary of [`crate::od`].
//!
//! Sans-I/O: [`Device::handle`] consumes a received frame, [`Device::poll`]
//! produces what is due at a given time; both push frames to the caller's
//! `out` closure. Time is a monotonic `u64` in microseconds supplied by the
//! caller; the device never reads a clock, so tests are deterministic.
//!
//! SYNC counter, SYNC-locked acquisition, heartbeat consumer, error
//! behaviour and the command RPDO: `device_sync.rs`.
//!
//! Limits: one SDO server, four TPDOs, one RPDO (fixed mapping), no node
//! guarding / RTR, no SYNC producer, no TIME, fixed SYNC COB-ID 0x80.

use core::mem::MaybeUninit;
use core::ptr::addr_of_mut;

use perpend_core::head::Sensor;
use perpend_core::params::Params;

use crate::config::{
    bitrate_of, Acquisition, Communication, Defaults, Measurement, SensorCalibration, SurfaceModel,
    TransferFunction, CAL_SUB_COEFFS, CAL_SUB_KNOTS, CAL_SUB_SPOT, CAL_VALUES,
    SURFACE_AXIS_MIN_LEN, SURFACE_CYLINDER, SURFACE_RADIUS_MIN_MM,
};
use crate::frame::Frame;
pub use crate::od::Group;
use crate::od::{
    self, Access, Class, DataType, Init, Limits, Lookup, Text, ENTRIES, HB_CONSUMERS,
    LOAD_SIGNATURE, MAX_MAPPED, PERSISTENT, SAVE_SIGNATURE, TPDOS, UNLOCK_SIGNATURE,
};
use crate::sdo::{Dictionary, SdoAbort, SdoServer, Value, Written};
use crate::status::{self, error_register};
use crate::Error;

/// Slot of the uptime 0x200C, written on every poll (no lookup).
const UPTIME: usize = od::slot_of(0x200C, 0);

/// NMT states (CiA 301 §7.3.2.2), with their heartbeat codes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NmtState {
    /// After power-on or a reset, until the boot-up message is sent by the
    /// next [`Device::poll`].
    Initialising,
    /// SDO, EMCY, NMT, heartbeat; no PDOs. Calibration/configuration
    /// writable.
    PreOperational,
    /// Everything, PDOs included; calibration/configuration read-only.
    Operational,
    /// Only NMT and heartbeat.
    Stopped,
}

impl NmtState {
    /// The state byte of the heartbeat message.
    pub const fn heartbeat_code(self) -> u8 {
        match self {
            NmtState::Initialising => 0x00,
            NmtState::PreOperational => 0x7F,
            NmtState::Operational => 0x05,
            NmtState::Stopped => 0x04,
        }
    }
}

/// A request the application must carry out on its non-volatile storage.
/// In both cases it writes [`Device::persistent_image`], which already
/// holds what the request leaves stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Request {
    /// 0x1010 sub 1/2/3 "save": the group's current values are stored,
    /// the other persisted objects keep their stored values; the store
    /// count 0x2011 sub 3 is stored one higher (sub 1 and 3).
    Store(Group),
    /// 0x1011 sub 1/2/3 "load": the group's defaults are stored (0x2400
    /// excepted, see [`od::restorable`]); they become active at the next
    /// reset node or power-on (CiA 301 §7.5.2.14).
    Restore(Group),
    /// LSS "store configuration" (CiA 305, [`crate::lss`]): 0x2400 is
    /// stored (sub 1 the pending node-id, sub 2 `bit_rate_kbps`), every
    /// other object keeps its stored value; the LSS answer follows
    /// [`Device::finish_request`].
    StoreLss {
        /// The configured bit rate \[kbit/s\].
        bit_rate_kbps: u16,
    },
    /// 0x1F50 sub 1 (CiA 302-3 program data): `len` bytes of the program
    /// at byte `offset` ([`Device::program_part`]), parts in order from
    /// offset 0; `last`: the download is complete (its size and, by block
    /// transfer, its CRC checked). The application writes them to its
    /// program store; a refusal aborts the download with 0x08000020.
    ProgramData {
        /// Byte offset of the part in the program.
        offset: u32,
        /// Bytes in the part.
        len: u16,
        /// The last part.
        last: bool,
    },
    /// 0x1F51 sub 1 program control ([`od::PROGRAM_STOP`], start, reset,
    /// clear); reads back once carried out.
    ProgramControl(u8),
}

/// Things that happened since the application last called
/// [`Device::take_events`] (a bit set).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Events(pub u8);

impl Events {
    /// NMT reset node was executed: the application should restart its own
    /// processing (re-read calibration and configuration).
    pub const RESET_NODE: u8 = 1 << 0;
    /// NMT reset communication was executed (node-id and bit rate of 0x2400
    /// may have changed).
    pub const RESET_COMM: u8 = 1 << 1;
    /// A calibration or configuration value changed (SDO write, reset,
    /// image load): re-read them.
    pub const CONFIG_CHANGED: u8 = 1 << 2;
    /// The NMT state changed.
    pub const STATE_CHANGED: u8 = 1 << 3;
    /// A [`Request`] is waiting ([`Device::pending_request`]).
    pub const REQUEST: u8 = 1 << 4;
    /// SYNC-locked acquisition (0x2301): a SYNC asks for one scan now; its
    /// TPDOs wait for [`Device::set_sample_time`] and the published sample.
    pub const SYNC_SAMPLE: u8 = 1 << 6;
    /// A command was written to 0x2500 (SDO or RPDO): see
    /// [`Device::command`].
    pub const COMMAND: u8 = 1 << 7;

    /// Whether `bit` is set.
    pub const fn contains(self, bit: u8) -> bool {
        self.0 & bit != 0
    }

    /// Whether nothing happened.
    pub const fn is_empty(self) -> bool {
        self.0 == 0
    }
}

/// Length of the persistence image \[bytes\]: layout signature (4), entry
/// count (4), then one little-endian `u32` per persisted entry in
/// dictionary order.
pub const IMAGE_LEN: usize = 8 + 4 * PERSISTENT;

/// Largest number of simultaneously active emergencies recorded code by
/// code. The board holds at most 13 at once (both codes of each of the
/// four sensors during its clear delay, no plane, data set, heartbeat,
/// SYNC length, PDO length) plus one raised-and-cleared bus or reset event:
/// 16 leaves a margin. Beyond it an overflow bucket still sends one EMCY
/// per code and never a repeat, and [`EMCY_TABLE_FULL`] stands for the
/// codes beyond the bucket ([`Device::signal_emcy`]).
pub const MAX_ACTIVE_ERRORS: usize = 16;
/// EMCY code sent once when a code is raised while the table and the
/// overflow bucket are both taken: 0x6100 "internal software", the code
/// CANopenNode reports for an error it cannot record
/// (`CO_EM_WRONG_ERROR_REPORT`), with the first such code in manufacturer
/// bytes 0-1. It stays active, with the register bits of every code it
/// stands for, until nothing recorded is active any more.
pub const EMCY_TABLE_FULL: u16 = 0x6100;
/// EMCYs waiting for the next poll. In stopped they wait (CANopenNode
/// keeps its EMCY FIFO through stopped), a raise and the error reset of
/// the same code cancelling out, so each code holds at most an error
/// reset and a raise: two per code of a full table, the bucket and
/// [`EMCY_TABLE_FULL`].
const EMCY_QUEUE: usize = 2 * (MAX_ACTIVE_ERRORS + 2);

/// Codes raised while the table of active codes was full.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct Overflow {
    /// The bucket: the first code raised while the table was full (sent,
    /// active) and its error-register bits.
    code: Option<(u16, u8)>,
    /// The error-register bits of the codes raised while the bucket was
    /// taken (not recorded, not sent one by one); non-zero while
    /// [`EMCY_TABLE_FULL`] is active.
    lost: u8,
}

/// Length of an image of layout 1 (firmware before issue 16, without the
/// entries of layout 2 and 3): still accepted by [`Device::load_image`].
pub const IMAGE_LEN_V1: usize = 8 + 4 * od::PERSISTENT_V1;

/// Length of an image of layout 2 (firmware before the surface model
/// 0x2310 of issue 14): still accepted by [`Device::load_image`].
pub const IMAGE_LEN_V2: usize = 8 + 4 * od::PERSISTENT_V2;

/// Length of an image of layout 3 (firmware before the heartbeat consumer,
/// SYNC counter, error behaviour, trigger, RPDO and capture objects):
/// still accepted by [`Device::load_image`].
pub const IMAGE_LEN_V3: usize = 8 + 4 * od::PERSISTENT_V3;

/// Length of an image of layout 4 (firmware before the linearity tables,
/// 0x2101..0x2104 sub 16..23): still accepted by [`Device::load_image`].
pub const IMAGE_LEN_V4: usize = 8 + 4 * od::PERSISTENT_V4;

/// Length of an image of layout 5 (firmware before the thermal time
/// constant 0x2105): still accepted by [`Device::load_image`].
pub const IMAGE_LEN_V5: usize = 8 + 4 * od::PERSISTENT_V5;

/// Length of an image of layout 6 (firmware before the calibration stamp
/// 0x2011): still accepted by [`Device::load_image`] (the stamp stays 0).
pub const IMAGE_LEN_V6: usize = 8 + 4 * od::PERSISTENT_V6;

/// Length of an image of layout 7 (firmware before the spot coefficients,
/// 0x2101..0x2104 sub 24..25): still accepted by [`Device::load_image`]
/// (the spot coefficients keep their current values).
pub const IMAGE_LEN_V7: usize = 8 + 4 * od::PERSISTENT_V7;

/// FNV-1a over (index, sub, type) of the entries persisted by image layout
/// `layout` ([`od::Entry::since`]): changes when the persisted layout
/// changes.
fn layout_signature_of(layout: u8) -> u32 {
    let mut h: u32 = 0x811C_9DC5;
    for (_, index, e) in od::entries() {
        if e.persist && e.since <= layout {
            for b in index
                .to_le_bytes()
                .into_iter()
                .chain([e.sub])
                .chain(e.ty.code().to_le_bytes())
            {
                h ^= b as u32;
                h = h.wrapping_mul(0x0100_0193);
            }
        }
    }
    h
}

fn layout_signature() -> u32 {
    layout_signature_of(od::LAYOUT)
}

/// Converts a current image ([`IMAGE_LEN`] bytes) into the layout-1 image
/// older firmware wrote: for compatibility tests. Returns the length
/// written ([`IMAGE_LEN_V1`]).
pub fn image_as_v1(img: &[u8; IMAGE_LEN], out: &mut [u8; IMAGE_LEN]) -> usize {
    image_as_layout(img, 1, out)
}

/// Converts a current image ([`IMAGE_LEN`] bytes) into the image of the
/// older layout `layout` (1 or 2: the entries added since left out), as
/// older firmware wrote it: for compatibility tests. Returns the length
/// written.
pub fn image_as_layout(img: &[u8; IMAGE_LEN], layout: u8, out: &mut [u8; IMAGE_LEN]) -> usize {
    out[0..4].copy_from_slice(&layout_signature_of(layout).to_le_bytes());
    out[4..8].copy_from_slice(&(od::persistent_of(layout) as u32).to_le_bytes());
    let (mut p, mut q) = (8, 8);
    for (_, _, e) in od::entries() {
        if e.persist {
            if e.since <= layout {
                out[q..q + 4].copy_from_slice(&img[p..p + 4]);
                q += 4;
            }
            p += 4;
        }
    }
    q
}

/// A TPDO mapping resolved to value slots: what [`Core::tpdo_frame`] needs
/// of the dictionary, found once for the mapping words `words` (sub 0..=8
/// of 0x1A0x; resolving is a function of them alone).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct PdoMap {
    words: [u32; MAX_MAPPED + 1],
    /// Mapped entries.
    n: u8,
    /// Payload bytes; 0: the mapping is empty or unusable (nothing sent).
    len: u8,
    slots: [u16; MAX_MAPPED],
    /// The mapped length's mask of each value.
    masks: [u32; MAX_MAPPED],
    /// Where each value starts in the payload \[bytes\].
    starts: [u8; MAX_MAPPED],
}

impl PdoMap {
    /// The slots of `words` (as [`Core::map_target`] checks them: a
    /// mapping with an unmappable entry, or longer than 8 bytes, is
    /// unusable).
    #[cold]
    fn resolve(words: &[u32]) -> Self {
        let mut m = PdoMap::default();
        for (w, &v) in m.words.iter_mut().zip(words) {
            *w = v;
        }
        let words = m.words;
        let n = (words[0] as usize).min(MAX_MAPPED);
        let mut len = 0usize;
        for (i, &w) in words[1..=n].iter().enumerate() {
            let Ok((s, bits)) = Core::map_target(w) else {
                return m;
            };
            let at = len;
            len += usize::from(bits) / 8;
            if len > 8 {
                return m;
            }
            m.slots[i] = s as u16;
            m.masks[i] = u32::MAX
                .checked_shr(32u32.saturating_sub(u32::from(bits)))
                .unwrap_or(0);
            m.starts[i] = at as u8;
        }
        m.n = n as u8;
        m.len = len as u8;
        m
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct TpdoRt {
    sync_count: u8,
    /// The SYNC start value (sub 6) was met since the PDO became valid.
    started: bool,
    last_tx: Option<u64>,
    /// The mapped data changed (beyond the deadband) since the last
    /// transmission.
    event_pending: bool,
    timer_due: Option<u64>,
    /// Payload of the last transmission (`None`: nothing sent yet).
    last_data: Option<([u8; 8], u8)>,
}

#[derive(Debug, Clone)]
struct Core {
    defaults: Defaults,
    node_id: u8,
    values: [u32; ENTRIES],
    /// Power-on values: what a reset restores (defaults overlaid with the
    /// loaded / stored image).
    boot: [u32; ENTRIES],
    state: NmtState,
    unlocked: bool,
    hb_next: Option<u64>,
    hb_restart: bool,
    /// Heartbeats sent (not the boot-up), wrapping.
    hb_sent: u32,
    /// When the uptime 0x200C next turns a second [µs] (one 64-bit
    /// division a second, not one a poll).
    uptime_next_us: u64,
    tpdo: [TpdoRt; TPDOS],
    /// The TPDO mappings resolved (a cache of the dictionary lookups).
    pdo_maps: [PdoMap; TPDOS],
    active: [(u16, u8); MAX_ACTIVE_ERRORS],
    n_active: usize,
    /// Codes beyond `active`: the bucket and the lost ones.
    overflow: Overflow,
    emcy_queue: [[u8; 8]; EMCY_QUEUE],
    emcy_len: usize,
    /// Time of the last EMCY sent (the inhibit time 0x1015 counts from it).
    emcy_last_tx: Option<u64>,
    request: Option<Request>,
    events: u8,
    config_gen: u32,
    /// SYNC-locked acquisition (`device_sync.rs`).
    syncs: SyncRt,
    /// Heartbeat consumers (0x1016).
    hb_cons: [HbMonitor; HB_CONSUMERS],
    /// 0x2500 = [`od::CMD_BOOTLOADER`] is refused (SDO abort 0x08000022):
    /// the board's bootloader does not allow the ROM loader
    /// ([`Device::set_rom_loader_allowed`]).
    rom_loader_locked: bool,
}

/// Every field of [`Core`]: a field added to it stops this from compiling
/// until it is written by [`Device::init`] too (which builds a `Core` in
/// place, field by field).
#[allow(dead_code)]
fn core_fields(c: Core) {
    let Core {
        defaults: _,
        node_id: _,
        values: _,
        boot: _,
        state: _,
        unlocked: _,
        hb_next: _,
        hb_restart: _,
        hb_sent: _,
        uptime_next_us: _,
        tpdo: _,
        pdo_maps: _,
        active: _,
        n_active: _,
        overflow: _,
        emcy_queue: _,
        emcy_len: _,
        emcy_last_tx: _,
        request: _,
        events: _,
        config_gen: _,
        syncs: _,
        hb_cons: _,
        rom_loader_locked: _,
    } = c;
}

/// A CANopen device (CiA 301 subset) holding the perpend object
/// dictionary. See the crate documentation for the behaviour contract.
#[derive(Debug, Clone)]
pub struct Device {
    core: Core,
    sdo: SdoServer,
    /// LSS slave (`device_lss.rs`).
    lss: lss_glue::LssRt,
}

/// The calibration and configuration objects of a set of object values:
/// the device's own ([`Device::objects`]) or those a stored image would
/// leave ([`Device::staged_objects`]).
#[derive(Debug, Clone, Copy)]
pub struct Objects<'a> {
    values: &'a [u32; ENTRIES],
    node_id: u8,
}

impl Objects<'_> {
    fn get(&self, index: u16, sub: u8) -> u32 {
        slot(index, sub).map_or(0, |s| self.values[s])
    }

    fn get_f32(&self, index: u16, sub: u8) -> f32 {
        f32::from_bits(self.get(index, sub))
    }

    /// The node-id active with these values.
    pub fn node_id(&self) -> u8 {
        self.node_id
    }

    /// Calibration of sensor `i` (0-based; `None` beyond 3): 0x2101 + i.
    pub fn calibration(&self, i: usize) -> Option<SensorCalibration> {
        if i >= 4 {
            return None;
        }
        let idx = 0x2101 + i as u16;
        let a: [f32; CAL_VALUES] = core::array::from_fn(|k| self.get_f32(idx, k as u8 + 1));
        Some(SensorCalibration::from_array(&a))
    }

    /// Transfer function of sensor `i` (0-based): 0x2201 + i.
    pub fn transfer(&self, i: usize) -> Option<TransferFunction> {
        if i >= 4 {
            return None;
        }
        let idx = 0x2201 + i as u16;
        Some(TransferFunction {
            kind: self.get(idx, 1) as u8,
            scale: self.get_f32(idx, 2),
            mm_at_low: self.get_f32(idx, 3),
            mm_at_high: self.get_f32(idx, 4),
        })
    }

    /// Surface model 0x2310 (issue 14).
    pub fn surface(&self) -> SurfaceModel {
        SurfaceModel {
            model: self.get(0x2310, 1) as u8,
            radius_mm: self.get_f32(0x2310, 2),
            axis: core::array::from_fn(|k| self.get_f32(0x2310, k as u8 + 3)),
        }
    }

    /// The head's thermal time constant 0x2105 \[s\] (0 = no lag).
    pub fn thermal_tau_s(&self) -> f32 {
        self.get_f32(0x2105, 0)
    }

    /// Acquisition settings 0x2300.
    pub fn acquisition(&self) -> Acquisition {
        Acquisition {
            period_us: self.get(0x2300, 1),
            oversampling: self.get(0x2300, 2) as u16,
            method: self.get(0x2300, 3) as u8,
            residual_limit_mm: self.get_f32(0x2300, 4),
        }
    }

    /// Communication settings 0x2400 as configured.
    pub fn communication(&self) -> Communication {
        Communication {
            node_id: self.get(0x2400, 1) as u8,
            bit_rate_kbps: self.get(0x2400, 2) as u16,
        }
    }
}

/// Whether the linearity table held in subs 16..23 of a sensor calibration
/// object (`value(sub)`, raw bits) is usable
/// ([`SensorCalibration::table_valid`]).
fn table_ok(value: impl Fn(u8) -> u32) -> bool {
    let f = |s: u8| f32::from_bits(value(s));
    let c = SensorCalibration {
        knots: core::array::from_fn(|k| f(CAL_SUB_KNOTS + k as u8)),
        coeffs: core::array::from_fn(|k| f(CAL_SUB_COEFFS + k as u8)),
        ..SensorCalibration::from_array(&[0.0; CAL_VALUES])
    };
    c.table_valid()
}

/// Whether every sensor's linearity table in the value slots `values` is
/// usable (image and record loads check it after the per-entry limits).
fn tables_ok(values: &[u32; ENTRIES]) -> Result<(), Error> {
    for index in 0x2101..=0x2104u16 {
        let value = |s: u8| {
            slot(index, s)
                .and_then(|n| values.get(n))
                .copied()
                .unwrap_or(0)
        };
        if !table_ok(value) {
            return Err(Error::Value {
                index,
                sub: CAL_SUB_KNOTS,
            });
        }
    }
    Ok(())
}

/// Whether an entry belongs to the stored parameter record (calibration
/// and configuration objects).
fn index_is_app(e: &od::Entry) -> bool {
    matches!(e.class, Class::Calibration | Class::Config)
}

fn slot(index: u16, sub: u8) -> Option<usize> {
    od::slot(index, sub)
}

/// Whether an 11-bit COB-ID may be used by a TPDO (CiA 301 §7.3.5,
/// restricted COB-IDs excluded).
fn cob_allowed(id: u32) -> bool {
    !matches!(id, 0x000..=0x07F | 0x101..=0x180 | 0x581..=0x5FF | 0x601..=0x67F | 0x6E0..=0x6FF | 0x701..=0x7FF)
        && id <= 0x7FF
}

fn decode(ty: DataType, data: &[u8]) -> u32 {
    let mut b = [0u8; 4];
    let n = data.len().min(4);
    b[..n].copy_from_slice(&data[..n]);
    match ty {
        DataType::U8 => b[0] as u32,
        DataType::U16 => u16::from_le_bytes([b[0], b[1]]) as u32,
        _ => u32::from_le_bytes(b),
    }
}

fn check_limits(limits: Limits, ty: DataType, v: u32) -> Result<(), SdoAbort> {
    match limits {
        Limits::Any => Ok(()),
        Limits::Range(lo, hi) => {
            if v < lo {
                Err(SdoAbort::TooLow)
            } else if v > hi {
                Err(SdoAbort::TooHigh)
            } else {
                Ok(())
            }
        }
        Limits::Real(lo, hi) => {
            let f = f32::from_bits(v);
            if ty != DataType::Real32 || !f.is_finite() {
                Err(SdoAbort::Range)
            } else if f < lo {
                Err(SdoAbort::TooLow)
            } else if f > hi {
                Err(SdoAbort::TooHigh)
            } else {
                Ok(())
            }
        }
        Limits::OneOf(set) => {
            if set.contains(&v) {
                Ok(())
            } else {
                Err(SdoAbort::Range)
            }
        }
        Limits::PowerOfTwo(lo, hi) => {
            if !v.is_power_of_two() {
                Err(SdoAbort::Range)
            } else if v < lo {
                Err(SdoAbort::TooLow)
            } else if v > hi {
                Err(SdoAbort::TooHigh)
            } else {
                Ok(())
            }
        }
    }
}

impl Core {
    fn init_value(&self, e: &od::Entry, node: u8) -> u32 {
        let d = &self.defaults;
        match e.init {
            Init::Fixed(v) => v,
            Init::Node(base) => base + node as u32,
            Init::DeviceType => d.device_type,
            Init::Identity(k) => match k {
                1 => d.identity.vendor_id,
                2 => d.identity.product_code,
                3 => d.identity.revision,
                _ => d.identity.serial,
            },
            Init::Heartbeat => d.heartbeat_ms as u32,
            Init::Calibration(s, k) => d
                .calibration
                .get(s as usize)
                .and_then(|c| c.to_array().get(k as usize).copied())
                .unwrap_or(0.0)
                .to_bits(),
            Init::Transfer(s, k) => d
                .transfer
                .get(s as usize)
                .map(|t| match k {
                    0 => t.kind as u32,
                    1 => t.scale.to_bits(),
                    2 => t.mm_at_low.to_bits(),
                    _ => t.mm_at_high.to_bits(),
                })
                .unwrap_or(0),
            Init::Acquisition(k) => {
                let a = &d.acquisition;
                match k {
                    0 => a.period_us,
                    1 => a.oversampling as u32,
                    2 => a.method as u32,
                    _ => a.residual_limit_mm.to_bits(),
                }
            }
            Init::ThermalTau => d.thermal_tau_s.to_bits(),
            Init::BitRate => d.bit_rate_kbps as u32,
            Init::Text(_) => 0,
        }
    }

    /// The value entry `s` (a persisted entry of `index`) has in storage
    /// once `req` is carried out.
    /// A store of the application group counts itself in the calibration
    /// stamp ([`od::STAMP_COUNT`]: one more than stored).
    fn staged(&self, req: Request, s: usize, index: u16, e: &od::Entry) -> u32 {
        match req {
            Request::Store(g) if g.contains(index) && s == od::STAMP_COUNT => {
                self.boot[s].saturating_add(1)
            }
            Request::Store(g) if g.contains(index) => self.values[s],
            Request::StoreLss { bit_rate_kbps } if index == 0x2400 => match e.sub {
                2 => u32::from(bit_rate_kbps),
                _ => self.values[s],
            },
            Request::Restore(g) if g.contains(index) && od::restorable(index) => {
                self.init_value(e, self.boot_node())
            }
            _ => self.boot[s],
        }
    }

    fn text(&self, t: Text) -> &'static str {
        match t {
            Text::DeviceName => self.defaults.device_name,
            Text::HardwareVersion => self.defaults.hardware_version,
            Text::SoftwareVersion => self.defaults.software_version,
        }
    }

    fn get(&self, index: u16, sub: u8) -> u32 {
        slot(index, sub).map_or(0, |s| self.values[s])
    }

    fn set(&mut self, index: u16, sub: u8, v: u32) {
        if let Some(s) = slot(index, sub) {
            self.values[s] = v;
        }
    }

    /// Sets subs `first..` of `index` to `vals` (they must be consecutive
    /// sub-indices, hence consecutive slots: one lookup for all).
    fn set_run(&mut self, index: u16, first: u8, vals: &[u32]) {
        if let Some(s) = slot(index, first) {
            if let Some(dst) = self.values.get_mut(s..s + vals.len()) {
                dst.copy_from_slice(vals);
            }
        }
    }

    fn get_f32(&self, index: u16, sub: u8) -> f32 {
        f32::from_bits(self.get(index, sub))
    }

    fn event(&mut self, bits: u8) {
        self.events |= bits;
    }

    fn config_changed(&mut self) {
        self.config_gen = self.config_gen.wrapping_add(1);
        self.event(Events::CONFIG_CHANGED);
    }

    fn set_state(&mut self, s: NmtState) {
        if self.state != s {
            self.state = s;
            self.unlocked = false;
            self.set(0x2010, 0, 0);
            self.event(Events::STATE_CHANGED);
            if s == NmtState::Operational {
                self.tpdo = [TpdoRt::default(); TPDOS];
                self.arm_event_timers(None);
            }
        }
    }

    /// Restarts event timers (all, or TPDO `only`), counted from the last
    /// known time (they are armed lazily by `poll`).
    fn arm_event_timers(&mut self, only: Option<usize>) {
        for k in 0..TPDOS {
            if only.is_none_or(|o| o == k) {
                self.tpdo[k].timer_due = None;
            }
        }
    }

    fn tpdo_valid(&self, k: usize) -> bool {
        TPDO_COB
            .get(k)
            .is_some_and(|&s| self.at(s) & 0x8000_0000 == 0)
    }

    /// Validates the mapping of TPDO `k` with `n` entries taken from `map`.
    fn check_mapping(map: &[u32; MAX_MAPPED], n: usize) -> Result<(), SdoAbort> {
        let mut bits = 0u32;
        for &m in map.iter().take(n) {
            bits += Self::check_map_entry(m)? as u32;
        }
        if bits > 64 {
            return Err(SdoAbort::PdoLength);
        }
        Ok(())
    }

    /// Validates one mapping entry; returns its bit length.
    fn check_map_entry(m: u32) -> Result<u8, SdoAbort> {
        Self::map_target(m).map(|(_, bits)| bits)
    }

    /// Validates one mapping entry; returns the slot of the mapped object
    /// and its bit length.
    fn map_target(m: u32) -> Result<(usize, u8), SdoAbort> {
        let index = (m >> 16) as u16;
        let sub = (m >> 8) as u8;
        let bits = m as u8;
        let (s, e) = od::find(index, sub).map_err(|l| match l {
            Lookup::NoObject => SdoAbort::NoObject,
            Lookup::NoSub => SdoAbort::NoSub,
        })?;
        if !e.pdo {
            return Err(SdoAbort::NotMappable);
        }
        if e.ty.bits() != bits {
            return Err(SdoAbort::Incompatible);
        }
        Ok((s, bits))
    }

    fn mapping_of(&self, k: usize) -> ([u32; MAX_MAPPED], usize) {
        let idx = 0x1A00 + k as u16;
        let n = (self.get(idx, 0) as usize).min(MAX_MAPPED);
        let map = core::array::from_fn(|i| self.get(idx, i as u8 + 1));
        (map, n)
    }

    /// The payload of TPDO `k`, or `None` if its mapping is unusable or
    /// empty (sub 0 = 0: an empty PDO is never sent).
    /// (Hot path of every SYNC: the mapping's subs 0..=8 are consecutive
    /// slots, read directly.)
    /// The mapping words are resolved to value slots once per mapping
    /// ([`PdoMap`], keyed by the words themselves: no dictionary lookup on
    /// a SYNC while the mapping stays, issue 50 item 8).
    fn tpdo_frame(&mut self, k: usize) -> Option<Frame> {
        let base = *TPDO_MAP.get(k)?;
        let words = self.values.get(base..=base + MAX_MAPPED)?;
        let cached = self.pdo_maps.get_mut(k)?;
        // The count and the mapped words (resolving reads no others),
        // word by word, OR-reduced: an equality test of the arrays became
        // a byte-wise `memcmp` (≈ 250 instructions a TPDO).
        let n = (words[0] as usize).min(MAX_MAPPED);
        let mut diff = 0u32;
        for (a, b) in cached.words.iter().zip(words).take(n + 1) {
            diff |= a ^ b;
        }
        if diff != 0 {
            *cached = PdoMap::resolve(words);
        }
        let m = &*cached;
        if m.len == 0 {
            return None;
        }
        // Each value masked as resolved and stored as four little-endian
        // bytes at its start, in payload order: the next value overwrites
        // the zeros above a shorter one, and the last one's spill lands in
        // the 4 bytes past the payload (a `u64` shift per value cost ≈ 27
        // instructions, this ≈ 10; `cargo xtask mcu-bench`).
        let mut buf = [0u8; 12];
        for i in 0..usize::from(m.n).min(MAX_MAPPED) {
            let v = self.values.get(usize::from(m.slots[i])).copied()? & m.masks[i];
            let at = usize::from(m.starts[i]);
            buf.get_mut(at..at + 4)?.copy_from_slice(&v.to_le_bytes());
        }
        let id = (self.values.get(TPDO_COB[k]).copied().unwrap_or(0) & 0x7FF) as u16;
        let mut data = [0u8; 8];
        data.copy_from_slice(&buf[..8]);
        Some(Frame {
            id,
            rtr: false,
            len: m.len,
            data,
        })
    }

    /// The deadband (0x2009) of a mapped REAL32 object, if it has one.
    fn deadband_of(&self, index: u16) -> Option<f32> {
        match index {
            0x2002 | 0x2003 => Some(self.get_f32(0x2009, 1)),
            0x2001 => Some(self.get_f32(0x2009, 2)),
            0x2004 | 0x2006 => Some(self.get_f32(0x2009, 3)),
            _ => None,
        }
    }

    /// Whether payload `f` of TPDO `k` differs from the last one sent:
    /// objects with a deadband by more than it, the others in any bit.
    fn changed(&self, k: usize, f: &Frame) -> bool {
        let Some((last, len)) = self.tpdo[k].last_data else {
            return true;
        };
        if len != f.len {
            return true;
        }
        let (map, n) = self.mapping_of(k);
        let mut pos = 0usize;
        for &m in map.iter().take(n) {
            let bytes = (m as u8 / 8) as usize;
            let (Some(a), Some(b)) = (last.get(pos..pos + bytes), f.data.get(pos..pos + bytes))
            else {
                return true;
            };
            let differs = match (self.deadband_of((m >> 16) as u16), a, b) {
                (Some(db), &[a0, a1, a2, a3], &[b0, b1, b2, b3]) => {
                    let d =
                        f32::from_le_bytes([a0, a1, a2, a3]) - f32::from_le_bytes([b0, b1, b2, b3]);
                    !(d.abs() <= db) // NaN counts as a change
                }
                _ => a != b,
            };
            if differs {
                return true;
            }
            pos += bytes;
        }
        false
    }

    /// Marks the TPDOs of type 0/254/255 whose mapped data changed since
    /// they were last sent (beyond the deadbands).
    fn mark_changed_tpdos(&mut self) {
        for (k, &slot) in TPDO_TYPE.iter().enumerate() {
            let tt = self.at(slot);
            if matches!(tt, 0 | 254 | 255) && self.tpdo_valid(k) && !self.tpdo[k].event_pending {
                if let Some(f) = self.tpdo_frame(k) {
                    self.tpdo[k].event_pending = self.changed(k, &f);
                }
            }
        }
    }

    /// Whether emergency `code` is active (recorded, or the code of the
    /// overflow bucket).
    #[inline]
    fn is_active(&self, code: u16) -> bool {
        // Every sample asks this for each of the application's ten
        // conditions: the usual case (nothing active) costs one test.
        if self.n_active == 0 && self.overflow == Overflow::default() {
            return false;
        }
        self.active[..self.n_active].iter().any(|&(k, _)| k == code)
            || self.overflow.code.is_some_and(|(k, _)| k == code)
            || (code == EMCY_TABLE_FULL && self.overflow.lost != 0)
    }

    /// Raises emergency `code` (see [`Device::signal_emcy`]); `false` if it
    /// was already active, or suppressed by the overflow bucket.
    ///
    /// Each code is recorded in `active`, so a repeat is never sent again
    /// (CANopenNode keeps one status bit per error condition to the same
    /// end). A code raised while the table is full goes to the overflow
    /// bucket and is sent with its own code. Codes raised while the bucket
    /// is taken cannot be told from repeats (nothing records them): the
    /// first of them sends [`EMCY_TABLE_FULL`] once, naming it, and all
    /// of them keep their register bits in 0x1001 (`lost`) while any
    /// recorded code is active; each is sent with its own code at its
    /// first raise after a slot or the bucket frees up. Still one EMCY per
    /// code, never a flood. (CANopenNode reports every error bit beyond
    /// its table as 0x6100 `CO_EM_WRONG_ERROR_REPORT`, one status bit for
    /// all; the bucket sends the first one's own code.)
    fn raise(&mut self, code: u16, reg: u8, mfr: [u8; 5]) -> bool {
        if self.is_active(code) {
            return false;
        }
        if self.n_active < MAX_ACTIVE_ERRORS {
            self.active[self.n_active] = (code, reg);
            self.n_active += 1;
        } else if self.overflow.code.is_none() {
            self.overflow.code = Some((code, reg));
        } else {
            return self.lose(code, reg);
        }
        self.update_error_register();
        let info = u16::from_le_bytes([mfr[0], mfr[1]]) as u32;
        self.record_error(code, info);
        let reg_now = self.get(0x1001, 0) as u8;
        let cb = code.to_le_bytes();
        self.queue_emcy([
            cb[0], cb[1], reg_now, mfr[0], mfr[1], mfr[2], mfr[3], mfr[4],
        ]);
        true
    }

    /// A code raised while the table and the bucket are taken: its
    /// register bits stay in 0x1001; the first such code since the last
    /// time nothing was lost sends [`EMCY_TABLE_FULL`] (manufacturer bytes
    /// 0-1: the code) and records it in 0x1003. `true` when sent.
    fn lose(&mut self, code: u16, reg: u8) -> bool {
        let first = self.overflow.lost == 0;
        self.overflow.lost |= reg | error_register::GENERIC;
        self.update_error_register();
        if !first {
            return false;
        }
        self.record_error(EMCY_TABLE_FULL, u32::from(code));
        let reg_now = self.get(0x1001, 0) as u8;
        let (t, cb) = (EMCY_TABLE_FULL.to_le_bytes(), code.to_le_bytes());
        self.queue_emcy([t[0], t[1], reg_now, cb[0], cb[1], 0, 0, 0]);
        true
    }

    /// Clears emergency `code` (see [`Device::clear_emcy`]); `false` if it
    /// was not active. Clearing the bucket's code empties the bucket; the
    /// lost codes' bits stay in 0x1001 until no recorded code is active,
    /// when [`EMCY_TABLE_FULL`] is reset too (after the code's own reset).
    fn clear(&mut self, code: u16) -> bool {
        let pos = self.active[..self.n_active]
            .iter()
            .position(|&(k, _)| k == code);
        if let Some(pos) = pos {
            self.active.copy_within(pos + 1..self.n_active, pos);
            self.n_active -= 1;
        } else if self.overflow.code.is_some_and(|(k, _)| k == code) {
            self.overflow.code = None;
        } else {
            return false;
        }
        self.update_error_register();
        self.queue_reset(code);
        if self.n_active == 0 && self.overflow.code.is_none() && self.overflow.lost != 0 {
            self.overflow.lost = 0;
            self.update_error_register();
            self.queue_reset(EMCY_TABLE_FULL);
        }
        true
    }

    /// Queues the error reset of `code`, with the register as it is now.
    fn queue_reset(&mut self, code: u16) {
        let reg_now = self.get(0x1001, 0) as u8;
        let cb = code.to_le_bytes();
        self.queue_emcy([0, 0, reg_now, cb[0], cb[1], 0, 0, 0]);
    }

    /// Sends TPDO `k` at `now_us` (nothing if it is empty or unusable) and
    /// remembers what was sent.
    fn send_tpdo(&mut self, k: usize, now_us: u64, out: &mut impl FnMut(Frame)) {
        let rt = &mut self.tpdo[k];
        rt.event_pending = false;
        rt.last_tx = Some(now_us);
        if let Some(f) = self.tpdo_frame(k) {
            self.tpdo[k].last_data = Some((f.data, f.len));
            out(f);
        }
    }

    /// The node-id the stored (power-on) values were made for: 0x2400
    /// sub 1 of `boot`.
    fn boot_node(&self) -> u8 {
        let v = slot(0x2400, 1).map_or(0, |s| self.boot[s]);
        if (1..=127).contains(&v) {
            v as u8
        } else {
            self.node_id
        }
    }

    /// Makes the configured node-id (0x2400 sub 1) active: node-relative
    /// values follow. Persisted COB-IDs follow only where they still hold
    /// their default for `from` (the node-id the current values were made
    /// for); the stored values are not touched.
    fn apply_node_id(&mut self, from: u8) {
        let configured = self.get(0x2400, 1);
        let new = if (1..=127).contains(&configured) {
            configured as u8
        } else {
            self.node_id
        };
        for (s, _, e) in od::entries() {
            if let Init::Node(base) = e.init {
                if base == 0 {
                    continue; // 0x2400 sub 1 is the source, not a follower
                }
                if !e.persist {
                    self.values[s] = base + new as u32;
                    self.boot[s] = base + new as u32;
                } else if from != new && self.values[s] & 0x7FF == (base & 0x7FF) + from as u32 {
                    let new_id = (base & 0x7FF) + new as u32;
                    self.values[s] = (self.values[s] & !0x7FF) | new_id;
                }
            }
        }
        self.node_id = new;
    }

    fn reset_node(&mut self) {
        // 0x2400 is kept: a written node-id / bit rate becomes active now,
        // saved or not (docs/can.md).
        let comm = [self.get(0x2400, 1), self.get(0x2400, 2)];
        self.values = self.boot;
        self.set(0x2400, 1, comm[0]);
        self.set(0x2400, 2, comm[1]);
        self.n_active = 0;
        self.overflow = Overflow::default();
        self.emcy_len = 0;
        let from = self.boot_node();
        self.apply_node_id(from);
        self.reset_common();
        self.config_changed();
        self.event(Events::RESET_NODE);
    }

    fn reset_comm(&mut self) {
        for (s, index, e) in od::entries() {
            if index < 0x2000 && (e.persist || matches!(e.init, Init::Node(_))) {
                self.values[s] = self.boot[s];
            }
        }
        let from = self.boot_node();
        self.apply_node_id(from);
        self.reset_common();
        self.event(Events::RESET_COMM);
    }

    fn reset_common(&mut self) {
        self.unlocked = false;
        self.set(0x2010, 0, 0);
        self.tpdo = [TpdoRt::default(); TPDOS];
        self.syncs = SyncRt::default();
        self.hb_cons = [HbMonitor::default(); HB_CONSUMERS];
        self.hb_next = None;
        self.hb_restart = true;
        if self.state != NmtState::Initialising {
            self.state = NmtState::Initialising;
            self.event(Events::STATE_CHANGED);
        }
    }

    /// Sends queued EMCYs: all of them without an inhibit time (0x1015),
    /// else one when the inhibit time since the previous one has passed.
    fn send_emcys(&mut self, now_us: u64, out: &mut impl FnMut(Frame)) {
        let id = (self.get(0x1014, 0) & 0x7FF) as u16;
        let inhibit = self.get(0x1015, 0) as u64 * 100;
        let mut sent = 0;
        while sent < self.emcy_len {
            if self.emcy_last_tx.is_some_and(|l| now_us < l + inhibit) {
                break;
            }
            out(Frame::new(id, &self.emcy_queue[sent]));
            self.emcy_last_tx = Some(now_us);
            sent += 1;
        }
        self.emcy_queue.copy_within(sent.., 0);
        self.emcy_len -= sent;
    }

    /// Records `code` (with additional information `info`) as the newest
    /// entry of 0x1003, and the uptime (0x200C) as its time in 0x2012 (same
    /// sub-index: the two move together). A code already in the history
    /// moves to sub 1 instead of appearing twice (a flapping condition
    /// fills no history; its time is that of its latest raise).
    fn record_error(&mut self, code: u16, info: u32) {
        let n = (self.get(0x1003, 0) as u8).min(8);
        let found = (1..=n).find(|&s| self.get(0x1003, s) & 0xFFFF == code as u32);
        // Shift subs 1..last down by one, newest at sub 1.
        let last = found.unwrap_or((n + 1).min(8));
        for s in (2..=last).rev() {
            let prev = self.get(0x1003, s - 1);
            self.set(0x1003, s, prev);
            let at = self.get(0x2012, s - 1);
            self.set(0x2012, s, at);
        }
        self.set(0x1003, 1, (info << 16) | code as u32);
        let now = self.get(0x200C, 0);
        self.set(0x2012, 1, now);
        if found.is_none() {
            self.set(0x1003, 0, (n + 1).min(8) as u32);
        }
    }

    fn update_error_register(&mut self) {
        let mut reg = 0u8;
        for &(_, r) in self.active[..self.n_active]
            .iter()
            .chain(&self.overflow.code)
        {
            reg |= r | error_register::GENERIC;
        }
        reg |= self.overflow.lost;
        self.set(0x1001, 0, reg as u32);
    }

    /// Queues an EMCY for the next poll. In stopped EMCYs wait for the
    /// next pre-operational or operational (CiA 301 allows no EMCY in
    /// stopped; CANopenNode's `CO_EM_process` keeps its FIFO and sends it
    /// then), so the master sees every code raised meanwhile and never an
    /// error reset without its raise; a condition that came and went
    /// while stopped cancels out (its raise is still queued: both are
    /// dropped) and is only in 0x1003.
    fn queue_emcy(&mut self, payload: [u8; 8]) {
        if self.state == NmtState::Stopped && payload[..2] == [0, 0] {
            let raised = self.emcy_queue[..self.emcy_len]
                .iter()
                .rposition(|q| q[..2] == payload[3..5]);
            if let Some(k) = raised {
                self.emcy_queue.copy_within(k + 1..self.emcy_len, k);
                self.emcy_len -= 1;
                return;
            }
        }
        if self.emcy_len == EMCY_QUEUE {
            // Drop the oldest: the newest state matters most.
            self.emcy_queue.copy_within(1.., 0);
            self.emcy_len -= 1;
        }
        self.emcy_queue[self.emcy_len] = payload;
        self.emcy_len += 1;
    }

    /// Write rules common to SDO downloads and segmented-download checks.
    fn write_allowed(&self, index: u16, e: &od::Entry) -> Result<(), SdoAbort> {
        if !matches!(e.access, Access::Rw | Access::Wo) {
            return Err(SdoAbort::ReadOnly);
        }
        match e.class {
            Class::Calibration => {
                if self.state != NmtState::PreOperational {
                    return Err(SdoAbort::State);
                }
                if !self.unlocked {
                    return Err(SdoAbort::Locked);
                }
            }
            // Program download and control (CiA 302-3): pre-operational.
            Class::Config | Class::Command
                if (e.class == Class::Config || matches!(index, 0x2010 | 0x1F50 | 0x1F51))
                    && self.state != NmtState::PreOperational =>
            {
                return Err(SdoAbort::State);
            }
            _ => {}
        }
        Ok(())
    }

    /// Object-specific semantics of a write of `v` to `(index, sub)` that
    /// passed the generic checks. Returns the value to store.
    fn special_write(&mut self, index: u16, sub: u8, v: u32) -> Result<Option<Written>, SdoAbort> {
        match index {
            0x1003 => {
                // Only 0 is accepted (limits): clears the history.
                for s in 1..=8 {
                    self.set(0x1003, s, 0);
                    self.set(0x2012, s, 0);
                }
                self.set(0x1003, 0, 0);
                Ok(Some(Written::Done))
            }
            0x1010 | 0x1011 => {
                let group = Group::of_sub(sub).ok_or(SdoAbort::NoSub)?;
                let (sig, req) = if index == 0x1010 {
                    (SAVE_SIGNATURE, Request::Store(group))
                } else {
                    (LOAD_SIGNATURE, Request::Restore(group))
                };
                if v != sig || self.request.is_some() {
                    return Err(SdoAbort::Store);
                }
                self.request = Some(req);
                self.event(Events::REQUEST);
                Ok(Some(Written::Deferred))
            }
            0x1F51 => {
                if self.request.is_some() {
                    return Err(SdoAbort::Store);
                }
                self.request = Some(Request::ProgramControl(v as u8));
                self.event(Events::REQUEST);
                Ok(Some(Written::Deferred))
            }
            0x1017 => {
                self.set(0x1017, 0, v);
                self.hb_restart = true;
                Ok(Some(Written::Done))
            }
            0x1016 => self.write_hb_consumer(sub, v),
            0x1019 => {
                // 1 is reserved (CiA 301 §7.5.2.22); a new value restarts
                // the SYNC start values.
                if v == 1 {
                    return Err(SdoAbort::Range);
                }
                self.set(0x1019, 0, v);
                for rt in self.tpdo.iter_mut() {
                    rt.started = false;
                }
                Ok(Some(Written::Done))
            }
            0x1400 => self.write_rpdo_comm(sub, v),
            0x2500 => self.command(v),
            0x1800..=0x1803 => self.write_tpdo_comm((index - 0x1800) as usize, sub, v),
            0x1A00..=0x1A03 => {
                let k = (index - 0x1A00) as usize;
                if self.tpdo_valid(k) {
                    return Err(SdoAbort::State);
                }
                if sub == 0 {
                    let (map, _) = self.mapping_of(k);
                    Self::check_mapping(&map, v as usize)?;
                } else {
                    if self.get(index, 0) != 0 {
                        return Err(SdoAbort::State);
                    }
                    if v != 0 {
                        Self::check_map_entry(v)?;
                    }
                }
                Ok(None)
            }
            0x2300 => self.check_scan(sub, v).map(|()| None),
            0x2310 => self.check_surface(sub, v).map(|()| None),
            0x2101..=0x2104 => self.check_table(index, sub, v).map(|()| None),
            0x2010 => {
                if v == UNLOCK_SIGNATURE {
                    self.unlocked = true;
                    self.set(0x2010, 0, 1);
                } else if v == 0 {
                    self.unlocked = false;
                    self.set(0x2010, 0, 0);
                } else {
                    return Err(SdoAbort::Range);
                }
                Ok(Some(Written::Done))
            }
            _ => Ok(None),
        }
    }

    /// Writes TPDO communication parameter `sub` of TPDO `k` (CiA 301
    /// §7.5.2.35): COB-ID bits 0-30 and the inhibit time only while the PDO
    /// does not exist (0x06090030 otherwise), a valid COB-ID only with
    /// bit 30 = 1 (no RTR); transmission type and event timer at any time.
    fn write_tpdo_comm(&mut self, k: usize, sub: u8, v: u32) -> Result<Option<Written>, SdoAbort> {
        let index = 0x1800 + k as u16;
        match sub {
            1 => {
                let old = self.get(index, 1);
                if v & 0x2000_0000 != 0 || v & 0x1FFF_F800 != 0 {
                    return Err(SdoAbort::Range);
                }
                let valid = v & 0x8000_0000 == 0;
                if valid {
                    // Bit 30 = 0 would allow remote frames, which the
                    // device never answers: a TPDO that exists must have
                    // it set. (CANopenNode's OD_write_18xx refuses only
                    // bits 11-29, a moved or restricted CAN-ID and an
                    // empty mapping; it ignores bit 30 and its TPDOs do
                    // not answer RTR either.) An invalid PDO's bit 30 is
                    // not checked: it describes nothing on the bus.
                    if v & 0x4000_0000 == 0 || !cob_allowed(v & 0x7FF) {
                        return Err(SdoAbort::Range);
                    }
                    // CiA 301 §7.5.2.35: bits 0-30 change only
                    // while the PDO does not exist.
                    if old & 0x8000_0000 == 0 && old & 0x7FFF_FFFF != v & 0x7FFF_FFFF {
                        return Err(SdoAbort::Range);
                    }
                }
                self.set(index, 1, v);
                self.tpdo[k] = TpdoRt::default();
                Ok(Some(Written::Done))
            }
            2 => {
                if !(v <= 240 || v >= 254) {
                    return Err(SdoAbort::Range);
                }
                self.set(index, 2, v);
                self.tpdo[k].sync_count = 0;
                self.arm_event_timers(Some(k));
                Ok(Some(Written::Done))
            }
            3 | 6 if self.tpdo_valid(k) => {
                // The inhibit time and the SYNC start value change only
                // while the PDO does not exist (CiA 301 §7.5.2.35).
                Err(SdoAbort::Range)
            }
            5 => {
                self.set(index, 5, v);
                self.arm_event_timers(Some(k));
                Ok(Some(Written::Done))
            }
            _ => Ok(None),
        }
    }

    /// 0x2300 sub 1 (period) and sub 2 (oversampling) are checked
    /// together: one scan at the oversampling ratio must fit into the
    /// period ([`Defaults::adc_scan_ns`]); otherwise 0x06090030 (the value
    /// is outside the range the other sub-index allows; 0x08000022 is kept
    /// for the NMT state). Raise the period before the oversampling.
    fn check_scan(&self, sub: u8, v: u32) -> Result<(), SdoAbort> {
        let (period_us, ratio) = match sub {
            1 => (v, self.get(0x2300, 2)),
            2 => (self.get(0x2300, 1), v),
            _ => return Ok(()),
        };
        let scan_ns = self.defaults.adc_scan_ns as u64;
        if scan_ns == 0 || ratio as u64 * scan_ns <= period_us as u64 * 1000 {
            Ok(())
        } else {
            Err(SdoAbort::Range)
        }
    }

    /// 0x2310 beyond the per-entry limits: a radius of magnitude below
    /// [`SURFACE_RADIUS_MIN_MM`] (zero included) is refused, and with the
    /// cylinder model the axis (subs 3-5) must stay at least
    /// [`SURFACE_AXIS_MIN_LEN`] long: selecting the cylinder with a zero
    /// axis or zeroing the axis of a selected cylinder is refused. Both
    /// abort 0x06090030 (value range exceeded). Set the axis before the
    /// model.
    fn check_surface(&self, sub: u8, v: u32) -> Result<(), SdoAbort> {
        if sub == 2 && !(f32::from_bits(v).abs() >= SURFACE_RADIUS_MIN_MM) {
            return Err(SdoAbort::Range);
        }
        let model = if sub == 1 { v } else { self.get(0x2310, 1) };
        if model != SURFACE_CYLINDER as u32 || sub == 2 {
            return Ok(());
        }
        let axis: [f32; 3] = core::array::from_fn(|k| {
            let s = k as u8 + 3;
            f32::from_bits(if s == sub { v } else { self.get(0x2310, s) })
        });
        let len2 = axis.iter().map(|a| a * a).sum::<f32>();
        if len2 >= SURFACE_AXIS_MIN_LEN * SURFACE_AXIS_MIN_LEN {
            Ok(())
        } else {
            Err(SdoAbort::Range)
        }
    }

    /// 0x2101..0x2104 sub 16..23 beyond the per-entry limits: the
    /// linearity table the write leaves must be inactive (coefficients all
    /// zero) or have strictly ascending knots
    /// ([`SensorCalibration::table_valid`]); otherwise 0x06090030. Write
    /// the knots before the coefficients, and zero the coefficients before
    /// changing the knots of an active table.
    fn check_table(&self, index: u16, sub: u8, v: u32) -> Result<(), SdoAbort> {
        if !(CAL_SUB_KNOTS..CAL_SUB_SPOT).contains(&sub) {
            return Ok(());
        }
        let value = |s: u8| {
            if s == sub {
                v
            } else {
                self.get(index, s)
            }
        };
        if table_ok(value) {
            Ok(())
        } else {
            Err(SdoAbort::Range)
        }
    }

    /// Whether a persisted value would be accepted (image load).
    fn valid_persisted(&self, index: u16, sub: u8, e: &od::Entry, v: u32) -> bool {
        if (index, sub, v) == (0x2400, 1, u32::from(crate::lss::UNCONFIGURED)) {
            return true; // non-configured (LSS), see device_lss.rs
        }
        if check_limits(e.limits, e.ty, v).is_err() {
            return false;
        }
        let max = match e.ty {
            DataType::U8 => 0xFF,
            DataType::U16 => 0xFFFF,
            _ => u32::MAX,
        };
        if v > max {
            return false;
        }
        match (index, sub) {
            // Bit 30 is not checked here: firmware before the bit-30 rule
            // of `write_tpdo_comm` may have stored a valid COB-ID with it
            // clear; refusing would drop the whole image, and the PDO
            // behaves the same either way (no RTR is ever answered).
            (0x1800..=0x1803, 1) => {
                v & 0x3FFF_F800 == 0 && (v & 0x8000_0000 != 0 || cob_allowed(v & 0x7FF))
            }
            (0x1800..=0x1803, 2) => v <= 240 || v >= 254,
            (0x1400, 1) => v & 0x7FFF_F800 == 0 && (v & 0x8000_0000 != 0 || cob_allowed(v & 0x7FF)),
            (0x1019, 0) => v != 1,
            (0x1016, _) => (v >> 16) & 0xFF <= 127,
            (0x1A00..=0x1A03, s) if s > 0 => v == 0 || Self::check_map_entry(v).is_ok(),
            (0x2310, 2) => f32::from_bits(v).abs() >= SURFACE_RADIUS_MIN_MM,
            _ => true,
        }
    }
}

impl Dictionary for Core {
    fn read(&self, index: u16, sub: u8) -> Result<Value, SdoAbort> {
        let (s, e) = od::find(index, sub).map_err(|l| match l {
            Lookup::NoObject => SdoAbort::NoObject,
            Lookup::NoSub => SdoAbort::NoSub,
        })?;
        if e.access == Access::Wo {
            return Err(SdoAbort::WriteOnly);
        }
        Ok(match e.init {
            Init::Text(t) => Value::Str(self.text(t).as_bytes()),
            _ => Value::Num(self.values[s].to_le_bytes(), e.ty.size()),
        })
    }

    fn check_write(&self, index: u16, sub: u8, len: Option<usize>) -> Result<(), SdoAbort> {
        let (_, e) = od::find(index, sub).map_err(|l| match l {
            Lookup::NoObject => SdoAbort::NoObject,
            Lookup::NoSub => SdoAbort::NoSub,
        })?;
        if !matches!(e.access, Access::Rw | Access::Wo) {
            return Err(SdoAbort::ReadOnly);
        }
        let size = e.ty.size();
        if let Some(a) = len.and_then(|l| crate::sdo::length_abort(size, l)) {
            if e.ty != DataType::Domain {
                return Err(a);
            }
        }
        self.write_allowed(index, e)
    }

    fn domain(&self, index: u16, sub: u8) -> bool {
        od::find(index, sub).is_ok_and(|(_, e)| e.ty == DataType::Domain)
    }

    fn write_part(
        &mut self,
        index: u16,
        sub: u8,
        offset: u32,
        data: &[u8],
        last: bool,
    ) -> Result<Written, SdoAbort> {
        self.check_write(index, sub, None)?;
        if self.request.is_some() {
            return Err(SdoAbort::Store);
        }
        let len = u16::try_from(data.len()).map_err(|_| SdoAbort::TooLong)?;
        self.request = Some(Request::ProgramData { offset, len, last });
        self.event(Events::REQUEST);
        Ok(Written::Deferred)
    }

    fn write(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<Written, SdoAbort> {
        self.check_write(index, sub, Some(data.len()))?;
        let (s, e) = od::find(index, sub).map_err(|_| SdoAbort::NoObject)?;
        let v = decode(e.ty, data);
        check_limits(e.limits, e.ty, v)?;
        if let Some(w) = self.special_write(index, sub, v)? {
            return Ok(w);
        }
        self.values[s] = v;
        if matches!(e.class, Class::Calibration | Class::Config) {
            self.config_changed();
        }
        Ok(Written::Done)
    }
}

impl Device {
    /// A device with node-id `node_id` (1..=127; other values are taken
    /// as 1) and the given defaults, in state [`NmtState::Initialising`]. The
    /// application may call [`Device::load_image`] before the first
    /// [`Device::poll`], which sends the boot-up message.
    pub fn new(node_id: u8, defaults: &Defaults) -> Self {
        let mut slot = MaybeUninit::uninit();
        Device::init(&mut slot, node_id, defaults);
        // SAFETY: `init` wrote every field.
        unsafe { slot.assume_init() }
    }

    /// Makes this device what [`Device::new`] with these arguments makes,
    /// in place (no device-sized temporary on the stack).
    pub fn reinit(&mut self, node_id: u8, defaults: &Defaults) {
        const { assert!(!core::mem::needs_drop::<Device>()) };
        // SAFETY: `MaybeUninit<Device>` has the layout of `Device`;
        // `init` writes a complete, valid device, and the old one needs
        // no drop (asserted above).
        let slot = unsafe { &mut *(self as *mut Device).cast::<MaybeUninit<Device>>() };
        Device::init(slot, node_id, defaults);
    }

    /// [`Device::new`] built in place in `slot` (a static, for the
    /// firmware): no copy of the device (≈ 4.8 KiB) passes through a stack
    /// frame (issue 50 item 6). Returns the device.
    pub fn init<'a>(
        slot: &'a mut MaybeUninit<Device>,
        node_id: u8,
        defaults: &Defaults,
    ) -> &'a mut Device {
        // 0xFF: a non-configured node (CiA 305), waiting for LSS.
        let unconfigured = node_id == crate::lss::UNCONFIGURED;
        let node_id = if (1..=127).contains(&node_id) {
            node_id
        } else {
            1
        };
        let d = slot.as_mut_ptr();
        // SAFETY: every field of `Device`, of its `Core` and of its
        // `SdoServer` is written once through a raw pointer into `slot`
        // (never read before); the arrays are zeroed in place (all-zero
        // is a valid `[u32; N]` / `[u8; N]`). `Core`'s fields are listed
        // in `core_fields`, which stops compiling when one is added.
        unsafe {
            let c = addr_of_mut!((*d).core);
            addr_of_mut!((*c).defaults).write(*defaults);
            addr_of_mut!((*c).node_id).write(node_id);
            addr_of_mut!((*c).values).write_bytes(0, 1);
            addr_of_mut!((*c).boot).write_bytes(0, 1);
            addr_of_mut!((*c).state).write(NmtState::Initialising);
            addr_of_mut!((*c).unlocked).write(false);
            addr_of_mut!((*c).hb_next).write(None);
            addr_of_mut!((*c).hb_restart).write(true);
            addr_of_mut!((*c).hb_sent).write(0);
            addr_of_mut!((*c).uptime_next_us).write(0);
            addr_of_mut!((*c).tpdo).write([TpdoRt::default(); TPDOS]);
            addr_of_mut!((*c).pdo_maps).write([PdoMap::default(); TPDOS]);
            addr_of_mut!((*c).active).write([(0, 0); MAX_ACTIVE_ERRORS]);
            addr_of_mut!((*c).n_active).write(0);
            addr_of_mut!((*c).overflow).write(Overflow::default());
            addr_of_mut!((*c).emcy_queue).write([[0; 8]; EMCY_QUEUE]);
            addr_of_mut!((*c).emcy_len).write(0);
            addr_of_mut!((*c).emcy_last_tx).write(None);
            addr_of_mut!((*c).request).write(None);
            addr_of_mut!((*c).events).write(0);
            addr_of_mut!((*c).config_gen).write(0);
            addr_of_mut!((*c).syncs).write(SyncRt::default());
            addr_of_mut!((*c).hb_cons).write([HbMonitor::default(); HB_CONSUMERS]);
            addr_of_mut!((*c).rom_loader_locked).write(false);
            SdoServer::init(addr_of_mut!((*d).sdo), defaults.sdo_timeout_us);
            addr_of_mut!((*d).lss).write(lss_glue::LssRt::default());
        }
        // SAFETY: initialised above.
        let dev = unsafe { slot.assume_init_mut() };
        let core = &mut dev.core;
        for (s, _, e) in od::entries() {
            core.values[s] = core.init_value(e, node_id);
        }
        if unconfigured {
            core.set(0x2400, 1, u32::from(crate::lss::UNCONFIGURED));
        }
        core.boot.copy_from_slice(&core.values);
        dev
    }

    // ------------------------------------------------------------------
    // Bus side

    /// Handles a received frame at time `now_us`; responses (SDO answers,
    /// TPDOs on SYNC) go to `out`. Malformed frames, remote frames and
    /// frames not addressed to this node are ignored; so is everything
    /// until the boot-up message has been sent.
    pub fn handle(&mut self, frame: &Frame, now_us: u64, out: &mut impl FnMut(Frame)) {
        if !frame.is_well_formed()
            || frame.rtr
            || self.lss_handle(frame, now_us, out)
            || self.core.state == NmtState::Initialising
        {
            return;
        }
        if self.handle_sync(frame, now_us) {
            return;
        }
        let node = self.core.node_id as u16;
        let p = frame.payload();
        match frame.id {
            0x000 => self.nmt(p),
            0x080 => self.sync(p, now_us, out),
            id if id == 0x600 + node => {
                if matches!(
                    self.core.state,
                    NmtState::PreOperational | NmtState::Operational
                ) {
                    if let Some(r) = self.sdo.handle(&mut self.core, p, now_us) {
                        out(Frame::new(0x580 + node, &r));
                    }
                }
            }
            _ => {}
        }
    }

    fn nmt(&mut self, p: &[u8]) {
        let (Some(&cs), Some(&target)) = (p.first(), p.get(1)) else {
            return;
        };
        if target != 0 && target != self.core.node_id {
            return;
        }
        match cs {
            0x01 => self.core.set_state(NmtState::Operational),
            0x02 => {
                self.sdo.reset();
                self.core.set_state(NmtState::Stopped);
            }
            0x80 => self.core.set_state(NmtState::PreOperational),
            0x81 => {
                self.sdo.reset();
                self.core.reset_node();
            }
            0x82 => {
                self.sdo.reset();
                self.core.reset_comm();
            }
            _ => {}
        }
    }

    /// Produces what is due at `now_us`: the boot-up message after a
    /// power-on or reset, heartbeats, queued emergencies, event-driven
    /// TPDOs (event timer, application events after the inhibit time) and
    /// SDO timeout aborts. Call it at least every millisecond.
    pub fn poll(&mut self, now_us: u64, out: &mut impl FnMut(Frame)) {
        // Non-configured (LSS only) or switching the bit rate: silent.
        if self.lss_poll(now_us) {
            return;
        }
        let c = &mut self.core;
        let node = c.node_id as u16;
        // (A reset puts the value back to 0: computed again at once.)
        if now_us >= c.uptime_next_us || c.values.get(UPTIME) == Some(&0) {
            let s = now_us / 1_000_000;
            c.uptime_next_us = (s + 1) * 1_000_000;
            if let Some(v) = c.values.get_mut(UPTIME) {
                *v = s as u32;
            }
        }
        // The boot-up is the node's first frame: the poll that sends it
        // sends no EMCY (raised while initialising, they wait for the next
        // poll). A transmit queue in CAN priority order (perpend-board's
        // `txq`, the FDCAN's buffers) would otherwise put a same-poll EMCY
        // (0x080 + id) ahead of it (0x700 + id): seen on the virtual board.
        // CANopenNode does the same: `CO_process` decides whether EMCYs may
        // go from the NMT state before its NMT step.
        let booting = c.state == NmtState::Initialising;
        if booting {
            out(Frame::new(0x700 + node, &[0]));
            c.set_state(NmtState::PreOperational);
            c.hb_restart = true;
        }
        if let Some(r) = self.sdo.check_timeout(now_us) {
            out(Frame::new(0x580 + node, &r));
        }
        // Heartbeat.
        let hb = c.get(0x1017, 0) as u64 * 1000;
        if c.hb_restart {
            c.hb_restart = false;
            c.hb_next = (hb > 0).then(|| now_us + hb);
        }
        if let Some(t) = c.hb_next {
            if now_us >= t {
                out(Frame::new(0x700 + node, &[c.state.heartbeat_code()]));
                c.hb_sent = c.hb_sent.wrapping_add(1);
                // Keep the cadence; if far behind, restart from now.
                let next = t + hb;
                c.hb_next = Some(if next > now_us { next } else { now_us + hb });
            }
        }
        // Heartbeats consumed and TPDOs waiting for a SYNC's sample.
        self.poll_sync(now_us, out);
        let c = &mut self.core;
        // Emergencies (not in stopped, not with the boot-up), at most one
        // per inhibit time.
        if c.state != NmtState::Stopped && !booting {
            c.send_emcys(now_us, out);
        }
        // Event-driven TPDOs.
        if c.state == NmtState::Operational {
            for k in 0..TPDOS {
                let idx = 0x1800 + k as u16;
                if !c.tpdo_valid(k) || !matches!(c.get(idx, 2), 254 | 255) {
                    continue;
                }
                let timer = c.get(idx, 5) as u64 * 1000;
                let inhibit = c.get(idx, 3) as u64 * 100;
                let rt = c.tpdo[k];
                if timer > 0 && rt.timer_due.is_none() {
                    c.tpdo[k].timer_due = Some(now_us + timer);
                }
                let timer_fired = c.tpdo[k].timer_due.is_some_and(|t| now_us >= t);
                // Event timer or change of the mapped data, never closer
                // than the inhibit time to the previous transmission.
                let inhibit_ok = rt.last_tx.is_none_or(|l| now_us >= l + inhibit);
                if (timer_fired || rt.event_pending) && inhibit_ok {
                    c.send_tpdo(k, now_us, out);
                    c.tpdo[k].timer_due = (timer > 0).then(|| now_us + timer);
                }
            }
        }
    }

    // ------------------------------------------------------------------
    // Application side: state and identity

    /// Current NMT state.
    pub fn nmt_state(&self) -> NmtState {
        self.core.state
    }

    /// Active node-id.
    pub fn node_id(&self) -> u8 {
        self.core.node_id
    }

    /// The defaults the device was created with.
    pub fn defaults(&self) -> &Defaults {
        &self.core.defaults
    }

    /// Whether calibration writes are unlocked (0x2010).
    pub fn calibration_unlocked(&self) -> bool {
        self.core.unlocked
    }

    /// Returns and clears the events since the last call.
    pub fn take_events(&mut self) -> Events {
        Events(core::mem::take(&mut self.core.events))
    }

    /// Counter incremented whenever calibration or configuration values
    /// change (compare with a saved value to know when to re-read them).
    pub fn config_generation(&self) -> u32 {
        self.core.config_gen
    }

    // ------------------------------------------------------------------
    // Application side: measurement

    /// Publishes one sample: writes 0x2001..0x2006, increments the sample
    /// counter 0x2007 and marks the TPDOs of types 0, 254 and 255 whose
    /// mapped data changed since their last transmission (beyond the
    /// deadbands of 0x2009): type 0 is sent at the next SYNC, 254/255 at the
    /// next poll after the inhibit time.
    pub fn set_measurement(&mut self, m: &Measurement) {
        // Compile-time slots (a lookup each cost ≈ 15 instructions a
        // sample, issue 50 item 8).
        const NORMAL: usize = od::slot_of(0x2001, 1);
        const ANGLES: usize = od::slot_of(0x2002, 1);
        const ATTITUDE: usize = od::slot_of(0x2003, 1);
        const DISTANCES: usize = od::slot_of(0x2004, 1);
        const STATUS: usize = od::slot_of(0x2005, 0);
        const RMS: usize = od::slot_of(0x2006, 0);
        const COUNTER: usize = od::slot_of(0x2007, 0);
        let c = &mut self.core;
        let mut put = |s: usize, v: &[f32]| {
            if let Some(dst) = c.values.get_mut(s..s + v.len()) {
                for (d, x) in dst.iter_mut().zip(v) {
                    *d = x.to_bits();
                }
            }
        };
        put(NORMAL, &m.normal);
        put(ANGLES, &[m.theta1_deg, m.theta2_deg, m.theta_deg]);
        put(ATTITUDE, &[m.pitch_deg, m.yaw_deg]);
        put(DISTANCES, &m.distances_mm);
        put(RMS, &[m.rms_mm]);
        if let Some(v) = c.values.get_mut(STATUS) {
            *v = m.status;
        }
        if let Some(v) = c.values.get_mut(COUNTER) {
            *v = v.wrapping_add(1);
        }
        c.mark_changed_tpdos();
    }

    /// Publishes one sample like [`Device::set_measurement`] and keeps the
    /// emergencies in step with its status word: per sensor
    /// [`status::emcy::sensor_current`] while its nibble has open loop or
    /// overcurrent, else [`status::emcy::sensor_reading`] while it is not
    /// valid; [`status::emcy::NO_PLANE`] while bit 19 is set;
    /// [`status::emcy::DATA_SET`] while bit 21 is set. Each is raised on the
    /// sample where its condition starts and cleared where it ends (EMCY
    /// frames only on changes).
    pub fn publish(&mut self, m: &Measurement) {
        self.set_measurement(m);
        let st = m.status;
        let stuck = u8::from(st & status::SENSOR_STUCK != 0);
        let mut valid = 0u8;
        for i in 0..status::SENSORS {
            let nib = status::sensor_nibble(st, i);
            let current = nib & (status::SENSOR_OPEN_LOOP | status::SENSOR_OVERCURRENT) != 0;
            let ok = nib & status::SENSOR_VALID != 0;
            valid += u8::from(ok);
            let data = [i as u8 + 1, nib as u8, 0, 0, 0];
            self.set_emcy(
                status::emcy::sensor_current(i),
                current,
                error_register::CURRENT,
                data,
            );
            self.set_emcy(
                status::emcy::sensor_reading(i),
                !current && !ok,
                error_register::MANUFACTURER,
                [i as u8 + 1, nib as u8, stuck, 0, 0],
            );
        }
        self.set_emcy(
            status::emcy::NO_PLANE,
            st & status::NO_PLANE != 0,
            error_register::MANUFACTURER,
            [valid, 0, 0, 0, 0],
        );
        self.set_emcy(
            status::emcy::DATA_SET,
            st & status::CONFIG_INVALID != 0,
            error_register::GENERIC,
            [0; 5],
        );
    }

    fn set_emcy(&mut self, code: u16, on: bool, reg: u8, mfr: [u8; 5]) {
        if on {
            self.signal_emcy(code, reg, mfr);
        } else {
            self.clear_emcy(code);
        }
    }

    /// The published measurement (0x2001..0x2006).
    pub fn measurement(&self) -> Measurement {
        let c = &self.core;
        Measurement {
            normal: [
                c.get_f32(0x2001, 1),
                c.get_f32(0x2001, 2),
                c.get_f32(0x2001, 3),
            ],
            theta1_deg: c.get_f32(0x2002, 1),
            theta2_deg: c.get_f32(0x2002, 2),
            theta_deg: c.get_f32(0x2002, 3),
            pitch_deg: c.get_f32(0x2003, 1),
            yaw_deg: c.get_f32(0x2003, 2),
            distances_mm: core::array::from_fn(|i| c.get_f32(0x2004, i as u8 + 1)),
            status: c.get(0x2005, 0),
            rms_mm: c.get_f32(0x2006, 0),
        }
    }

    /// The status word 0x2005.
    pub fn status(&self) -> u32 {
        self.core.get(0x2005, 0)
    }

    /// The sample counter 0x2007.
    pub fn sample_counter(&self) -> u32 {
        self.core.get(0x2007, 0)
    }

    /// Sets the transmit-queue counters 0x2008 (sub 1 frames dropped
    /// because the software queue was full, sub 2 its peak fill, both
    /// since power-on). They are not measurements: no TPDO event.
    pub fn set_tx_counters(&mut self, dropped: u32, peak: u32) {
        self.core.set(0x2008, 1, dropped);
        self.core.set(0x2008, 2, peak);
    }

    /// Sets the die temperature 0x200A [°C] (not a measurement of the
    /// pipeline: no TPDO event).
    pub fn set_die_temperature(&mut self, t_c: f32) {
        self.core.set(0x200A, 0, t_c.to_bits());
    }

    /// Sets board-health value 0x200B sub `sub` (1 reset flags, 2 worst
    /// loop cycles, 3 stack used bytes, 4 VREF+ mV).
    pub fn set_board_health(&mut self, sub: u8, v: u32) {
        self.core.set(0x200B, sub, v);
    }

    // ------------------------------------------------------------------
    // Application side: calibration and configuration

    /// The calibration and configuration objects as they are now.
    pub fn objects(&self) -> Objects<'_> {
        Objects {
            values: &self.core.values,
            node_id: self.core.node_id,
        }
    }

    /// Calibration of sensor `i` (0-based; `None` beyond 3): 0x2101 + i.
    pub fn calibration(&self, i: usize) -> Option<SensorCalibration> {
        self.objects().calibration(i)
    }

    /// Transfer function of sensor `i` (0-based): 0x2201 + i.
    pub fn transfer(&self, i: usize) -> Option<TransferFunction> {
        self.objects().transfer(i)
    }

    /// Surface model 0x2310 (issue 14).
    pub fn surface(&self) -> SurfaceModel {
        self.objects().surface()
    }

    /// The head's thermal time constant 0x2105 \[s\] (0 = no lag).
    pub fn thermal_tau_s(&self) -> f32 {
        self.objects().thermal_tau_s()
    }

    /// Acquisition settings 0x2300.
    pub fn acquisition(&self) -> Acquisition {
        self.objects().acquisition()
    }

    /// Communication settings 0x2400 as configured (they become active at
    /// the next reset; the active node-id is [`Device::node_id`]).
    pub fn communication(&self) -> Communication {
        self.objects().communication()
    }

    /// Whether the calibration objects still hold the defaults' head
    /// (status bit [`crate::status::UNCALIBRATED`]).
    pub fn calibration_is_default(&self) -> bool {
        (0..4).all(|i| self.calibration(i) == self.core.defaults.calibration.get(i).copied())
    }

    /// Heartbeat period 0x1017 \[ms\].
    pub fn heartbeat_ms(&self) -> u16 {
        self.core.get(0x1017, 0) as u16
    }

    /// Heartbeats sent since the device was built (not the boot-up
    /// message), wrapping: a caller that compares it before and after
    /// [`Device::poll`] knows whether the poll sent one without wrapping
    /// the poll's output (each closure type is one more copy of the send
    /// paths in flash).
    pub fn heartbeats_sent(&self) -> u32 {
        self.core.hb_sent
    }

    /// Raw value of a numeric entry (`u32`; REAL32 as its bits). `None` for
    /// unknown entries and strings.
    pub fn read_u32(&self, index: u16, sub: u8) -> Option<u32> {
        let (s, e) = od::find(index, sub).ok()?;
        (e.ty != DataType::VisibleString).then(|| self.core.values[s])
    }

    /// Value of a REAL32 entry. `None` for unknown or non-REAL32 entries.
    pub fn read_f32(&self, index: u16, sub: u8) -> Option<f32> {
        let (s, e) = od::find(index, sub).ok()?;
        (e.ty == DataType::Real32).then(|| f32::from_bits(self.core.values[s]))
    }

    /// Value of a VISIBLE_STRING entry.
    pub fn read_str(&self, index: u16, sub: u8) -> Option<&'static str> {
        match od::find(index, sub).ok()?.1.init {
            Init::Text(t) => Some(self.core.text(t)),
            _ => None,
        }
    }

    // ------------------------------------------------------------------
    // Application side: emergencies

    /// Raises emergency `code` with error-register bits `reg` and 5 bytes of
    /// manufacturer data: sends one EMCY (at the next poll after the
    /// inhibit time 0x1015; in stopped it waits for pre-operational or
    /// operational, and is dropped with its error reset when the code
    /// clears before), sets 0x1001 and records the code in 0x1003
    /// (newest at sub 1; bits 16-31 = `mfr[0..2]`; a code already in the
    /// history moves to sub 1). Returns `false` (and sends nothing) if
    /// `code` is already active.
    ///
    /// With [`MAX_ACTIVE_ERRORS`] codes active, the next new code is
    /// still sent and active (the overflow bucket); codes raised after it
    /// while the table stays full are not recorded (nothing tells them
    /// from repeats): the first of them sends [`EMCY_TABLE_FULL`] with its
    /// code in manufacturer bytes 0-1, and the error-register bits of all
    /// of them stay in 0x1001 until no recorded code is active (then
    /// [`EMCY_TABLE_FULL`]'s error reset). Once a slot or the bucket frees
    /// up, the next raise of such a code is sent and recorded with its own
    /// code: one EMCY per code, never a flood.
    pub fn signal_emcy(&mut self, code: u16, reg: u8, mfr: [u8; 5]) -> bool {
        self.core.raise(code, reg, mfr)
    }

    /// Clears emergency `code`: one "error reset" EMCY (code 0x0000, CiA
    /// 301 §7.2.7.1) per clear, with the error register that remains and
    /// the cleared code in manufacturer bytes 0-1 (little-endian). Returns
    /// whether `code` was active.
    pub fn clear_emcy(&mut self, code: u16) -> bool {
        self.core.clear(code)
    }

    /// Whether emergency `code` is active.
    #[inline]
    pub fn emcy_active(&self, code: u16) -> bool {
        self.core.is_active(code)
    }

    /// Whether any emergency is active (recorded, or in the overflow
    /// bucket).
    pub fn any_emcy_active(&self) -> bool {
        self.core.n_active != 0 || self.core.overflow != Overflow::default()
    }

    /// Error register 0x1001.
    pub fn error_register(&self) -> u8 {
        self.core.get(0x1001, 0) as u8
    }

    // ------------------------------------------------------------------
    // Application side: persistence

    /// The store/restore request waiting for the application, if any.
    pub fn pending_request(&self) -> Option<Request> {
        self.core.request
    }

    /// The data of a pending [`Request::ProgramData`] (empty otherwise):
    /// they stay in the SDO server's buffer until
    /// [`Device::finish_request`].
    pub fn program_part(&self) -> &[u8] {
        match self.core.request {
            Some(Request::ProgramData { len, .. }) => self.sdo.part(usize::from(len)),
            _ => &[],
        }
    }

    /// Whether an SDO block download is in progress.
    pub fn sdo_in_block(&self) -> bool {
        self.sdo.in_block()
    }

    /// Sets what 0x1F56 sub 1 (application software identification) and
    /// 0x1F57 sub 1 (flash status, [`od::FLASH_OK`] and the other CiA
    /// 302-3 codes) read.
    pub fn set_program_status(&mut self, identification: u32, flash_status: u32) {
        self.core.set(0x1F56, 1, identification);
        self.core.set(0x1F57, 1, flash_status);
    }

    /// Completes the pending request: `ok` tells whether the storage
    /// operation succeeded. The SDO confirmation (or abort 0x08000020) goes
    /// to `out`. On success a store makes the current persisted values the
    /// power-on values (a store of the application group also counts itself
    /// in 0x2011 sub 3, current value included); a restore makes the
    /// defaults the power-on values (applied at the next reset node; the
    /// calibration stamp's default is 0, its count included).
    ///
    /// # Errors
    /// [`Error::NoRequest`] when nothing is pending.
    pub fn finish_request(&mut self, ok: bool, out: &mut impl FnMut(Frame)) -> Result<(), Error> {
        let req = self.core.request.take().ok_or(Error::NoRequest)?;
        if ok {
            for (s, index, e) in od::entries() {
                if e.persist {
                    self.core.boot[s] = self.core.staged(req, s, index, e);
                }
            }
            if let Request::Store(g) = req {
                if g.contains(0x2011) {
                    self.core.values[od::STAMP_COUNT] = self.core.boot[od::STAMP_COUNT];
                }
            }
        }
        if let (Request::ProgramControl(v), true) = (req, ok) {
            self.core.set(0x1F51, 1, u32::from(v));
        }
        if let Request::StoreLss { .. } = req {
            out(Frame::new(crate::lss::SLAVE_ID, &lss_glue::store_done(ok)));
            return Ok(());
        }
        let err = (!ok).then_some(SdoAbort::Store);
        if let Some(r) = self.sdo.complete(err) {
            out(Frame::new(0x580 + self.core.node_id as u16, &r));
        }
        Ok(())
    }

    /// Loads the calibration and configuration objects (0x2101..0x2105,
    /// 0x2201..0x2204, 0x2300, 0x2400) from a stored parameter record, as
    /// current and power-on values (normally before the first poll). Every
    /// value is checked against its object's limits first; a node-id in
    /// `p.can` different from the active one becomes active now.
    ///
    /// # Errors
    /// [`Error::Value`] naming the first refused object; the device is
    /// unchanged.
    pub fn load_params(&mut self, p: &Params) -> Result<(), Error> {
        let src = Core {
            defaults: Defaults::from_params(p),
            ..self.core.clone()
        };
        let mut next = self.core.values;
        for (s, index, e) in od::entries() {
            let v = match e.init {
                Init::Calibration(..)
                | Init::Transfer(..)
                | Init::Acquisition(_)
                | Init::ThermalTau
                | Init::BitRate => src.init_value(e, p.can.node_id),
                Init::Node(0) => p.can.node_id as u32,
                _ => continue,
            };
            if !self.core.valid_persisted(index, e.sub, e, v) {
                return Err(Error::Value { index, sub: e.sub });
            }
            next[s] = v;
        }
        tables_ok(&next)?;
        self.core.values = next;
        for (s, _, e) in od::entries() {
            if e.persist && index_is_app(e) {
                self.core.boot[s] = next[s];
            }
        }
        let from = self.core.node_id;
        self.core.apply_node_id(from);
        self.core.config_changed();
        Ok(())
    }

    /// The stored-parameter record the objects describe, on top of `base`
    /// (fields without an object, such as the ADC reference, detector
    /// thresholds, stamp and signal spans of the same kind, are kept).
    /// Beam directions are normalised (a zero direction stays zero, which
    /// `Params::validate` refuses).
    pub fn params(&self, base: &Params) -> Params {
        let mut p = *base;
        for (i, s) in p.head.sensors.iter_mut().enumerate() {
            if let Some(c) = self.calibration(i) {
                *s = c.to_sensor::<f32>().unwrap_or(Sensor {
                    zero: nalgebra::Vector3::from(c.zero),
                    dir: nalgebra::Vector3::from(c.dir),
                    ext: c.extension(),
                });
            }
        }
        for (i, t) in p.transfer.iter_mut().enumerate() {
            if let Some(tf) = self.transfer(i) {
                *t = tf.to_transfer(t);
            }
        }
        p.acq = self.acquisition().to_params(&base.acq);
        p.thermal_tau_s = self.thermal_tau_s();
        let c = self.communication();
        p.can.node_id = c.node_id;
        if let Some(b) = bitrate_of(c.bit_rate_kbps) {
            p.can.bitrate = b;
        }
        p
    }

    /// Writes the persisted values as an image of [`IMAGE_LEN`] bytes:
    /// while a [`Request`] is pending, what storage must hold once it is
    /// carried out (see [`Request`]); otherwise the current values.
    pub fn persistent_image(&self, buf: &mut [u8; IMAGE_LEN]) {
        buf[0..4].copy_from_slice(&layout_signature().to_le_bytes());
        buf[4..8].copy_from_slice(&(PERSISTENT as u32).to_le_bytes());
        let mut p = 8;
        for (s, index, e) in od::entries() {
            if e.persist {
                let v = match self.core.request {
                    Some(req) => self.core.staged(req, s, index, e),
                    None => self.core.values[s],
                };
                buf[p..p + 4].copy_from_slice(&v.to_le_bytes());
                p += 4;
            }
        }
    }

    /// Checks `img` as [`Device::load_image`] does and overlays the
    /// values it holds on `next` (the entries an older layout lacks keep
    /// what `next` holds).
    fn image_values(&self, img: &[u8], next: &mut [u32; ENTRIES]) -> Result<(), Error> {
        let layout = match img.len() {
            IMAGE_LEN => od::LAYOUT,
            IMAGE_LEN_V7 => 7,
            IMAGE_LEN_V6 => 6,
            IMAGE_LEN_V5 => 5,
            IMAGE_LEN_V4 => 4,
            IMAGE_LEN_V3 => 3,
            IMAGE_LEN_V2 => 2,
            IMAGE_LEN_V1 => 1,
            got => {
                return Err(Error::ImageLength {
                    expected: IMAGE_LEN,
                    got,
                })
            }
        };
        let word = |p: usize| u32::from_le_bytes([img[p], img[p + 1], img[p + 2], img[p + 3]]);
        let count = od::persistent_of(layout);
        if word(0) != layout_signature_of(layout) || word(4) != count as u32 {
            return Err(Error::ImageLayout);
        }
        // An entry the image holds (an older layout lacks the newer ones,
        // which keep their current value).
        let held = |e: &od::Entry| e.persist && e.since <= layout;
        // Validate everything first (mappings against the image's own
        // counts).
        let mut p = 8;
        for (_, index, e) in od::entries() {
            if held(e) {
                let v = word(p);
                if !self.core.valid_persisted(index, e.sub, e, v) {
                    return Err(Error::Value { index, sub: e.sub });
                }
                p += 4;
            }
        }
        let mut p = 8;
        for (s, _, e) in od::entries() {
            if held(e) {
                next[s] = word(p);
                p += 4;
            }
        }
        tables_ok(next)?;
        for k in 0..TPDOS {
            let base = od::find(0x1A00 + k as u16, 0).map(|(s, _)| s).unwrap_or(0);
            let n = next[base] as usize;
            let map: [u32; MAX_MAPPED] = core::array::from_fn(|i| next[base + 1 + i]);
            if Core::check_mapping(&map, n).is_err() {
                return Err(Error::Value {
                    index: 0x1A00 + k as u16,
                    sub: 0,
                });
            }
        }
        Ok(())
    }

    /// The calibration and configuration objects as they would be after
    /// [`Device::load_image`] of `img`, held in `buf`; the device is
    /// unchanged. How the board derives the record it stores from the
    /// image it stores without a copy of the device (≈ 4.8 KiB of stack,
    /// issue 50 item 6): `buf` is a quarter of that.
    ///
    /// # Errors
    /// As [`Device::load_image`].
    pub fn staged_objects<'a>(
        &self,
        img: &[u8],
        buf: &'a mut [u32; ENTRIES],
    ) -> Result<Objects<'a>, Error> {
        buf.copy_from_slice(&self.core.values);
        self.image_values(img, buf)?;
        // The node-id `load_image` makes active (`Core::apply_node_id`).
        let configured = slot(0x2400, 1).map_or(0, |s| buf[s]);
        let node_id = if (1..=127).contains(&configured) {
            configured as u8
        } else {
            self.core.node_id
        };
        Ok(Objects {
            values: buf,
            node_id,
        })
    }

    /// Loads a stored image (normally before the first poll): every value
    /// is checked against its object's rules first; on success the values
    /// become both current and power-on values and a node-id stored in
    /// 0x2400 becomes active. An image of layout 1 ([`IMAGE_LEN_V1`]
    /// bytes, written before issue 16) or 2 ([`IMAGE_LEN_V2`], before the
    /// surface model 0x2310) loads too: the entries added since keep their
    /// current values.
    ///
    /// # Errors
    /// [`Error::ImageLength`], [`Error::ImageLayout`], [`Error::Value`];
    /// the device is unchanged.
    #[inline(never)] // its copy of the values stays out of the caller's frame
    pub fn load_image(&mut self, img: &[u8]) -> Result<(), Error> {
        let mut next = self.core.values;
        self.image_values(img, &mut next)?;
        for (s, _, e) in od::entries() {
            if e.persist {
                self.core.values[s] = next[s];
                self.core.boot[s] = next[s];
            }
        }
        let from = self.core.boot_node();
        self.core.apply_node_id(from);
        self.core.hb_restart = true;
        self.core.config_changed();
        Ok(())
    }
}

#[path = "device_lss.rs"]
mod lss_glue;

#[path = "device_sync.rs"]
mod sync;
use sync::{HbMonitor, SyncRt, TPDO_COB, TPDO_MAP, TPDO_TYPE};
pub use sync::{EMCY_HEARTBEAT, EMCY_PDO_LENGTH, EMCY_SYNC_LENGTH};

#[cfg(test)]
#[path = "device_tests.rs"]
mod tests;
