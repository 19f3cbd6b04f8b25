//! The object dictionary: a static table of every object and sub-index the
//! device implements, with data type, access, PDO mappability, write rule,
//! persistence, value limits and default. Values live in the
//! [`crate::Device`] as one `u32` slot per entry (REAL32 as its IEEE-754
//! bits); strings are constants taken from [`crate::Defaults`].
//!
//! The table is the single source of truth: the SDO server, the PDO mapper,
//! the persistence image and the EDS generator all read it.
//!
//! Limits: data types UNSIGNED8/16/32, REAL32, VISIBLE_STRING and one
//! DOMAIN (0x1F50 program data, streamed to the application, never held
//! here); at most 8 bytes of other writable data per entry.

/// CANopen data types used by the dictionary (CiA 301 table 44 codes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DataType {
    /// UNSIGNED8 (0x0005).
    U8,
    /// UNSIGNED16 (0x0006).
    U16,
    /// UNSIGNED32 (0x0007).
    U32,
    /// REAL32 (0x0008), IEEE-754 single precision.
    Real32,
    /// VISIBLE_STRING (0x0009), read-only constants here.
    VisibleString,
    /// DOMAIN (0x000F): write-only stream (0x1F50), see
    /// [`crate::sdo::Dictionary::write_part`].
    Domain,
}

impl DataType {
    /// CiA 301 data type index.
    pub const fn code(self) -> u16 {
        match self {
            DataType::U8 => 0x0005,
            DataType::U16 => 0x0006,
            DataType::U32 => 0x0007,
            DataType::Real32 => 0x0008,
            DataType::VisibleString => 0x0009,
            DataType::Domain => 0x000F,
        }
    }

    /// Size in bytes of a numeric value (0 for strings and domains, whose
    /// size is their length).
    pub const fn size(self) -> usize {
        match self {
            DataType::U8 => 1,
            DataType::U16 => 2,
            DataType::U32 | DataType::Real32 => 4,
            DataType::VisibleString | DataType::Domain => 0,
        }
    }

    /// Size in bits for PDO mapping (0 for strings, which are not mappable).
    pub const fn bits(self) -> u8 {
        (self.size() * 8) as u8
    }
}

/// Access rights (EDS `AccessType`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// Constant, never changes (`const`).
    Const,
    /// Write-only (`wo`): the DOMAIN 0x1F50.
    Wo,
    /// Read-only; may change by the device itself (`ro`).
    Ro,
    /// Read-write (`rw`), subject to the entry's [`Class`] rule.
    Rw,
}

/// Write rule and role of an entry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Class {
    /// Communication object (0x1000..0x1FFF): writable in pre-operational and
    /// operational.
    Comm,
    /// Measurement output of the application (read-only, PDO-mappable).
    Measurement,
    /// Calibration (0x21xx sensor geometry, 0x22xx transfer functions):
    /// writable only in pre-operational **and** after the unlock value was
    /// written to 0x2010 (abort 0x08000022 / 0x08000021 otherwise).
    Calibration,
    /// Configuration (0x2300, 0x2400): writable only in pre-operational.
    Config,
    /// A command object (0x1010, 0x1011, 0x2010): writing triggers an action.
    Command,
}

/// Range a written value must satisfy (beyond its length).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Limits {
    /// Any value of the type.
    Any,
    /// Unsigned integer in `min..=max` (abort 0x06090032 below,
    /// 0x06090031 above).
    Range(u32, u32),
    /// Finite REAL32 in `min..=max` (abort 0x06090030 for NaN/inf,
    /// 0x06090032 below, 0x06090031 above).
    Real(f32, f32),
    /// One of the listed values (abort 0x06090030 otherwise).
    OneOf(&'static [u32]),
    /// A power of two in `min..=max` (abort 0x06090030 otherwise).
    PowerOfTwo(u32, u32),
}

/// Which string constant of [`crate::Defaults`] a VISIBLE_STRING holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Text {
    /// 0x1008.
    DeviceName,
    /// 0x1009.
    HardwareVersion,
    /// 0x100A.
    SoftwareVersion,
}

/// Where an entry's default (power-on / restored) value comes from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Init {
    /// A fixed value.
    Fixed(u32),
    /// `base + node-id` (EDS `$NODEID+base`).
    Node(u32),
    /// [`crate::Defaults::device_type`].
    DeviceType,
    /// [`crate::Defaults::identity`] field 1..=4 (vendor, product, revision,
    /// serial).
    Identity(u8),
    /// [`crate::Defaults::heartbeat_ms`].
    Heartbeat,
    /// Calibration of sensor `.0` (0-based), value `.1` (0-based sub - 1).
    Calibration(u8, u8),
    /// Transfer function of sensor `.0` (0-based), field `.1` (0 kind,
    /// 1 scale, 2 low, 3 high).
    Transfer(u8, u8),
    /// Acquisition field 0..=3 (period, oversampling, method, limit).
    Acquisition(u8),
    /// [`crate::Defaults::thermal_tau_s`] (0x2105).
    ThermalTau,
    /// [`crate::Defaults::bit_rate_kbps`].
    BitRate,
    /// A string constant.
    Text(Text),
}

/// One sub-index of an object.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Entry {
    /// Sub-index.
    pub sub: u8,
    /// Name (ASCII, as in the EDS); "" without the feature `names`.
    pub name: &'static str,
    /// Data type.
    pub ty: DataType,
    /// Access rights.
    pub access: Access,
    /// Write rule / role.
    pub class: Class,
    /// Whether it may be mapped into a TPDO.
    pub pdo: bool,
    /// Whether 0x1010 "save" stores it.
    pub persist: bool,
    /// Image layout that first persisted it: 1, 2 (issue 16), 3 (issue 14,
    /// the surface model 0x2310), 4 (issue 16: heartbeat consumer, SYNC
    /// counter, error behaviour, acquisition trigger, RPDO1, capture), 5
    /// (the linearity tables, 0x2101..0x2104 sub 16..23), 6 (the head's
    /// thermal time constant 0x2105), 7 (the calibration stamp 0x2011) or
    /// 8 (the spot coefficients, 0x2101..0x2104 sub 24..25).
    /// Images of an older layout lack it and still load (the entry keeps
    /// its current value).
    pub since: u8,
    /// Accepted values on write.
    pub limits: Limits,
    /// Default value.
    pub init: Init,
}

/// `name`, or "" in a build without the feature `names` (the firmware:
/// the names serve only the EDS, ≈ 4 KB of flash, issue 50 item 7).
const fn named(name: &'static str) -> &'static str {
    if cfg!(feature = "names") {
        name
    } else {
        ""
    }
}

impl Entry {
    const fn new(sub: u8, name: &'static str, ty: DataType, access: Access, class: Class) -> Self {
        Self {
            sub,
            name: named(name),
            ty,
            access,
            class,
            pdo: false,
            persist: false,
            since: 1,
            limits: Limits::Any,
            init: Init::Fixed(0),
        }
    }
    const fn init(mut self, init: Init) -> Self {
        self.init = init;
        self
    }
    const fn limits(mut self, limits: Limits) -> Self {
        self.limits = limits;
        self
    }
    const fn pdo(mut self) -> Self {
        self.pdo = true;
        self
    }
    const fn persist(mut self) -> Self {
        self.persist = true;
        self
    }
    const fn v2(mut self) -> Self {
        self.since = 2;
        self
    }
    const fn v3(mut self) -> Self {
        self.since = 3;
        self
    }
    const fn v4(mut self) -> Self {
        self.since = 4;
        self
    }
    const fn v5(mut self) -> Self {
        self.since = 5;
        self
    }
    const fn v6(mut self) -> Self {
        self.since = 6;
        self
    }
    const fn v7(mut self) -> Self {
        self.since = 7;
        self
    }
    const fn v8(mut self) -> Self {
        self.since = 8;
        self
    }
}

/// CiA 306 object code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// VAR (7): a single value at sub-index 0.
    Var,
    /// ARRAY (8): sub 0 = count, subs of one type.
    Array,
    /// RECORD (9): sub 0 = highest sub-index, subs of mixed types.
    Record,
}

impl Kind {
    /// CiA 306 `ObjectType` code.
    pub const fn code(self) -> u8 {
        match self {
            Kind::Var => 7,
            Kind::Array => 8,
            Kind::Record => 9,
        }
    }
}

/// One object (index) of the dictionary.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Object {
    /// Index.
    pub index: u16,
    /// Name (ASCII, as in the EDS); "" without the feature `names`.
    pub name: &'static str,
    /// Object code.
    pub kind: Kind,
    /// Its sub-indices in increasing order (for VAR exactly one, sub 0).
    pub subs: &'static [Entry],
}

use Access::{Const, Ro, Rw, Wo};
use DataType::{Domain, Real32, VisibleString, U16, U32, U8};

const fn var(index: u16, name: &'static str, e: &'static [Entry]) -> Object {
    Object {
        index,
        name: named(name),
        kind: Kind::Var,
        subs: e,
    }
}
const fn rec(index: u16, name: &'static str, e: &'static [Entry]) -> Object {
    Object {
        index,
        name: named(name),
        kind: Kind::Record,
        subs: e,
    }
}
const fn arr(index: u16, name: &'static str, e: &'static [Entry]) -> Object {
    Object {
        index,
        name: named(name),
        kind: Kind::Array,
        subs: e,
    }
}
const fn sub0(n: u8) -> Entry {
    Entry::new(0, "Highest sub-index supported", U8, Const, Class::Comm).init(Init::Fixed(n as u32))
}
const fn sub0m(n: u8) -> Entry {
    Entry::new(
        0,
        "Highest sub-index supported",
        U8,
        Const,
        Class::Measurement,
    )
    .init(Init::Fixed(n as u32))
}
const fn meas(sub: u8, name: &'static str) -> Entry {
    Entry::new(sub, name, Real32, Ro, Class::Measurement).pdo()
}
const fn cal(sensor: u8, sub: u8, name: &'static str, lo: f32, hi: f32) -> Entry {
    Entry::new(sub, name, Real32, Rw, Class::Calibration)
        .persist()
        .limits(Limits::Real(lo, hi))
        .init(Init::Calibration(sensor, sub - 1))
}

/// Largest magnitude of a spot coefficient, 0x2101..0x2104 sub 24..25
/// \[mm per unit of tan²γ\] (`perpend_core::params::SPOT_MAX_MM`, the
/// bound of the stored record).
pub const SPOT_MAX_MM: f32 = perpend_core::params::SPOT_MAX_MM;

/// Upper limit of 0x2105, the head's thermal time constant \[s\]
/// (`perpend_core::params::THERMAL_TAU_MAX_S`).
pub const THERMAL_TAU_MAX_S: f32 = perpend_core::params::THERMAL_TAU_MAX_S;

/// Signature written to 0x1010 sub 1 to store parameters: ASCII "save"
/// read as a little-endian UNSIGNED32 (CiA 301 §7.5.2.13).
pub const SAVE_SIGNATURE: u32 = 0x6576_6173;
/// Signature written to 0x1011 sub 1 to restore defaults: ASCII "load".
pub const LOAD_SIGNATURE: u32 = 0x6461_6F6C;
/// Value written to 0x2010 to unlock calibration writes: ASCII "ucal"
/// read as a little-endian UNSIGNED32 (bytes `75 63 61 6C` on the bus).
/// Writing 0 locks again; any other value is refused (0x06090030) and, like
/// every refused write, changes nothing (an unlocked device stays unlocked).
/// The unlock is cleared by every NMT state change and reset.
pub const UNLOCK_SIGNATURE: u32 = 0x6C61_6375;

/// A parameter group of 0x1010 / 0x1011 (CiA 301 §7.5.2.13/14).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Group {
    /// Sub 1: every persisted object.
    All,
    /// Sub 2: communication objects 0x1000..0x1FFF (heartbeat, TPDOs).
    Communication,
    /// Sub 3: application objects 0x2000.. (calibration, transfer
    /// functions, acquisition, 0x2400).
    Application,
}

impl Group {
    /// The group of sub-index `sub` of 0x1010 / 0x1011.
    pub const fn of_sub(sub: u8) -> Option<Self> {
        match sub {
            1 => Some(Group::All),
            2 => Some(Group::Communication),
            3 => Some(Group::Application),
            _ => None,
        }
    }

    /// Whether the persisted object `index` belongs to the group.
    pub const fn contains(self, index: u16) -> bool {
        match self {
            Group::All => true,
            Group::Communication => index < 0x2000,
            Group::Application => index >= 0x2000,
        }
    }
}

/// The node-id and bit rate (0x2400) are layer settings (what CiA 305 LSS
/// would set): 0x1010 sub 1 and 3 store them, no 0x1011 restore touches
/// them, and a written value becomes active at the next NMT reset
/// communication or reset node, saved or not.
pub const fn restorable(index: u16) -> bool {
    index != 0x2400
}

/// Default of 0x2009 sub 1: a TPDO of type 0/254/255 counts a mapped angle
/// (0x2002, 0x2003) as changed when it differs from the value last sent
/// by more than this \[deg\] (over 4σ of the difference of two noisy
/// samples of the virtual board, whose θ noise is ~0.003° 1σ).
pub const DEADBAND_DEG: f32 = 0.02;
/// Default of 0x2009 sub 2: the same for the normal's components (0x2001).
pub const DEADBAND_NORMAL: f32 = 0.0002;
/// Default of 0x2009 sub 3: the same for distances and the residual
/// (0x2004, 0x2006) \[mm\].
pub const DEADBAND_MM: f32 = 0.01;

/// Number of TPDOs.
pub const TPDOS: usize = 4;
/// Value of 0x200A (die temperature) before the first measurement, and
/// on a board without a temperature sensor (the virtual board): absolute
/// zero, -273.15 °C.
pub const DIE_TEMP_UNKNOWN: f32 = -273.15;

/// Number of heartbeats 0x1016 can consume (sub 1..=this).
pub const HB_CONSUMERS: usize = 2;
/// 0x2301 sub 1: one scan per sample period (timer), free-running.
pub const TRIGGER_TIMER: u8 = 0;
/// 0x2301 sub 1: one scan per SYNC; the synchronous TPDOs of that SYNC
/// carry its sample.
pub const TRIGGER_SYNC: u8 = 1;
/// 0x1F51 program control (CiA 302-3): stop the program.
pub const PROGRAM_STOP: u8 = 0;
/// 0x1F51 program control: start the program.
pub const PROGRAM_START: u8 = 1;
/// 0x1F51 program control: reset the program.
pub const PROGRAM_RESET: u8 = 2;
/// 0x1F51 program control: clear the program (erase its area).
pub const PROGRAM_CLEAR: u8 = 3;
/// 0x1F57 flash status (CiA 302-3): bit 0, an operation in progress.
pub const FLASH_BUSY: u32 = 1;
/// 0x1F57 flash status bits 1..7 (value << 1): no error.
pub const FLASH_OK: u32 = 0;
/// 0x1F57 flash status bits 1..7 (value << 1): no valid program.
pub const FLASH_NO_PROGRAM: u32 = 1 << 1;
/// 0x1F57 flash status bits 1..7 (value << 1): data format unknown.
pub const FLASH_FORMAT_UNKNOWN: u32 = 2 << 1;
/// 0x1F57 flash status bits 1..7 (value << 1): data format error or CRC
/// error.
pub const FLASH_FORMAT_ERROR: u32 = 3 << 1;
/// 0x1F57 flash status bits 1..7 (value << 1): flash not cleared before
/// writing.
pub const FLASH_NOT_CLEARED: u32 = 4 << 1;
/// 0x1F57 flash status bits 1..7 (value << 1): flash write error.
pub const FLASH_WRITE_ERROR: u32 = 5 << 1;
/// 0x1F57 flash status bits 1..7 (value << 1): general address error
/// (the program does not fit).
pub const FLASH_ADDRESS_ERROR: u32 = 6 << 1;
/// 0x1F57 flash status bits 1..7 (value << 1): flash secured (writing
/// forbidden now).
pub const FLASH_SECURED: u32 = 7 << 1;
/// 0x1F57 flash status bits 1..7 (value << 1): unspecified error.
pub const FLASH_UNSPECIFIED: u32 = 63 << 1;

/// 0x2500 command: nothing (the value reads back after a command ran).
pub const CMD_NONE: u8 = 0;
/// 0x2500 command: average the next 0x2501 valid samples into 0x2502.
pub const CMD_CAPTURE: u8 = 1;
/// 0x2500 command: enter the MCU's system bootloader (field update,
/// docs/bring-up.md); honoured only in pre-operational (the firmware
/// resets into the ROM bootloader, the virtual board ignores it).
pub const CMD_BOOTLOADER: u8 = 0xB0;
/// Default of 0x2501: samples a capture averages (16 ms at 1 kHz: the
/// angle noise of one sample divided by 4).
pub const CAPTURE_SAMPLES_DEFAULT: u16 = 16;
/// Largest number of objects one TPDO maps.
pub const MAX_MAPPED: usize = 8;

macro_rules! sensor_cal {
    ($s:expr) => {
        &[
            sub0(25),
            cal($s, 1, "Zero point x mm", -1000.0, 1000.0),
            cal($s, 2, "Zero point y mm", -1000.0, 1000.0),
            cal($s, 3, "Zero point z mm", -1000.0, 1000.0),
            cal($s, 4, "Beam direction x", -1.0, 1.0),
            cal($s, 5, "Beam direction y", -1.0, 1.0),
            cal($s, 6, "Beam direction z", -1.0, 1.0),
            cal($s, 7, "Reference distance mm", 0.0, 1000.0),
            cal($s, 8, "Gain error", -0.5, 0.5),
            cal($s, 9, "Quadratic nonlinearity per mm", -1.0, 1.0),
            cal($s, 10, "Cubic nonlinearity per mm2", -1.0, 1.0),
            cal($s, 11, "Incidence bias mm", -10.0, 10.0),
            cal($s, 12, "Crosstalk", -0.5, 0.5),
            cal($s, 13, "Thermal drift mm per degC", -1.0, 1.0),
            cal($s, 14, "Reference temperature degC", -50.0, 150.0),
            cal($s, 15, "Drift mm per s", -1.0, 1.0),
            cal($s, 16, "Linearity table knot 0 mm", -1000.0, 1000.0).v5(),
            cal($s, 17, "Linearity table knot 1 mm", -1000.0, 1000.0).v5(),
            cal($s, 18, "Linearity table knot 2 mm", -1000.0, 1000.0).v5(),
            cal($s, 19, "Linearity table knot 3 mm", -1000.0, 1000.0).v5(),
            cal($s, 20, "Linearity table knot 4 mm", -1000.0, 1000.0).v5(),
            cal($s, 21, "Linearity table value 0 mm", -1.0, 1.0).v5(),
            cal($s, 22, "Linearity table value 1 mm", -1.0, 1.0).v5(),
            cal($s, 23, "Linearity table value 2 mm", -1.0, 1.0).v5(),
            cal($s, 24, "Spot bias cos mm", -SPOT_MAX_MM, SPOT_MAX_MM).v8(),
            cal($s, 25, "Spot bias sin mm", -SPOT_MAX_MM, SPOT_MAX_MM).v8(),
        ]
    };
}

macro_rules! transfer {
    ($s:expr) => {
        &[
            sub0(4),
            Entry::new(1, "Kind", U8, Rw, Class::Calibration)
                .persist()
                .limits(Limits::OneOf(&[0, 1]))
                .init(Init::Transfer($s, 0)),
            Entry::new(
                2,
                "Shunt ohm or divider ratio",
                Real32,
                Rw,
                Class::Calibration,
            )
            .persist()
            .limits(Limits::Real(0.001, 1000.0))
            .init(Init::Transfer($s, 1)),
            Entry::new(
                3,
                "Distance at 4 mA or 0 V mm",
                Real32,
                Rw,
                Class::Calibration,
            )
            .persist()
            .limits(Limits::Real(-1000.0, 1000.0))
            .init(Init::Transfer($s, 2)),
            Entry::new(
                4,
                "Distance at 20 mA or 10 V mm",
                Real32,
                Rw,
                Class::Calibration,
            )
            .persist()
            .limits(Limits::Real(-1000.0, 1000.0))
            .init(Init::Transfer($s, 3)),
        ]
    };
}

macro_rules! tpdo_comm {
    ($k:expr) => {
        &[
            sub0(6),
            Entry::new(1, "COB-ID used by TPDO", U32, Rw, Class::Comm)
                .persist()
                .init(Init::Node(0x4000_0180 + 0x100 * $k)),
            Entry::new(2, "Transmission type", U8, Rw, Class::Comm)
                .persist()
                .init(Init::Fixed(1)),
            Entry::new(3, "Inhibit time", U16, Rw, Class::Comm).persist(),
            Entry::new(5, "Event timer", U16, Rw, Class::Comm).persist(),
            Entry::new(6, "SYNC start value", U8, Rw, Class::Comm)
                .persist()
                .v4()
                .limits(Limits::Range(0, 240)),
        ]
    };
}

const fn map_entry(sub: u8, v: u32) -> Entry {
    Entry::new(sub, "Application object", U32, Rw, Class::Comm)
        .persist()
        .init(Init::Fixed(v))
}

macro_rules! tpdo_map {
    ($n:expr, [$a:expr, $b:expr, $c:expr, $d:expr]) => {
        &[
            Entry::new(0, "Number of mapped objects", U8, Rw, Class::Comm)
                .persist()
                .limits(Limits::Range(0, MAX_MAPPED as u32))
                .init(Init::Fixed($n)),
            map_entry(1, $a),
            map_entry(2, $b),
            map_entry(3, $c),
            map_entry(4, $d),
            map_entry(5, 0),
            map_entry(6, 0),
            map_entry(7, 0),
            map_entry(8, 0),
        ]
    };
}

/// A PDO mapping entry value: `index << 16 | sub << 8 | bits`.
pub const fn mapping(index: u16, sub: u8, bits: u8) -> u32 {
    ((index as u32) << 16) | ((sub as u32) << 8) | bits as u32
}

/// The whole dictionary, sorted by index.
pub const OBJECTS: &[Object] = &[
    var(
        0x1000,
        "Device type",
        &[Entry::new(0, "Device type", U32, Const, Class::Comm).init(Init::DeviceType)],
    ),
    var(
        0x1001,
        "Error register",
        &[Entry::new(0, "Error register", U8, Ro, Class::Comm).pdo()],
    ),
    arr(
        0x1003,
        "Pre-defined error field",
        &[
            Entry::new(0, "Number of errors", U8, Rw, Class::Comm).limits(Limits::OneOf(&[0])),
            Entry::new(1, "Standard error field", U32, Ro, Class::Comm),
            Entry::new(2, "Standard error field", U32, Ro, Class::Comm),
            Entry::new(3, "Standard error field", U32, Ro, Class::Comm),
            Entry::new(4, "Standard error field", U32, Ro, Class::Comm),
            Entry::new(5, "Standard error field", U32, Ro, Class::Comm),
            Entry::new(6, "Standard error field", U32, Ro, Class::Comm),
            Entry::new(7, "Standard error field", U32, Ro, Class::Comm),
            Entry::new(8, "Standard error field", U32, Ro, Class::Comm),
        ],
    ),
    var(
        0x1005,
        "COB-ID SYNC",
        &[Entry::new(0, "COB-ID SYNC", U32, Const, Class::Comm).init(Init::Fixed(0x80))],
    ),
    var(
        0x1008,
        "Manufacturer device name",
        &[Entry::new(
            0,
            "Manufacturer device name",
            VisibleString,
            Const,
            Class::Comm,
        )
        .init(Init::Text(Text::DeviceName))],
    ),
    var(
        0x1009,
        "Manufacturer hardware version",
        &[Entry::new(
            0,
            "Manufacturer hardware version",
            VisibleString,
            Const,
            Class::Comm,
        )
        .init(Init::Text(Text::HardwareVersion))],
    ),
    var(
        0x100A,
        "Manufacturer software version",
        &[Entry::new(
            0,
            "Manufacturer software version",
            VisibleString,
            Const,
            Class::Comm,
        )
        .init(Init::Text(Text::SoftwareVersion))],
    ),
    arr(
        0x1010,
        "Store parameters",
        &[
            sub0(3),
            Entry::new(1, "Save all parameters", U32, Rw, Class::Command).init(Init::Fixed(1)),
            Entry::new(2, "Save communication parameters", U32, Rw, Class::Command)
                .init(Init::Fixed(1)),
            Entry::new(3, "Save application parameters", U32, Rw, Class::Command)
                .init(Init::Fixed(1)),
        ],
    ),
    arr(
        0x1011,
        "Restore default parameters",
        &[
            sub0(3),
            Entry::new(1, "Restore all default parameters", U32, Rw, Class::Command)
                .init(Init::Fixed(1)),
            Entry::new(
                2,
                "Restore communication default parameters",
                U32,
                Rw,
                Class::Command,
            )
            .init(Init::Fixed(1)),
            Entry::new(
                3,
                "Restore application default parameters",
                U32,
                Rw,
                Class::Command,
            )
            .init(Init::Fixed(1)),
        ],
    ),
    var(
        0x1014,
        "COB-ID EMCY",
        &[Entry::new(0, "COB-ID EMCY", U32, Ro, Class::Comm).init(Init::Node(0x80))],
    ),
    var(
        0x1015,
        "Inhibit time EMCY",
        &[Entry::new(0, "Inhibit time EMCY", U16, Rw, Class::Comm)
            .persist()
            .v2()],
    ),
    arr(
        0x1016,
        "Consumer heartbeat time",
        &[
            sub0(HB_CONSUMERS as u8),
            Entry::new(1, "Consumer heartbeat time", U32, Rw, Class::Comm)
                .persist()
                .v4()
                .limits(Limits::Range(0, 0x007F_FFFF)),
            Entry::new(2, "Consumer heartbeat time", U32, Rw, Class::Comm)
                .persist()
                .v4()
                .limits(Limits::Range(0, 0x007F_FFFF)),
        ],
    ),
    var(
        0x1017,
        "Producer heartbeat time",
        &[
            Entry::new(0, "Producer heartbeat time", U16, Rw, Class::Comm)
                .persist()
                .init(Init::Heartbeat),
        ],
    ),
    rec(
        0x1018,
        "Identity object",
        &[
            sub0(4),
            Entry::new(1, "Vendor-ID", U32, Const, Class::Comm).init(Init::Identity(1)),
            Entry::new(2, "Product code", U32, Const, Class::Comm).init(Init::Identity(2)),
            Entry::new(3, "Revision number", U32, Const, Class::Comm).init(Init::Identity(3)),
            Entry::new(4, "Serial number", U32, Const, Class::Comm).init(Init::Identity(4)),
        ],
    ),
    var(
        0x1019,
        "Synchronous counter overflow value",
        &[
            Entry::new(0, "Synchronous counter overflow value", U8, Rw, Class::Comm)
                .persist()
                .v4()
                .limits(Limits::Range(0, 240)),
        ],
    ),
    arr(
        0x1029,
        "Error behavior",
        &[
            sub0(1),
            Entry::new(1, "Communication error", U8, Rw, Class::Comm)
                .persist()
                .v4()
                .limits(Limits::OneOf(&[0, 1, 2])),
        ],
    ),
    rec(
        0x1200,
        "SDO server parameter",
        &[
            sub0(2),
            Entry::new(1, "COB-ID client to server", U32, Ro, Class::Comm).init(Init::Node(0x600)),
            Entry::new(2, "COB-ID server to client", U32, Ro, Class::Comm).init(Init::Node(0x580)),
        ],
    ),
    rec(
        0x1400,
        "RPDO1 communication parameter",
        &[
            sub0(2),
            Entry::new(1, "COB-ID used by RPDO", U32, Rw, Class::Comm)
                .persist()
                .v4()
                .init(Init::Node(0x200)),
            Entry::new(2, "Transmission type", U8, Rw, Class::Comm)
                .persist()
                .v4()
                .limits(Limits::OneOf(&[254, 255]))
                .init(Init::Fixed(255)),
        ],
    ),
    rec(
        0x1600,
        "RPDO1 mapping parameter",
        &[
            Entry::new(0, "Number of mapped objects", U8, Const, Class::Comm).init(Init::Fixed(1)),
            Entry::new(1, "Application object", U32, Const, Class::Comm)
                .init(Init::Fixed(mapping(0x2500, 0, 8))),
        ],
    ),
    rec(0x1800, "TPDO1 communication parameter", tpdo_comm!(0)),
    rec(0x1801, "TPDO2 communication parameter", tpdo_comm!(1)),
    rec(0x1802, "TPDO3 communication parameter", tpdo_comm!(2)),
    rec(0x1803, "TPDO4 communication parameter", tpdo_comm!(3)),
    rec(
        0x1A00,
        "TPDO1 mapping parameter",
        tpdo_map!(2, [mapping(0x2002, 1, 32), mapping(0x2002, 2, 32), 0, 0]),
    ),
    rec(
        0x1A01,
        "TPDO2 mapping parameter",
        tpdo_map!(2, [mapping(0x2005, 0, 32), mapping(0x2007, 0, 32), 0, 0]),
    ),
    rec(
        0x1A02,
        "TPDO3 mapping parameter",
        tpdo_map!(2, [mapping(0x2001, 1, 32), mapping(0x2001, 2, 32), 0, 0]),
    ),
    rec(
        0x1A03,
        "TPDO4 mapping parameter",
        tpdo_map!(2, [mapping(0x2001, 3, 32), mapping(0x2006, 0, 32), 0, 0]),
    ),
    arr(
        0x1F50,
        "Program data",
        &[
            sub0(1),
            Entry::new(1, "Program number 1", Domain, Wo, Class::Command),
        ],
    ),
    arr(
        0x1F51,
        "Program control",
        &[
            sub0(1),
            Entry::new(1, "Program number 1", U8, Rw, Class::Command)
                .limits(Limits::Range(PROGRAM_STOP as u32, PROGRAM_CLEAR as u32)),
        ],
    ),
    arr(
        0x1F56,
        "Program software identification",
        &[
            sub0(1),
            Entry::new(1, "Program number 1", U32, Ro, Class::Measurement),
        ],
    ),
    arr(
        0x1F57,
        "Flash status identification",
        &[
            sub0(1),
            Entry::new(1, "Program number 1", U32, Ro, Class::Measurement),
        ],
    ),
    arr(
        0x2001,
        "Surface normal",
        &[
            sub0m(3),
            meas(1, "Normal x"),
            meas(2, "Normal y"),
            meas(3, "Normal z"),
        ],
    ),
    rec(
        0x2002,
        "Deviation",
        &[
            sub0m(3),
            meas(1, "Theta1 deg"),
            meas(2, "Theta2 deg"),
            meas(3, "Theta deg"),
        ],
    ),
    rec(
        0x2003,
        "Attitude correction",
        &[sub0m(2), meas(1, "Pitch deg"), meas(2, "Yaw deg")],
    ),
    arr(
        0x2004,
        "Distances",
        &[
            sub0m(4),
            meas(1, "Distance sensor 1 mm"),
            meas(2, "Distance sensor 2 mm"),
            meas(3, "Distance sensor 3 mm"),
            meas(4, "Distance sensor 4 mm"),
        ],
    ),
    var(
        0x2005,
        "Measurement status",
        &[
            Entry::new(0, "Measurement status", U32, Ro, Class::Measurement)
                .pdo()
                .init(Init::Fixed(crate::status::NO_PLANE)),
        ],
    ),
    var(
        0x2006,
        "Plane RMS residual mm",
        &[meas(0, "Plane RMS residual mm")],
    ),
    var(
        0x2007,
        "Sample counter",
        &[Entry::new(0, "Sample counter", U32, Ro, Class::Measurement).pdo()],
    ),
    rec(
        0x2008,
        "CAN transmit queue",
        &[
            sub0m(2),
            Entry::new(1, "Frames dropped", U32, Ro, Class::Measurement).pdo(),
            Entry::new(2, "Peak fill", U32, Ro, Class::Measurement).pdo(),
        ],
    ),
    rec(
        0x2009,
        "TPDO change deadband",
        &[
            sub0(3),
            Entry::new(1, "Angle deadband deg", Real32, Rw, Class::Comm)
                .persist()
                .v2()
                .limits(Limits::Real(0.0, 90.0))
                .init(Init::Fixed(DEADBAND_DEG.to_bits())),
            Entry::new(2, "Normal deadband", Real32, Rw, Class::Comm)
                .persist()
                .v2()
                .limits(Limits::Real(0.0, 2.0))
                .init(Init::Fixed(DEADBAND_NORMAL.to_bits())),
            Entry::new(3, "Length deadband mm", Real32, Rw, Class::Comm)
                .persist()
                .v2()
                .limits(Limits::Real(0.0, 1000.0))
                .init(Init::Fixed(DEADBAND_MM.to_bits())),
        ],
    ),
    var(
        0x200A,
        "Die temperature degC",
        &[meas(0, "Die temperature degC").init(Init::Fixed(DIE_TEMP_UNKNOWN.to_bits()))],
    ),
    rec(
        0x200B,
        "Board health",
        &[
            sub0m(4),
            Entry::new(1, "Reset flags", U32, Ro, Class::Measurement).pdo(),
            Entry::new(2, "Worst loop cycles", U32, Ro, Class::Measurement).pdo(),
            Entry::new(3, "Stack used bytes", U32, Ro, Class::Measurement).pdo(),
            Entry::new(4, "VREF+ mV", U32, Ro, Class::Measurement).pdo(),
        ],
    ),
    var(
        0x200C,
        "Uptime s",
        &[Entry::new(0, "Uptime s", U32, Ro, Class::Measurement).pdo()],
    ),
    var(
        0x2010,
        "Calibration unlock",
        &[Entry::new(0, "Calibration unlock", U32, Rw, Class::Command)],
    ),
    // What calibration the board carries (issue 30): sub 1/2 written by the
    // host with the calibration (pre-op + unlock), stored and restored with
    // the application group; the device counts the stores itself (sub 3:
    // read-only, a value the device produces, hence `Measurement`, see
    // `STAMP_COUNT`).
    rec(
        0x2011,
        "Calibration stamp",
        &[
            sub0(3),
            Entry::new(1, "Record hash", U32, Rw, Class::Calibration)
                .persist()
                .v7(),
            Entry::new(2, "Stored UTC s", U32, Rw, Class::Calibration)
                .persist()
                .v7(),
            Entry::new(3, "Store count", U32, Ro, Class::Measurement)
                .persist()
                .v7(),
        ],
    ),
    arr(
        0x2012,
        "Error history time s",
        &[
            sub0m(8),
            Entry::new(1, "Error time s", U32, Ro, Class::Measurement),
            Entry::new(2, "Error time s", U32, Ro, Class::Measurement),
            Entry::new(3, "Error time s", U32, Ro, Class::Measurement),
            Entry::new(4, "Error time s", U32, Ro, Class::Measurement),
            Entry::new(5, "Error time s", U32, Ro, Class::Measurement),
            Entry::new(6, "Error time s", U32, Ro, Class::Measurement),
            Entry::new(7, "Error time s", U32, Ro, Class::Measurement),
            Entry::new(8, "Error time s", U32, Ro, Class::Measurement),
        ],
    ),
    var(
        0x2020,
        "Sample time us",
        &[Entry::new(0, "Sample time us", U32, Ro, Class::Measurement).pdo()],
    ),
    rec(0x2101, "Sensor 1 calibration", sensor_cal!(0)),
    rec(0x2102, "Sensor 2 calibration", sensor_cal!(1)),
    rec(0x2103, "Sensor 3 calibration", sensor_cal!(2)),
    rec(0x2104, "Sensor 4 calibration", sensor_cal!(3)),
    // One value for the head, next to the four sensors' calibrations: the
    // sensors sit in one body, so one lag (a 24th sub-index in each of
    // 0x2101..0x2104 would be four copies that could disagree).
    var(
        0x2105,
        "Thermal time constant s",
        &[
            Entry::new(0, "Thermal time constant s", Real32, Rw, Class::Calibration)
                .persist()
                .v6()
                .limits(Limits::Real(0.0, THERMAL_TAU_MAX_S))
                .init(Init::ThermalTau),
        ],
    ),
    rec(0x2201, "Sensor 1 transfer function", transfer!(0)),
    rec(0x2202, "Sensor 2 transfer function", transfer!(1)),
    rec(0x2203, "Sensor 3 transfer function", transfer!(2)),
    rec(0x2204, "Sensor 4 transfer function", transfer!(3)),
    rec(
        0x2300,
        "Acquisition",
        &[
            sub0(4),
            Entry::new(1, "Sample period us", U32, Rw, Class::Config)
                .persist()
                .limits(Limits::Range(100, 100_000))
                .init(Init::Acquisition(0)),
            Entry::new(2, "Oversampling ratio", U16, Rw, Class::Config)
                .persist()
                .limits(Limits::PowerOfTwo(1, 256))
                .init(Init::Acquisition(1)),
            Entry::new(3, "Plane method", U8, Rw, Class::Config)
                .persist()
                .limits(Limits::OneOf(&[0, 1]))
                .init(Init::Acquisition(2)),
            Entry::new(4, "Residual limit mm", Real32, Rw, Class::Config)
                .persist()
                .limits(Limits::Real(0.0001, 100.0))
                .init(Init::Acquisition(3)),
        ],
    ),
    rec(
        0x2301,
        "Acquisition trigger",
        &[
            sub0(2),
            Entry::new(1, "Trigger", U8, Rw, Class::Config)
                .persist()
                .v4()
                .limits(Limits::OneOf(&[TRIGGER_TIMER as u32, TRIGGER_SYNC as u32])),
            Entry::new(2, "SYNC samples missed", U32, Ro, Class::Measurement).pdo(),
        ],
    ),
    rec(
        0x2310,
        "Surface model",
        &[
            sub0(5),
            Entry::new(1, "Model", U8, Rw, Class::Config)
                .persist()
                .v3()
                .limits(Limits::OneOf(&[
                    crate::config::SURFACE_PLANE as u32,
                    crate::config::SURFACE_SPHERE as u32,
                    crate::config::SURFACE_CYLINDER as u32,
                ]))
                .init(Init::Fixed(crate::config::SURFACE_PLANE as u32)),
            Entry::new(2, "Radius mm", Real32, Rw, Class::Config)
                .persist()
                .v3()
                .limits(Limits::Real(
                    -crate::config::SURFACE_RADIUS_MAX_MM,
                    crate::config::SURFACE_RADIUS_MAX_MM,
                ))
                .init(Init::Fixed(
                    crate::config::SURFACE_RADIUS_DEFAULT_MM.to_bits(),
                )),
            Entry::new(3, "Cylinder axis x", Real32, Rw, Class::Config)
                .persist()
                .v3()
                .limits(Limits::Real(-1.0, 1.0))
                .init(Init::Fixed(1.0f32.to_bits())),
            Entry::new(4, "Cylinder axis y", Real32, Rw, Class::Config)
                .persist()
                .v3()
                .limits(Limits::Real(-1.0, 1.0))
                .init(Init::Fixed(0)),
            Entry::new(5, "Cylinder axis z", Real32, Rw, Class::Config)
                .persist()
                .v3()
                .limits(Limits::Real(-1.0, 1.0))
                .init(Init::Fixed(0)),
        ],
    ),
    rec(
        0x2400,
        "Communication",
        &[
            sub0(2),
            Entry::new(1, "Node-ID", U8, Rw, Class::Config)
                .persist()
                .limits(Limits::Range(1, 127))
                .init(Init::Node(0)),
            Entry::new(2, "Bit rate kbps", U16, Rw, Class::Config)
                .persist()
                .limits(Limits::OneOf(&[125, 250, 500, 1000]))
                .init(Init::BitRate),
        ],
    ),
    var(
        0x2500,
        "Command",
        &[
            Entry::new(0, "Command", U8, Rw, Class::Command).limits(Limits::OneOf(&[
                CMD_NONE as u32,
                CMD_CAPTURE as u32,
                CMD_BOOTLOADER as u32,
            ])),
        ],
    ),
    var(
        0x2501,
        "Capture samples",
        &[Entry::new(0, "Capture samples", U16, Rw, Class::Comm)
            .persist()
            .v4()
            .limits(Limits::Range(1, 1000))
            .init(Init::Fixed(CAPTURE_SAMPLES_DEFAULT as u32))],
    ),
    rec(
        0x2502,
        "Captured measurement",
        &[
            sub0m(7),
            meas(1, "Theta1 deg"),
            meas(2, "Theta2 deg"),
            meas(3, "Theta deg"),
            meas(4, "Pitch deg"),
            meas(5, "Yaw deg"),
            Entry::new(6, "Samples used", U16, Ro, Class::Measurement).pdo(),
            Entry::new(7, "Capture counter", U16, Ro, Class::Measurement).pdo(),
        ],
    ),
];

const fn count_entries() -> usize {
    let mut n = 0;
    let mut i = 0;
    while i < OBJECTS.len() {
        n += OBJECTS[i].subs.len();
        i += 1;
    }
    n
}

const fn count_persist(layout: u8) -> usize {
    let mut n = 0;
    let mut i = 0;
    while i < OBJECTS.len() {
        let mut j = 0;
        while j < OBJECTS[i].subs.len() {
            let e = &OBJECTS[i].subs[j];
            if e.persist && e.since <= layout {
                n += 1;
            }
            j += 1;
        }
        i += 1;
    }
    n
}

/// Number of entries (sub-indices) in the dictionary: the number of value
/// slots of a [`crate::Device`].
pub const ENTRIES: usize = count_entries();
/// The current image layout (see [`Entry::since`]).
pub const LAYOUT: u8 = 8;
/// Number of entries stored by 0x1010.
pub const PERSISTENT: usize = count_persist(LAYOUT);
/// Number of entries an image of layout 1 (before issue 16) holds.
pub const PERSISTENT_V1: usize = count_persist(1);
/// Number of entries an image of layout 2 (before the surface model 0x2310)
/// holds.
pub const PERSISTENT_V2: usize = count_persist(2);
/// Number of entries an image of layout 3 (before the objects of layout 4)
/// holds.
pub const PERSISTENT_V3: usize = count_persist(3);
/// Number of entries an image of layout 4 (before the linearity tables of
/// layout 5) holds.
pub const PERSISTENT_V4: usize = count_persist(4);
/// Number of entries an image of layout 5 (before the thermal time
/// constant 0x2105 of layout 6) holds.
pub const PERSISTENT_V5: usize = count_persist(5);
/// Number of entries an image of layout 6 (before the calibration stamp
/// 0x2011 of layout 7) holds.
pub const PERSISTENT_V6: usize = count_persist(6);
/// Number of entries an image of layout 7 (before the spot coefficients,
/// 0x2101..0x2104 sub 24..25, of layout 8) holds.
pub const PERSISTENT_V7: usize = count_persist(7);

/// The slot of 0x2011 sub 3, the store count of the calibration stamp:
/// read-only, persisted, one more in the image of every 0x1010 store of the
/// application group (sub 1 or 3), 0 after a 0x1011 restore of it.
pub const STAMP_COUNT: usize = slot_of(0x2011, 3);

/// Number of persisted entries of image layout `layout` (1..=[`LAYOUT`]).
pub const fn persistent_of(layout: u8) -> usize {
    count_persist(layout)
}

/// Slot of the first entry of each object (prefix sums of the sub counts).
const OFFSETS: [usize; OBJECTS.len()] = {
    let mut o = [0usize; OBJECTS.len()];
    let mut i = 1;
    while i < OBJECTS.len() {
        o[i] = o[i - 1] + OBJECTS[i - 1].subs.len();
        i += 1;
    }
    o
};

/// `(index << 8) | sub` of every entry in slot order (sorted, as the table
/// is): the flat key array [`find`] searches (the hot path of every value
/// access, SYNC and sample).
const KEYS: [u32; ENTRIES] = {
    let mut k = [0u32; ENTRIES];
    let (mut i, mut n) = (0, 0);
    while i < OBJECTS.len() {
        let mut j = 0;
        while j < OBJECTS[i].subs.len() {
            k[n] = ((OBJECTS[i].index as u32) << 8) | OBJECTS[i].subs[j].sub as u32;
            n += 1;
            j += 1;
        }
        i += 1;
    }
    k
};

/// Object (position in the table) of every slot.
const OBJECT_OF: [u8; ENTRIES] = {
    let mut o = [0u8; ENTRIES];
    let (mut i, mut n) = (0, 0);
    while i < OBJECTS.len() {
        let mut j = 0;
        while j < OBJECTS[i].subs.len() {
            o[n] = i as u8;
            n += 1;
            j += 1;
        }
        i += 1;
    }
    o
};

const _: () = assert!(OBJECTS.len() <= 256, "OBJECT_OF holds u8");

/// Row of the hot table [`HOT`]: the objects every SYNC and sample reads
/// or writes (TPDO communication and mapping, measurement, deadbands).
const fn hot_row(index: u16) -> Option<usize> {
    match index {
        0x1800..=0x1803 => Some((index - 0x1800) as usize),
        0x1A00..=0x1A03 => Some(4 + (index - 0x1A00) as usize),
        0x2001..=0x2009 => Some(8 + (index - 0x2001) as usize),
        _ => None,
    }
}

/// Rows of [`HOT`].
const HOT_ROWS: usize = 17;

/// Sub-indices per row of [`HOT`] (0..=8: a TPDO mapping's).
const HOT_SUBS: usize = 1 + MAX_MAPPED;
/// "No such entry" in [`HOT`].
const NO_SLOT: u16 = u16::MAX;

/// The slot of `(index, sub)` for the [`hot_row`] objects, by direct
/// lookup ([`NO_SLOT`]: no such entry).
const HOT: [[u16; HOT_SUBS]; HOT_ROWS] = {
    let mut t = [[NO_SLOT; HOT_SUBS]; HOT_ROWS];
    let mut n = 0;
    while n < ENTRIES {
        let index = (KEYS[n] >> 8) as u16;
        let sub = (KEYS[n] & 0xFF) as usize;
        if let Some(r) = hot_row(index) {
            assert!(sub < HOT_SUBS, "hot object with a sub-index above 8");
            t[r][sub] = n as u16;
        }
        n += 1;
    }
    t
};

const _: () = assert!(ENTRIES < NO_SLOT as usize, "slots fit u16");

/// The value slot of `(index, sub)`, found at compile time (a constant
/// for the hot paths: no lookup at run time). Fails to compile when the
/// entry does not exist.
#[allow(clippy::panic)] // used in constants: a missing entry fails the build
pub const fn slot_of(index: u16, sub: u8) -> usize {
    let key = ((index as u32) << 8) | sub as u32;
    let mut n = 0;
    while n < ENTRIES {
        if KEYS[n] == key {
            return n;
        }
        n += 1;
    }
    panic!("no such object dictionary entry")
}

/// The value slot of `(index, sub)` (`None`: no such entry): a direct
/// lookup for the objects of every SYNC and sample, else a binary search.
pub fn slot(index: u16, sub: u8) -> Option<usize> {
    if let Some(r) = hot_row(index) {
        let s = *HOT.get(r)?.get(sub as usize)?;
        return (s != NO_SLOT).then_some(s as usize);
    }
    KEYS.binary_search(&(((index as u32) << 8) | sub as u32))
        .ok()
}

/// Failure of a dictionary lookup.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Lookup {
    /// No object with this index (SDO abort 0x06020000).
    NoObject,
    /// The object exists but not this sub-index (SDO abort 0x06090011).
    NoSub,
}

/// The object with this index.
pub fn object(index: u16) -> Option<(usize, &'static Object)> {
    OBJECTS
        .binary_search_by_key(&index, |o| o.index)
        .ok()
        .and_then(|i| OBJECTS.get(i).map(|o| (i, o)))
}

/// The value slot and descriptor of `(index, sub)`.
///
/// # Errors
/// [`Lookup::NoObject`] / [`Lookup::NoSub`].
pub fn find(index: u16, sub: u8) -> Result<(usize, &'static Entry), Lookup> {
    if let Some(s) = slot(index, sub) {
        let oi = OBJECT_OF[s] as usize;
        if let Some(e) = OBJECTS.get(oi).and_then(|o| o.subs.get(s - OFFSETS[oi])) {
            return Ok((s, e));
        }
    }
    let (oi, obj) = object(index).ok_or(Lookup::NoObject)?;
    let si = obj
        .subs
        .binary_search_by_key(&sub, |e| e.sub)
        .map_err(|_| Lookup::NoSub)?;
    let e = obj.subs.get(si).ok_or(Lookup::NoSub)?;
    Ok((OFFSETS[oi] + si, e))
}

/// Iterates over every entry as `(slot, index, entry)` in dictionary order.
pub fn entries() -> impl Iterator<Item = (usize, u16, &'static Entry)> {
    OBJECTS.iter().enumerate().flat_map(|(oi, o)| {
        o.subs
            .iter()
            .enumerate()
            .map(move |(si, e)| (OFFSETS[oi] + si, o.index, e))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_is_sorted_and_consistent() {
        for w in OBJECTS.windows(2) {
            assert!(w[0].index < w[1].index, "{:#06x}", w[1].index);
        }
        for o in OBJECTS {
            for w in o.subs.windows(2) {
                assert!(w[0].sub < w[1].sub, "{:#06x}", o.index);
            }
            match o.kind {
                Kind::Var => assert_eq!(o.subs.len(), 1),
                _ => {
                    // sub 0 is the highest sub-index, an U8
                    assert_eq!(o.subs[0].sub, 0);
                    assert_eq!(o.subs[0].ty, DataType::U8);
                    let last = o.subs[o.subs.len() - 1].sub as u32;
                    if let Init::Fixed(n) = o.subs[0].init {
                        if o.subs[0].access == Access::Const {
                            assert_eq!(n, last, "{:#06x}", o.index);
                        }
                    }
                }
            }
            for e in o.subs {
                if e.pdo {
                    assert!(e.ty.bits() > 0);
                }
                if e.ty == DataType::VisibleString {
                    assert_eq!(e.access, Access::Const);
                }
            }
        }
        let mut n = 0;
        for (slot, index, e) in entries() {
            assert_eq!(slot, n);
            assert_eq!(find(index, e.sub), Ok((slot, e)));
            n += 1;
        }
        assert_eq!(n, ENTRIES);
    }

    #[test]
    fn slot_lookup_agrees_with_the_table() {
        for (n, index, e) in entries() {
            assert_eq!(slot(index, e.sub), Some(n), "{index:#06x} sub {}", e.sub);
        }
        // absent subs of the direct-table objects, and around them
        assert_eq!(slot(0x1800, 4), None);
        assert_eq!(slot(0x1A00, 9), None);
        assert_eq!(slot(0x2001, 200), None);
        assert_eq!(slot(0x1804, 0), None);
        assert_eq!(slot(0x200D, 0), None);
        assert_eq!(find(0x1800, 4), Err(Lookup::NoSub));
        assert_eq!(persistent_of(LAYOUT), PERSISTENT);
        const {
            assert!(
                PERSISTENT_V1 < PERSISTENT_V2
                    && PERSISTENT_V2 < PERSISTENT_V3
                    && PERSISTENT_V3 < PERSISTENT_V4
                    && PERSISTENT_V4 < PERSISTENT_V5
                    && PERSISTENT_V5 + 1 == PERSISTENT_V6
                    && PERSISTENT_V6 + 3 == PERSISTENT_V7
                    && PERSISTENT_V7 + 4 * 2 == PERSISTENT
            )
        };
    }

    #[test]
    fn lookups_distinguish_object_and_sub() {
        assert_eq!(find(0x1234, 0), Err(Lookup::NoObject));
        assert_eq!(find(0x1018, 5), Err(Lookup::NoSub));
        assert_eq!(find(0x1800, 4), Err(Lookup::NoSub));
        assert!(find(0x2104, 25).is_ok());
        assert_eq!(find(0x2104, 26), Err(Lookup::NoSub));
        assert!(find(0x2105, 0).is_ok());
        assert_eq!(find(0x2105, 1), Err(Lookup::NoSub));
        assert_eq!(find(0x2106, 0), Err(Lookup::NoObject));
        assert!(find(0x2011, 3).is_ok());
        assert_eq!(find(0x2011, 4), Err(Lookup::NoSub));
    }

    #[test]
    fn signatures_are_ascii() {
        assert_eq!(&SAVE_SIGNATURE.to_le_bytes(), b"save");
        assert_eq!(&LOAD_SIGNATURE.to_le_bytes(), b"load");
        assert_eq!(&UNLOCK_SIGNATURE.to_le_bytes(), b"ucal");
    }
}
