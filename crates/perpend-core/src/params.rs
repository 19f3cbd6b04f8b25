//! Stored-parameter format of the sensor head's calibration and configuration.
//!
//! [`Params`] is everything the board keeps across power cycles: the
//! calibrated sensor head (zero points, beam directions and the
//! [`crate::ext::Extension`] coefficients of each sensor), the analog
//! transfer function of each channel, the acquisition settings and the CAN
//! settings. It is stored in `f32` (the board computes in `f32`; the host
//! casts its `f64` calibration with [`crate::head::Head::cast`]).
//!
//! ## Record layout (version 4, little endian)
//!
//! ```text
//! offset  size  field
//!      0     4  magic "PPND"
//!      4     2  version (u16) = 4
//!      6     2  payload length (u16) = PAYLOAD_LEN = 517
//!      8   517  payload: stamp u32; 4 × sensor (zero xyz, dir xyz, the nine
//!               scalar extension coefficients d_ref, gain, nonlinearity[0..2],
//!               incidence, crosstalk, thermal, temp_ref, drift, then the
//!               linearity table's knots[0..5] and coeffs[0..3]: 23 × f32);
//!               4 × transfer (front end u8 0 = shunt / 1 = divider, its
//!               f32, sig_lo, sig_hi, mm_lo, mm_hi: f32); acquisition
//!               (period_us u32, os_log2 u8, os_shift u8, vref_mv u16,
//!               method u8 0 = least squares / 1 = Chen, stuck_samples u16,
//!               stuck_counts u16, jump_mm f32, jump_hold u16,
//!               max_rms_mm f32); CAN (node_id u8, bit-rate code u8);
//!               thermal_tau_s f32 (payload offset 481, record offset 489);
//!               4 × spot[0..2] f32 (payload offset 485, record offset 493)
//!    525     4  CRC-32 (IEEE 802.3, reflected, as zlib) of bytes 0..525
//! ```
//!
//! The spot coefficients of the incidence correction (the azimuthal
//! terms `spot·[tan²γ·cos φ, tan²γ·sin φ]`, [`crate::ext`], "Incidence")
//! are appended after `thermal_tau_s`, sensor by sensor, so every offset
//! of version 3 is unchanged in version 4.
//!
//! The head-level thermal time constant `thermal_tau_s` (the sensor bodies
//! follow the head thermometer through a first-order lag,
//! [`crate::lag`]) is appended at the end of the payload, so every offset
//! of version 2 is unchanged in version 3.
//!
//! ## Versions 3, 2 and 1 (read only: migration)
//!
//! Version 3 is version 4 without the spot coefficients: payload length
//! [`V3_PAYLOAD_LEN`] = 485, record length [`V3_RECORD_LEN`] = 497, CRC
//! over bytes 0..493. It decodes with `spot = [0, 0]` for each sensor (the
//! symmetric incidence term only: the behaviour of the firmware that
//! wrote it).
//!
//! Version 2 is version 3 without `thermal_tau_s`: payload length
//! [`V2_PAYLOAD_LEN`] = 481, record length [`V2_RECORD_LEN`] = 493, CRC
//! over bytes 0..489. It decodes with `thermal_tau_s = 0` (no lag: the
//! behaviour of the firmware that wrote it).
//!
//! Version 1 is version 2 without the linearity table: 15 × f32 per
//! sensor (ending with `drift`), payload length [`V1_PAYLOAD_LEN`] = 353,
//! record length [`V1_RECORD_LEN`] = 365, CRC over bytes 0..361. It
//! decodes with [`LinTable::none`] for each sensor and `thermal_tau_s = 0`.
//! Versions 2 and 1 decode with zero spot coefficients too.
//!
//! A board whose flash holds an older record (older firmware) boots from
//! it: [`Params::decode`] reads it with every structural check of its own
//! length (magic, payload length, CRC); the next store writes version 4.
//! [`Params::encode`] writes version 4 only.
//!
//! [`Params::decode`] rejects, in this order: a short buffer, a wrong magic,
//! an unknown version, a wrong payload length (for that version), a
//! checksum mismatch, an unknown enum code, and then any value that
//! [`Params::validate`] refuses (for the table: an active table whose
//! knots are not strictly ascending within ±1000 mm or whose coefficients
//! exceed 1 mm; for the time constant: not finite, or outside
//! 0..=[`THERMAL_TAU_MAX_S`]; for a spot coefficient: not finite, or
//! above [`SPOT_MAX_MM`]). A decoded record is therefore always usable
//! as it is; the board falls back to [`Params::factory`] on any error.
//! [`Params::encode`] validates first, so an invalid record is never
//! written.
//!
//! Versioning: a later layout gets a new version number; the decoder keeps
//! reading every older version it knows (1, 2, 3 and 4) and the board writes
//! the newest layout on the next store (0x1010).
//!
//! Limits: exactly four sensors (the product's head); the CRC detects every
//! error burst up to 32 bits and any odd number of bit errors; it is not a
//! MAC.

use nalgebra::Vector3;

use crate::ext::{Extension, LinTable, TABLE_COEFFS, TABLE_KNOTS};
use crate::head::{Head4, Sensor};
use crate::normal::Method;
use crate::{Error, Result};

/// Magic bytes at the start of a record.
pub const MAGIC: [u8; 4] = *b"PPND";
/// The layout version this code writes.
pub const VERSION: u16 = 4;
/// The layout version before the spot coefficients, still decoded.
pub const VERSION_3: u16 = 3;
/// The layout version before the thermal time constant, still decoded.
pub const VERSION_2: u16 = 2;
/// The layout version before the linearity table, still decoded.
pub const VERSION_1: u16 = 1;
/// Number of sensors in a record.
pub const SENSORS: usize = 4;
/// Header length: magic, version, payload length.
pub const HEADER_LEN: usize = 8;
/// Payload length of the current version ([`VERSION`]).
pub const PAYLOAD_LEN: usize = V3_PAYLOAD_LEN + SPOT_LEN;
/// Total length of an encoded record of the current version.
pub const RECORD_LEN: usize = HEADER_LEN + PAYLOAD_LEN + 4;
/// Payload length of a version-3 record (no spot coefficients).
pub const V3_PAYLOAD_LEN: usize = V2_PAYLOAD_LEN + TAU_LEN;
/// Total length of a version-3 record.
pub const V3_RECORD_LEN: usize = HEADER_LEN + V3_PAYLOAD_LEN + 4;
/// Payload length of a version-2 record (no thermal time constant).
pub const V2_PAYLOAD_LEN: usize = 4 + SENSORS * SENSOR_LEN + SENSORS * TRANSFER_LEN + ACQ_LEN + 2;
/// Total length of a version-2 record.
pub const V2_RECORD_LEN: usize = HEADER_LEN + V2_PAYLOAD_LEN + 4;
/// Payload length of a version-1 record (no linearity table).
pub const V1_PAYLOAD_LEN: usize = V2_PAYLOAD_LEN - SENSORS * TABLE_LEN;
/// Total length of a version-1 record.
pub const V1_RECORD_LEN: usize = HEADER_LEN + V1_PAYLOAD_LEN + 4;

/// Per sensor: zero, dir, nine scalar coefficients (as version 1), table.
const SENSOR_LEN: usize = 15 * 4 + TABLE_LEN;
/// The linearity table: knots then coefficients, f32 each.
const TABLE_LEN: usize = (TABLE_KNOTS + TABLE_COEFFS) * 4;
const TRANSFER_LEN: usize = 1 + 5 * 4;
const ACQ_LEN: usize = 4 + 1 + 1 + 2 + 1 + 2 + 2 + 4 + 2 + 4;
/// The thermal time constant: one f32.
const TAU_LEN: usize = 4;
/// The spot coefficients: two f32 per sensor.
const SPOT_LEN: usize = SENSORS * 2 * 4;
/// Largest spot coefficient magnitude [mm per unit of tan²γ] (as the
/// incidence coefficient's bound of the CAN object).
pub const SPOT_MAX_MM: f32 = 10.0;
/// Largest thermal time constant \[s\] (one day): a head that needs more
/// never reaches thermal equilibrium within a shift.
pub const THERMAL_TAU_MAX_S: f32 = 86_400.0;
/// Largest table knot magnitude [mm] (about `d_ref`).
pub const TABLE_KNOT_MAX_MM: f32 = 1000.0;
/// Largest table value (`LinTable::coeffs`) magnitude \[mm\].
pub const TABLE_COEFF_MAX: f32 = 1.0;

/// The analog front end between a sensor's output and the ADC pin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Frontend {
    /// Current output into a shunt resistor of `ohm` Ω to ground: the pin
    /// sees `V = I·R`.
    Shunt {
        /// Shunt resistance [Ω], 10..=1000.
        ohm: f32,
    },
    /// Voltage output through a resistive divider: the pin sees
    /// `V = ratio · V_out`.
    Divider {
        /// Divider ratio `R_low / (R_high + R_low)`, in (0, 1].
        ratio: f32,
    },
}

/// Per-channel transfer function: ADC pin voltage → sensor signal (mA or V)
/// → distance [mm].
///
/// The sensor maps its measuring range `[mm_lo, mm_hi]` linearly onto the
/// signal span `[sig_lo, sig_hi]` (mA for [`Frontend::Shunt`], V for
/// [`Frontend::Divider`]); `mm_hi < mm_lo` describes a sensor whose signal
/// falls with distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Transfer {
    /// Front end.
    pub frontend: Frontend,
    /// Signal at the start of the measuring range (4 mA, or 0 V).
    pub sig_lo: f32,
    /// Signal at the end of the measuring range (20 mA, or 10 V).
    pub sig_hi: f32,
    /// Distance at `sig_lo` [mm].
    pub mm_lo: f32,
    /// Distance at `sig_hi` [mm].
    pub mm_hi: f32,
}

impl Transfer {
    /// The NAMUR 4-20 mA transfer over a shunt of `ohm` Ω for a measuring
    /// range `mm_lo..mm_hi`.
    pub const fn current(ohm: f32, mm_lo: f32, mm_hi: f32) -> Self {
        Self {
            frontend: Frontend::Shunt { ohm },
            sig_lo: 4.0,
            sig_hi: 20.0,
            mm_lo,
            mm_hi,
        }
    }

    /// The 0-10 V transfer through a divider of `ratio` for a measuring range
    /// `mm_lo..mm_hi`.
    pub const fn voltage(ratio: f32, mm_lo: f32, mm_hi: f32) -> Self {
        Self {
            frontend: Frontend::Divider { ratio },
            sig_lo: 0.0,
            sig_hi: 10.0,
            mm_lo,
            mm_hi,
        }
    }

    /// Checks the ranges: shunt 10..=1000 Ω, divider ratio in (0, 1],
    /// signal span at least 1 (mA or V) within 0..=25 mA or 0..=12 V,
    /// measuring range ends within 0..=10 000 mm and at least 0.01 mm
    /// apart.
    ///
    /// # Errors
    /// [`Error::NonFinite`] / [`Error::OutOfRange`] naming the field.
    pub fn validate(&self) -> Result<()> {
        let hi_max = match self.frontend {
            Frontend::Shunt { ohm } => {
                fin(ohm, "shunt")?;
                if !(10.0..=1000.0).contains(&ohm) {
                    return Err(Error::OutOfRange("shunt"));
                }
                25.0
            }
            Frontend::Divider { ratio } => {
                fin(ratio, "divider ratio")?;
                if !(ratio > 0.0 && ratio <= 1.0) {
                    return Err(Error::OutOfRange("divider ratio"));
                }
                12.0
            }
        };
        fin(self.sig_lo, "signal low")?;
        fin(self.sig_hi, "signal high")?;
        fin(self.mm_lo, "range low")?;
        fin(self.mm_hi, "range high")?;
        if !(self.sig_lo >= 0.0 && self.sig_hi <= hi_max && self.sig_hi - self.sig_lo >= 1.0) {
            return Err(Error::OutOfRange("signal span"));
        }
        let in_range = |x: f32| (0.0..=10_000.0).contains(&x);
        let span_ok = (self.mm_hi - self.mm_lo).abs() >= 0.01;
        if !(in_range(self.mm_lo) && in_range(self.mm_hi) && span_ok) {
            return Err(Error::OutOfRange("measuring range"));
        }
        Ok(())
    }
}

/// CAN bit rate (classic CAN).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bitrate {
    /// 125 kbit/s.
    K125,
    /// 250 kbit/s.
    K250,
    /// 500 kbit/s.
    K500,
    /// 1 Mbit/s (default).
    M1,
}

impl Bitrate {
    /// Bit rate in bit/s.
    pub const fn bps(self) -> u32 {
        match self {
            Bitrate::K125 => 125_000,
            Bitrate::K250 => 250_000,
            Bitrate::K500 => 500_000,
            Bitrate::M1 => 1_000_000,
        }
    }

    /// Stored code: 0 = 1 M, 1 = 500 k, 2 = 250 k, 3 = 125 k (also the
    /// value of the bit-rate object).
    pub const fn code(self) -> u8 {
        match self {
            Bitrate::M1 => 0,
            Bitrate::K500 => 1,
            Bitrate::K250 => 2,
            Bitrate::K125 => 3,
        }
    }

    /// Inverse of [`Bitrate::code`].
    ///
    /// # Errors
    /// [`Error::OutOfRange`] for an unknown code.
    pub const fn from_code(c: u8) -> Result<Self> {
        match c {
            0 => Ok(Bitrate::M1),
            1 => Ok(Bitrate::K500),
            2 => Ok(Bitrate::K250),
            3 => Ok(Bitrate::K125),
            _ => Err(Error::OutOfRange("bit rate")),
        }
    }
}

/// CAN settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CanConfig {
    /// CANopen node id, 1..=127.
    pub node_id: u8,
    /// Bit rate.
    pub bitrate: Bitrate,
}

/// Acquisition and plausibility settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Acquisition {
    /// Scan period [µs], 100..=100_000 (1000 = 1 kHz).
    pub period_us: u32,
    /// Hardware oversampling: log2 of the ratio, 0..=8 (0 = off, 4 = 16×).
    pub os_log2: u8,
    /// Oversampling right shift, 0..=8, with `os_log2 − os_shift ≤ 4` so the
    /// result fits 16 bits.
    pub os_shift: u8,
    /// ADC reference voltage [mV], 1800..=3600.
    pub vref_mv: u16,
    /// Plane method.
    pub method: Method,
    /// Stuck detection: samples without change before a channel is declared
    /// stuck (0 = off), ≤ 60000.
    pub stuck_samples: u16,
    /// Stuck detection: largest change [ADC counts of the oversampled
    /// result] still counted as "no change".
    pub stuck_counts: u16,
    /// Jump detection: largest plausible change of a reading between two
    /// samples beyond the common change of the others [mm] (0 = off),
    /// ≤ 1000.
    pub jump_mm: f32,
    /// Samples a channel stays out after a jump, ≤ 60000.
    pub jump_hold: u16,
    /// Largest plane RMS residual [mm] for a valid four-sensor normal,
    /// in (0, 100].
    pub max_rms_mm: f32,
}

/// The complete stored parameter set.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Params {
    /// Record stamp: the board increments it on every store (0 = never
    /// stored); a host tool that writes a record may put e.g. the Unix time
    /// of the calibration here.
    pub stamp: u32,
    /// The calibrated head (sensor `i` = ADC channel `i`).
    pub head: Head4<f32>,
    /// Transfer function of each channel.
    pub transfer: [Transfer; SENSORS],
    /// Acquisition settings.
    pub acq: Acquisition,
    /// CAN settings.
    pub can: CanConfig,
    /// Thermal time constant of the head \[s\], 0..=[`THERMAL_TAU_MAX_S`]:
    /// the sensor bodies' temperature follows the head thermometer through
    /// a first-order lag of this time constant ([`crate::lag`]), and the
    /// thermal extension `thermal·(T − T_ref)` of every sensor is applied
    /// to the lagged temperature. One value for the head (the sensors sit
    /// in one body); 0 = no lag, the thermometer's reading is used as it is
    /// (the behaviour before record version 3).
    pub thermal_tau_s: f32,
}

#[inline(never)]
fn fin(x: f32, what: &'static str) -> Result<f32> {
    if x.is_finite() {
        Ok(x)
    } else {
        Err(Error::NonFinite(what))
    }
}

impl Acquisition {
    /// Factory acquisition settings: 1 kHz, 16× oversampling without shift
    /// (16-bit result, full scale 65520), 3.3 V reference, least squares, stuck after
    /// 2000 unchanged samples (2 s), jump 0.5 mm held 20 samples, RMS limit
    /// 0.05 mm.
    pub const fn factory() -> Self {
        Self {
            period_us: 1000,
            os_log2: 4,
            os_shift: 0,
            vref_mv: 3300,
            method: Method::LeastSquares,
            stuck_samples: 2000,
            stuck_counts: 0,
            jump_mm: 0.5,
            jump_hold: 20,
            max_rms_mm: 0.05,
        }
    }

    /// Checks every field (see the field docs for ranges).
    ///
    /// # Errors
    /// [`Error::OutOfRange`] / [`Error::NonFinite`] naming the field.
    pub fn validate(&self) -> Result<()> {
        if !(100..=100_000).contains(&self.period_us) {
            return Err(Error::OutOfRange("period"));
        }
        if self.os_log2 > 8 {
            return Err(Error::OutOfRange("oversampling ratio"));
        }
        if self.os_shift > 8 || self.os_log2 > self.os_shift + 4 {
            return Err(Error::OutOfRange("oversampling shift"));
        }
        if !(1800..=3600).contains(&self.vref_mv) {
            return Err(Error::OutOfRange("vref"));
        }
        if self.stuck_samples > 60_000 {
            return Err(Error::OutOfRange("stuck samples"));
        }
        if self.jump_hold > 60_000 {
            return Err(Error::OutOfRange("jump hold"));
        }
        fin(self.jump_mm, "jump threshold")?;
        if !(0.0..=1000.0).contains(&self.jump_mm) {
            return Err(Error::OutOfRange("jump threshold"));
        }
        fin(self.max_rms_mm, "residual limit")?;
        if !(self.max_rms_mm > 0.0 && self.max_rms_mm <= 100.0) {
            return Err(Error::OutOfRange("residual limit"));
        }
        Ok(())
    }
}

impl CanConfig {
    /// Factory CAN settings: node 0x20, 1 Mbit/s.
    pub const fn factory() -> Self {
        Self {
            node_id: 0x20,
            bitrate: Bitrate::M1,
        }
    }

    /// Checks the node id.
    ///
    /// # Errors
    /// [`Error::OutOfRange`] for a node id outside 1..=127.
    pub fn validate(&self) -> Result<()> {
        if !(1..=127).contains(&self.node_id) {
            return Err(Error::OutOfRange("node id"));
        }
        Ok(())
    }
}

/// Checks one sensor's calibration: finite, zero point within ±10 m, unit
/// beam direction (±1e-3), finite extension, spot coefficients within
/// ±[`SPOT_MAX_MM`], and [`validate_table`].
///
/// # Errors
/// [`Error::NonFinite`] / [`Error::OutOfRange`] naming the field.
pub fn validate_sensor(s: &Sensor<f32>) -> Result<()> {
    for c in s.zero.iter() {
        fin(*c, "zero point")?;
        if !(c.abs() <= 10_000.0) {
            return Err(Error::OutOfRange("zero point"));
        }
    }
    for c in s.dir.iter() {
        fin(*c, "beam direction")?;
    }
    if !((s.dir.norm() - 1.0).abs() <= 1e-3) {
        return Err(Error::OutOfRange("beam direction"));
    }
    if !s.ext.is_finite() {
        return Err(Error::NonFinite("extension"));
    }
    if !s.ext.spot.iter().all(|c| c.abs() <= SPOT_MAX_MM) {
        return Err(Error::OutOfRange("spot bias"));
    }
    validate_table(&s.ext.table)
}

/// Checks a linearity table: every value finite; when it is active
/// ([`LinTable::is_active`]) its knots strictly ascending within
/// ±[`TABLE_KNOT_MAX_MM`] and its coefficients within
/// ±[`TABLE_COEFF_MAX`]. The knots of an inactive table are not used and
/// not checked beyond finiteness.
///
/// # Errors
/// [`Error::NonFinite`]`("linearity table")`, [`Error::OutOfRange`]
/// `("linearity table knots")` / `("linearity table values")`.
pub fn validate_table(t: &LinTable<f32>) -> Result<()> {
    if !t.knots.iter().chain(t.coeffs.iter()).all(|x| x.is_finite()) {
        return Err(Error::NonFinite("linearity table"));
    }
    if !t.is_active() {
        return Ok(());
    }
    let in_range = t.knots.iter().all(|k| k.abs() <= TABLE_KNOT_MAX_MM);
    if !(in_range && t.knots_valid()) {
        return Err(Error::OutOfRange("linearity table knots"));
    }
    if !t.coeffs.iter().all(|c| c.abs() <= TABLE_COEFF_MAX) {
        return Err(Error::OutOfRange("linearity table values"));
    }
    Ok(())
}

impl Params {
    /// Factory defaults, used when no valid record is stored: the design
    /// head (four sensors on a 50 mm circle at z = 0, beams tilted 30°
    /// towards the axis, sensor 1 on +x, numbered counter-clockwise, as
    /// `perpend demo`), no extension corrections (reference distance 50 mm,
    /// mid-range), 4-20 mA sensors over
    /// 150 Ω shunts with a 20..80 mm measuring range,
    /// [`Acquisition::factory`] and [`CanConfig::factory`]. The board flags
    /// them "uncalibrated".
    pub fn factory() -> Self {
        let fallback = Sensor {
            zero: Vector3::zeros(),
            dir: Vector3::z(),
            ext: Extension::identity(),
        };
        // cone() fails only on non-finite arguments; these are literals.
        let mut head = Head4::<f32>::cone(50.0, core::f32::consts::FRAC_PI_6, 0.0, 0.0)
            .unwrap_or(Head4::new([fallback; SENSORS]));
        for s in head.sensors.iter_mut() {
            s.ext.d_ref = 50.0;
        }
        Self {
            stamp: 0,
            head,
            transfer: [Transfer::current(150.0, 20.0, 80.0); SENSORS],
            acq: Acquisition::factory(),
            can: CanConfig::factory(),
            thermal_tau_s: 0.0,
        }
    }

    /// Checks every value: [`validate_sensor`] for each sensor,
    /// [`Transfer::validate`] for each channel, [`Acquisition::validate`],
    /// [`CanConfig::validate`], and the thermal time constant (finite,
    /// 0..=[`THERMAL_TAU_MAX_S`]).
    ///
    /// # Errors
    /// The first [`Error::NonFinite`] / [`Error::OutOfRange`] found.
    pub fn validate(&self) -> Result<()> {
        for s in &self.head.sensors {
            validate_sensor(s)?;
        }
        for t in &self.transfer {
            t.validate()?;
        }
        self.acq.validate()?;
        self.can.validate()?;
        fin(self.thermal_tau_s, "thermal time constant")?;
        if !(0.0..=THERMAL_TAU_MAX_S).contains(&self.thermal_tau_s) {
            return Err(Error::OutOfRange("thermal time constant"));
        }
        Ok(())
    }

    /// Encodes into `out` (at least [`RECORD_LEN`] bytes); returns the number
    /// of bytes written.
    ///
    /// # Errors
    /// [`Error::BufferTooSmall`], or the error of [`Params::validate`].
    pub fn encode(&self, out: &mut [u8]) -> Result<usize> {
        self.validate()?;
        let out = out.get_mut(..RECORD_LEN).ok_or(Error::BufferTooSmall)?;
        let mut w = Writer { buf: out, pos: 0 };
        w.bytes(&MAGIC);
        w.u16(VERSION);
        w.u16(PAYLOAD_LEN as u16);
        w.u32(self.stamp);
        for s in &self.head.sensors {
            for v in [s.zero.x, s.zero.y, s.zero.z, s.dir.x, s.dir.y, s.dir.z] {
                w.f32(v);
            }
            let e = &s.ext;
            for v in [
                e.d_ref,
                e.gain,
                e.nonlinearity[0],
                e.nonlinearity[1],
                e.incidence,
                e.crosstalk,
                e.thermal,
                e.temp_ref,
                e.drift,
            ] {
                w.f32(v);
            }
            for v in e.table.knots.iter().chain(e.table.coeffs.iter()) {
                w.f32(*v);
            }
        }
        for t in &self.transfer {
            match t.frontend {
                Frontend::Shunt { ohm } => {
                    w.u8(0);
                    w.f32(ohm);
                }
                Frontend::Divider { ratio } => {
                    w.u8(1);
                    w.f32(ratio);
                }
            }
            for v in [t.sig_lo, t.sig_hi, t.mm_lo, t.mm_hi] {
                w.f32(v);
            }
        }
        let a = &self.acq;
        w.u32(a.period_us);
        w.u8(a.os_log2);
        w.u8(a.os_shift);
        w.u16(a.vref_mv);
        w.u8(match a.method {
            Method::LeastSquares => 0,
            Method::Chen => 1,
        });
        w.u16(a.stuck_samples);
        w.u16(a.stuck_counts);
        w.f32(a.jump_mm);
        w.u16(a.jump_hold);
        w.f32(a.max_rms_mm);
        w.u8(self.can.node_id);
        w.u8(self.can.bitrate.code());
        w.f32(self.thermal_tau_s);
        for s in &self.head.sensors {
            w.f32(s.ext.spot[0]);
            w.f32(s.ext.spot[1]);
        }
        let crc = crc32(w.buf.get(..RECORD_LEN - 4).unwrap_or(&[]));
        w.u32(crc);
        Ok(w.pos)
    }

    /// Decodes and validates a record of version 4, 3, 2 or 1 (the layouts
    /// in the module docs; a version-3, -2 or -1 record gets zero spot
    /// coefficients, a version-2 or -1 record `thermal_tau_s = 0`, a
    /// version-1 record inactive linearity tables).
    /// Trailing bytes after the record are ignored (flash items are padded).
    ///
    /// # Errors
    /// [`Error::Decode`] naming the reason (`"short record"`, `"bad magic"`,
    /// `"unsupported version"`, `"bad length"`, `"checksum mismatch"`,
    /// `"unknown front end"`, `"unknown method"`), [`Error::OutOfRange`] for
    /// an unknown bit-rate code, or the error of [`Params::validate`] for a
    /// well-formed record with bad values.
    pub fn decode(buf: &[u8]) -> Result<Self> {
        Self::decode_with_len(buf).map(|(p, _)| p)
    }

    /// As [`Params::decode`], and returns the length of the record in `buf`
    /// ([`RECORD_LEN`], [`V3_RECORD_LEN`], [`V2_RECORD_LEN`] or
    /// [`V1_RECORD_LEN`] for a version-4, -3, -2 or -1 record): where
    /// the bytes stored after it start.
    ///
    /// # Errors
    /// As [`Params::decode`].
    pub fn decode_with_len(buf: &[u8]) -> Result<(Self, usize)> {
        if buf.len() < HEADER_LEN {
            return Err(Error::Decode("short record"));
        }
        let mut r = Reader { buf, pos: 0 };
        if r.take::<4>()? != MAGIC {
            return Err(Error::Decode("bad magic"));
        }
        let version = r.u16()?;
        let (payload_len, has_table) = match version {
            VERSION => (PAYLOAD_LEN, true),
            VERSION_3 => (V3_PAYLOAD_LEN, true),
            VERSION_2 => (V2_PAYLOAD_LEN, true),
            VERSION_1 => (V1_PAYLOAD_LEN, false),
            _ => return Err(Error::Decode("unsupported version")),
        };
        if r.u16()? as usize != payload_len {
            return Err(Error::Decode("bad length"));
        }
        let record_len = HEADER_LEN + payload_len + 4;
        let body = buf
            .get(..record_len - 4)
            .ok_or(Error::Decode("short record"))?;
        let stored = buf
            .get(record_len - 4..record_len)
            .ok_or(Error::Decode("short record"))?;
        if crc32(body).to_le_bytes() != stored {
            return Err(Error::Decode("checksum mismatch"));
        }
        let stamp = r.u32()?;
        let mut sensors = [Sensor {
            zero: Vector3::zeros(),
            dir: Vector3::z(),
            ext: Extension::identity(),
        }; SENSORS];
        for s in sensors.iter_mut() {
            *s = r.sensor(has_table)?;
        }
        let mut transfer = [Transfer::current(150.0, 0.0, 1.0); SENSORS];
        for t in transfer.iter_mut() {
            *t = r.transfer()?;
        }
        let acq = r.acquisition()?;
        let node_id = r.u8()?;
        let bitrate = Bitrate::from_code(r.u8()?)?;
        let thermal_tau_s = if version >= VERSION_3 { r.f32()? } else { 0.0 };
        if version >= VERSION {
            for s in sensors.iter_mut() {
                s.ext.spot = r.f32s::<2>()?;
            }
        }
        let p = Params {
            stamp,
            head: Head4::new(sensors),
            transfer,
            acq,
            can: CanConfig { node_id, bitrate },
            thermal_tau_s,
        };
        p.validate()?;
        Ok((p, record_len))
    }
}

/// Converts a current (version-4) record into the version-3 record of the
/// same values, as the firmware before the spot coefficients wrote it:
/// the trailing spot coefficients left out, header and CRC rewritten. For
/// compatibility tests and fuzz seeds (the board never writes version 3).
/// The input is not checked.
pub fn record_as_v3(v4: &[u8; RECORD_LEN]) -> [u8; V3_RECORD_LEN] {
    let mut v3 = [0u8; V3_RECORD_LEN];
    let mut w = Writer {
        buf: &mut v3,
        pos: 0,
    };
    w.bytes(&MAGIC);
    w.u16(VERSION_3);
    w.u16(V3_PAYLOAD_LEN as u16);
    w.bytes(&v4[HEADER_LEN..HEADER_LEN + V3_PAYLOAD_LEN]);
    let crc = crc32(&w.buf[..V3_RECORD_LEN - 4]);
    w.u32(crc);
    v3
}

/// Converts a current (version-4) record into the version-2 record of the
/// same values, as the firmware before the thermal time constant wrote
/// it: the trailing `thermal_tau_s` and spot coefficients left out,
/// header and CRC rewritten.
/// For compatibility tests and fuzz seeds (the board never writes
/// version 2). The input is not checked.
pub fn record_as_v2(v3: &[u8; RECORD_LEN]) -> [u8; V2_RECORD_LEN] {
    let mut v2 = [0u8; V2_RECORD_LEN];
    let mut w = Writer {
        buf: &mut v2,
        pos: 0,
    };
    w.bytes(&MAGIC);
    w.u16(VERSION_2);
    w.u16(V2_PAYLOAD_LEN as u16);
    w.bytes(&v3[HEADER_LEN..HEADER_LEN + V2_PAYLOAD_LEN]);
    let crc = crc32(&w.buf[..V2_RECORD_LEN - 4]);
    w.u32(crc);
    v2
}

/// Converts a current (version-4) record into the version-1 record of the
/// same values, as the firmware before the linearity table wrote it: each
/// sensor's table bytes, the thermal time constant and the spot
/// coefficients left out, header
/// and CRC rewritten. For compatibility tests and fuzz seeds (the board
/// never writes version 1). The input is not checked: a record that fails
/// to decode converts into one that fails too, unless only its tables or
/// its time constant were bad.
pub fn record_as_v1(v3: &[u8; RECORD_LEN]) -> [u8; V1_RECORD_LEN] {
    const V1_SENSOR_LEN: usize = SENSOR_LEN - TABLE_LEN;
    let mut v1 = [0u8; V1_RECORD_LEN];
    let mut w = Writer {
        buf: &mut v1,
        pos: 0,
    };
    w.bytes(&MAGIC);
    w.u16(VERSION_1);
    w.u16(V1_PAYLOAD_LEN as u16);
    let sensors = HEADER_LEN + 4;
    w.bytes(&v3[HEADER_LEN..sensors]);
    for s in v3[sensors..sensors + SENSORS * SENSOR_LEN].chunks_exact(SENSOR_LEN) {
        w.bytes(&s[..V1_SENSOR_LEN]);
    }
    w.bytes(&v3[sensors + SENSORS * SENSOR_LEN..HEADER_LEN + V2_PAYLOAD_LEN]);
    let crc = crc32(&w.buf[..V1_RECORD_LEN - 4]);
    w.u32(crc);
    v1
}

/// CRC-32 (IEEE 802.3 polynomial 0x04C11DB7, reflected, init and final XOR
/// 0xFFFFFFFF: the zlib/PNG CRC). Bitwise, no table: the record is read
/// once at boot and written on a store.
pub fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in data {
        crc ^= b as u32;
        for _ in 0..8 {
            let mask = (crc & 1).wrapping_neg();
            crc = (crc >> 1) ^ (0xEDB8_8320 & mask);
        }
    }
    !crc
}

struct Writer<'a> {
    buf: &'a mut [u8],
    pos: usize,
}

impl Writer<'_> {
    // The buffer is exactly RECORD_LEN (or V2_/V1_RECORD_LEN) long and the
    // layout constants add up to it (checked by the tests), so `get_mut`
    // never fails; it is used instead of indexing to keep the encoder
    // panic-free.
    fn bytes(&mut self, b: &[u8]) {
        if let Some(dst) = self.buf.get_mut(self.pos..self.pos + b.len()) {
            dst.copy_from_slice(b);
        }
        self.pos += b.len();
    }
    fn u8(&mut self, v: u8) {
        self.bytes(&[v]);
    }
    fn u16(&mut self, v: u16) {
        self.bytes(&v.to_le_bytes());
    }
    // Not inlined (nor `Reader::u32`, nor `fin`): one call per field
    // instead of the copy at each of the ~80 fields (−1,064 B of flash on the
    // board; records are written and read only when parameters change
    // or at boot).
    #[inline(never)]
    fn u32(&mut self, v: u32) {
        self.bytes(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.u32(v.to_bits());
    }
}

struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl Reader<'_> {
    fn take<const K: usize>(&mut self) -> Result<[u8; K]> {
        let s = self
            .buf
            .get(self.pos..self.pos + K)
            .ok_or(Error::Decode("short record"))?;
        let mut a = [0u8; K];
        a.copy_from_slice(s);
        self.pos += K;
        Ok(a)
    }
    fn u8(&mut self) -> Result<u8> {
        let [b] = self.take::<1>()?;
        Ok(b)
    }
    fn u16(&mut self) -> Result<u16> {
        Ok(u16::from_le_bytes(self.take()?))
    }
    #[inline(never)]
    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take()?))
    }
    fn f32(&mut self) -> Result<f32> {
        Ok(f32::from_bits(self.u32()?))
    }
    fn f32s<const K: usize>(&mut self) -> Result<[f32; K]> {
        let mut a = [0.0; K];
        for v in a.iter_mut() {
            *v = self.f32()?;
        }
        Ok(a)
    }

    /// One sensor; `has_table`: version 2 or 3 (else the table is
    /// inactive).
    fn sensor(&mut self, has_table: bool) -> Result<Sensor<f32>> {
        let zero = Vector3::from(self.f32s::<3>()?);
        let dir = Vector3::from(self.f32s::<3>()?);
        let [d_ref, gain, nl0, nl1, incidence, crosstalk, thermal, temp_ref, drift] =
            self.f32s::<9>()?;
        let table = if has_table {
            LinTable {
                knots: self.f32s::<TABLE_KNOTS>()?,
                coeffs: self.f32s::<TABLE_COEFFS>()?,
            }
        } else {
            LinTable::none()
        };
        let ext = Extension {
            d_ref,
            gain,
            nonlinearity: [nl0, nl1],
            table,
            incidence,
            spot: [0.0; 2],
            crosstalk,
            thermal,
            temp_ref,
            drift,
        };
        Ok(Sensor { zero, dir, ext })
    }

    fn transfer(&mut self) -> Result<Transfer> {
        let kind = self.u8()?;
        let v = self.f32()?;
        let frontend = match kind {
            0 => Frontend::Shunt { ohm: v },
            1 => Frontend::Divider { ratio: v },
            _ => return Err(Error::Decode("unknown front end")),
        };
        let [sig_lo, sig_hi, mm_lo, mm_hi] = self.f32s::<4>()?;
        Ok(Transfer {
            frontend,
            sig_lo,
            sig_hi,
            mm_lo,
            mm_hi,
        })
    }

    fn acquisition(&mut self) -> Result<Acquisition> {
        let period_us = self.u32()?;
        let os_log2 = self.u8()?;
        let os_shift = self.u8()?;
        let vref_mv = self.u16()?;
        let method = match self.u8()? {
            0 => Method::LeastSquares,
            1 => Method::Chen,
            _ => return Err(Error::Decode("unknown method")),
        };
        Ok(Acquisition {
            period_us,
            os_log2,
            os_shift,
            vref_mv,
            method,
            stuck_samples: self.u16()?,
            stuck_counts: self.u16()?,
            jump_mm: self.f32()?,
            jump_hold: self.u16()?,
            max_rms_mm: self.f32()?,
        })
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn crc32_check_value() {
        // The standard check value of CRC-32/ISO-HDLC.
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    #[test]
    fn layout_constants_add_up() {
        assert_eq!(PAYLOAD_LEN, 517);
        assert_eq!(RECORD_LEN, 529);
        assert_eq!(V3_PAYLOAD_LEN, 485);
        assert_eq!(V3_RECORD_LEN, 497);
        assert_eq!(V2_PAYLOAD_LEN, 481);
        assert_eq!(V2_RECORD_LEN, 493);
        assert_eq!(SENSOR_LEN, 23 * 4);
        assert_eq!(V1_PAYLOAD_LEN, 353);
        assert_eq!(V1_RECORD_LEN, 365);
        let mut buf = [0u8; RECORD_LEN + 3];
        assert_eq!(Params::factory().encode(&mut buf).unwrap(), RECORD_LEN);
        // the padding after the record is untouched
        assert_eq!(&buf[RECORD_LEN..], &[0, 0, 0]);
    }

    #[test]
    fn factory_round_trips_and_is_valid() {
        let p = Params::factory();
        p.validate().unwrap();
        assert!((p.head.sensors[1].zero - Vector3::new(0.0, 50.0, 0.0)).norm() < 1e-4);
        let mut buf = [0u8; RECORD_LEN];
        p.encode(&mut buf).unwrap();
        assert_eq!(&buf[..4], b"PPND");
        assert_eq!(Params::decode(&buf).unwrap(), p);
    }

    #[test]
    fn structural_errors_each_reported() {
        let mut buf = [0u8; RECORD_LEN];
        Params::factory().encode(&mut buf).unwrap();
        assert_eq!(
            Params::decode(&buf[..5]),
            Err(Error::Decode("short record"))
        );
        assert_eq!(
            Params::decode(&buf[..100]),
            Err(Error::Decode("short record"))
        );
        let mut b = buf;
        b[0] = b'X';
        assert_eq!(Params::decode(&b), Err(Error::Decode("bad magic")));
        for v in [0u8, 5, 9] {
            let mut b = buf;
            b[4] = v;
            assert_eq!(
                Params::decode(&b),
                Err(Error::Decode("unsupported version"))
            );
        }
        // an older header over a version-4 payload (and the reverse)
        for v in [1u8, 2, 3] {
            let mut b = buf;
            b[4] = v;
            assert_eq!(Params::decode(&b), Err(Error::Decode("bad length")));
        }
        let mut b3 = record_as_v3(&buf);
        b3[4] = 4;
        assert_eq!(Params::decode(&b3), Err(Error::Decode("bad length")));
        let mut b2 = record_as_v2(&buf);
        b2[4] = 3;
        assert_eq!(Params::decode(&b2), Err(Error::Decode("bad length")));
        let mut b1 = record_as_v1(&buf);
        b1[4] = 2;
        assert_eq!(Params::decode(&b1), Err(Error::Decode("bad length")));
        let mut b = buf;
        b[6] = 0;
        assert_eq!(Params::decode(&b), Err(Error::Decode("bad length")));
        let mut b = buf;
        b[200] ^= 0x10;
        assert_eq!(Params::decode(&b), Err(Error::Decode("checksum mismatch")));
        let mut b = buf;
        b[RECORD_LEN - 1] ^= 0x80;
        assert_eq!(Params::decode(&b), Err(Error::Decode("checksum mismatch")));
        // the same checks on a version-2 record, at its own length
        let v2 = record_as_v2(&buf);
        assert_eq!(
            Params::decode(&v2[..V2_RECORD_LEN - 1]),
            Err(Error::Decode("short record"))
        );
        let mut b = v2;
        b[1] = b'Q';
        assert_eq!(Params::decode(&b), Err(Error::Decode("bad magic")));
        let mut b = v2;
        b[6] ^= 0x04;
        assert_eq!(Params::decode(&b), Err(Error::Decode("bad length")));
        let mut b = v2;
        b[V2_RECORD_LEN - 5] ^= 0x01;
        assert_eq!(Params::decode(&b), Err(Error::Decode("checksum mismatch")));
        // the same checks on a version-1 record, at its own length
        let v1 = record_as_v1(&buf);
        assert_eq!(
            Params::decode(&v1[..V1_RECORD_LEN - 1]),
            Err(Error::Decode("short record"))
        );
        let mut b = v1;
        b[2] = b'Q';
        assert_eq!(Params::decode(&b), Err(Error::Decode("bad magic")));
        let mut b = v1;
        b[7] = 2;
        assert_eq!(Params::decode(&b), Err(Error::Decode("bad length")));
        let mut b = v1;
        b[V1_RECORD_LEN - 3] ^= 0x01;
        assert_eq!(Params::decode(&b), Err(Error::Decode("checksum mismatch")));
        // erased flash
        assert_eq!(
            Params::decode(&[0xFF; RECORD_LEN]),
            Err(Error::Decode("bad magic"))
        );
    }

    /// A record written by the version-1 encoder (the code before the
    /// linearity table, run once on [`golden_params`] with
    /// `LinTable::none()`): 365 bytes.
    const GOLDEN_V1_HEX: &str = "50504e4401006101785634120000c841000000000000c0bf00000000000000000000803f000034426f12833a17b75139000000800ad7a33c0ad7a33b000000800000b441acc527b7000000000000c841000010409a99193f00000000cdcc4c3f000038426f12033b17b7513982a8fbb70ad7233c0ad7a33b6f1283ba0000b441acc527b70000c8c1000000000000003e000000009a9919bfcdcc4c3f00003c42a69b443b17b7513982a87bb8000000000ad7a33b6f1203bb0000b441acc527b7000000000000c8c1000040bf295c8fbe000000008fc2753f000040426f12833b17b7513962bebcb80ad723bc0ad7a33ba69b44bb0000b441acc527b70000001643000080400000a0410000a0410000a042010000003f0000000000002041000020410000b4420000007a43000080400000a041000000000000c842010000803e00000000000020410000a0420000a041e80300000400e40c01d00703000000403f1400cdcc4c3d3101009b4158";

    fn unhex(s: &str) -> Vec<u8> {
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
            .collect()
    }

    /// Non-default values in every field, exactly representable where it
    /// matters (unit directions 0.6/0.8, 0.28/0.96).
    fn golden_params() -> Params {
        let dirs = [
            [0.0f32, 0.0, 1.0],
            [0.6, 0.0, 0.8],
            [0.0, -0.6, 0.8],
            [-0.28, 0.0, 0.96],
        ];
        let zeros = [
            [25.0f32, 0.0, -1.5],
            [0.0, 25.0, 2.25],
            [-25.0, 0.0, 0.125],
            [0.0, -25.0, -0.75],
        ];
        let sensor = |i: usize| {
            let k = i as f32;
            Sensor {
                zero: Vector3::from(zeros[i]),
                dir: Vector3::from(dirs[i]),
                ext: Extension {
                    d_ref: 45.0 + k,
                    gain: 1e-3 * (k + 1.0),
                    nonlinearity: [2e-4, -3e-5 * k],
                    table: LinTable::none(),
                    incidence: 0.02 - 0.01 * k,
                    spot: [0.0; 2],
                    crosstalk: 0.005,
                    thermal: -0.001 * k,
                    temp_ref: 22.5,
                    drift: -1e-5,
                },
            }
        };
        Params {
            stamp: 0x1234_5678,
            head: Head4::new([sensor(0), sensor(1), sensor(2), sensor(3)]),
            transfer: [
                Transfer::current(150.0, 20.0, 80.0),
                Transfer::voltage(0.5, 10.0, 90.0),
                Transfer::current(250.0, 0.0, 100.0),
                Transfer::voltage(0.25, 80.0, 20.0),
            ],
            acq: Acquisition {
                method: Method::Chen,
                jump_mm: 0.75,
                stuck_counts: 3,
                ..Acquisition::factory()
            },
            can: CanConfig {
                node_id: 0x31,
                bitrate: Bitrate::K500,
            },
            thermal_tau_s: 0.0,
        }
    }

    fn active_table() -> LinTable<f32> {
        LinTable {
            knots: [-12.0, -5.0, 0.0, 4.5, 12.0],
            coeffs: [1e-3, -2.5e-3, 1.25e-3],
        }
    }

    /// The migration path: a version-1 record from the old encoder decodes
    /// to the values it was made from, with inactive tables, and says where
    /// it ends; re-encoding writes version 2 with the same values.
    #[test]
    fn golden_v1_record_decodes_with_inactive_tables() {
        let v1 = unhex(GOLDEN_V1_HEX);
        assert_eq!(v1.len(), V1_RECORD_LEN);
        assert_eq!(&v1[4..6], &[1, 0]);
        let (p, len) = Params::decode_with_len(&v1).unwrap();
        assert_eq!(len, V1_RECORD_LEN);
        assert_eq!(p, golden_params());
        assert!(p.head.sensors.iter().all(|s| !s.ext.table.is_active()));
        // trailing bytes (a stored tail) are ignored
        let mut padded = v1.clone();
        padded.extend_from_slice(&[0xA5; 40]);
        assert_eq!(Params::decode_with_len(&padded), Ok((p, V1_RECORD_LEN)));
        // the next store writes version 3 of the same values
        let mut v3 = [0u8; RECORD_LEN];
        assert_eq!(p.encode(&mut v3), Ok(RECORD_LEN));
        assert_eq!(&v3[4..6], &VERSION.to_le_bytes());
        assert_eq!(Params::decode_with_len(&v3), Ok((p, RECORD_LEN)));
        // the test's converter reproduces the old encoder byte for byte
        assert_eq!(&record_as_v1(&v3)[..], &v1[..]);
    }

    /// Record offset of `thermal_tau_s` (module docs).
    const TAU_AT: usize = HEADER_LEN + V2_PAYLOAD_LEN;

    /// A record written by the version-3 encoder (the code before the spot
    /// coefficients, run once on [`golden_params`] with [`active_table`]
    /// on sensor 3 and τ = 412.75 s): 497 bytes.
    const GOLDEN_V3_HEX: &str = "50504e440300e501785634120000c841000000000000c0bf00000000000000000000803f000034426f12833a17b75139000000800ad7a33c0ad7a33b000000800000b441acc527b70000000000000000000000000000000000000000000000000000000000000000000000000000c841000010409a99193f00000000cdcc4c3f000038426f12033b17b7513982a8fbb70ad7233c0ad7a33b6f1283ba0000b441acc527b700000000000000000000000000000000000000000000000000000000000000000000c8c1000000000000003e000000009a9919bfcdcc4c3f00003c42a69b443b17b7513982a87bb8000000000ad7a33b6f1203bb0000b441acc527b7000040c10000a0c00000000000009040000040416f12833a0ad723bb0ad7a33a000000000000c8c1000040bf295c8fbe000000008fc2753f000040426f12833b17b7513962bebcb80ad723bc0ad7a33ba69b44bb0000b441acc527b700000000000000000000000000000000000000000000000000000000000000000000001643000080400000a0410000a0410000a042010000003f0000000000002041000020410000b4420000007a43000080400000a041000000000000c842010000803e00000000000020410000a0420000a041e80300000400e40c01d00703000000403f1400cdcc4c3d31010060ce43d566c23e";

    /// The migration path from version 3: it decodes to the values it was
    /// made from with zero spot coefficients, says where it ends, and the
    /// next store writes version 4 of the same values with the spot
    /// coefficients appended after τ; spot coefficients round-trip
    /// bit-exactly at their documented offset and a v3 record of the same
    /// values drops them.
    #[test]
    fn golden_v3_record_decodes_without_spot_terms() {
        let v3 = unhex(GOLDEN_V3_HEX);
        assert_eq!(v3.len(), V3_RECORD_LEN);
        assert_eq!(&v3[4..6], &[3, 0]);
        let mut want = golden_params();
        want.head.sensors[2].ext.table = active_table();
        want.thermal_tau_s = 412.75;
        let (p, len) = Params::decode_with_len(&v3).unwrap();
        assert_eq!((p, len), (want, V3_RECORD_LEN));
        assert!(p.head.sensors.iter().all(|s| s.ext.spot == [0.0; 2]));
        let mut v4 = [0u8; RECORD_LEN];
        assert_eq!(p.encode(&mut v4), Ok(RECORD_LEN));
        assert_eq!(
            &v4[8..HEADER_LEN + V3_PAYLOAD_LEN],
            &v3[8..V3_RECORD_LEN - 4]
        );
        assert_eq!(&record_as_v3(&v4)[..], &v3[..]);
        let mut q = want;
        for (i, s) in q.head.sensors.iter_mut().enumerate() {
            s.ext.spot = [0.0125 * (i as f32 + 1.0), 0.25 * i as f32 - 0.75];
        }
        q.head.sensors[1].ext.spot[0] = -SPOT_MAX_MM;
        let mut buf = [0u8; RECORD_LEN];
        q.encode(&mut buf).unwrap();
        assert_eq!(Params::decode_with_len(&buf), Ok((q, RECORD_LEN)));
        let at = HEADER_LEN + V3_PAYLOAD_LEN + 2 * 8 + 4;
        assert_eq!(&buf[at..at + 4], &(-0.25f32).to_le_bytes());
        assert_eq!(Params::decode(&record_as_v3(&buf)), Ok(want));
        q.head.sensors[3].ext.spot[1] = 10.5;
        assert_eq!(q.validate(), Err(Error::OutOfRange("spot bias")));
        assert_eq!(q.encode(&mut buf), Err(Error::OutOfRange("spot bias")));
        q.head.sensors[3].ext.spot[1] = f32::NAN;
        assert_eq!(q.validate(), Err(Error::NonFinite("extension")));
    }

    /// A record written by the version-2 encoder (the code before the
    /// thermal time constant, run once on [`golden_params`] with
    /// [`active_table`] on sensor 3): 493 bytes.
    const GOLDEN_V2_HEX: &str = "50504e440200e101785634120000c841000000000000c0bf00000000000000000000803f000034426f12833a17b75139000000800ad7a33c0ad7a33b000000800000b441acc527b70000000000000000000000000000000000000000000000000000000000000000000000000000c841000010409a99193f00000000cdcc4c3f000038426f12033b17b7513982a8fbb70ad7233c0ad7a33b6f1283ba0000b441acc527b700000000000000000000000000000000000000000000000000000000000000000000c8c1000000000000003e000000009a9919bfcdcc4c3f00003c42a69b443b17b7513982a87bb8000000000ad7a33b6f1203bb0000b441acc527b7000040c10000a0c00000000000009040000040416f12833a0ad723bb0ad7a33a000000000000c8c1000040bf295c8fbe000000008fc2753f000040426f12833b17b7513962bebcb80ad723bc0ad7a33ba69b44bb0000b441acc527b700000000000000000000000000000000000000000000000000000000000000000000001643000080400000a0410000a0410000a042010000003f0000000000002041000020410000b4420000007a43000080400000a041000000000000c842010000803e00000000000020410000a0420000a041e80300000400e40c01d00703000000403f1400cdcc4c3d31010f7bd97f";

    /// The migration path from version 2: it decodes to the values it was
    /// made from with `thermal_tau_s = 0` (no lag), says where it ends, and
    /// the next store writes version 3 of the same values with the time
    /// constant appended after the CAN settings.
    #[test]
    fn golden_v2_record_decodes_without_lag() {
        let v2 = unhex(GOLDEN_V2_HEX);
        assert_eq!(v2.len(), V2_RECORD_LEN);
        assert_eq!(&v2[4..6], &[2, 0]);
        let mut want = golden_params();
        want.head.sensors[2].ext.table = active_table();
        let (p, len) = Params::decode_with_len(&v2).unwrap();
        assert_eq!((p, len), (want, V2_RECORD_LEN));
        assert_eq!(p.thermal_tau_s, 0.0);
        let mut padded = v2.clone();
        padded.extend_from_slice(&[0x5A; 17]);
        assert_eq!(Params::decode_with_len(&padded), Ok((p, V2_RECORD_LEN)));
        let mut v4 = [0u8; RECORD_LEN];
        assert_eq!(p.encode(&mut v4), Ok(RECORD_LEN));
        assert_eq!(&v4[4..8], &[4, 0, 0x05, 0x02]);
        // the v2 payload is the v4 payload's prefix; τ follows it
        assert_eq!(
            &v4[8..HEADER_LEN + V2_PAYLOAD_LEN],
            &v2[8..V2_RECORD_LEN - 4]
        );
        assert_eq!(&v4[TAU_AT..TAU_AT + 4], &[0; 4]);
        assert_eq!(&record_as_v2(&v4)[..], &v2[..]);
    }

    /// τ round-trips bit-exactly at the documented offset; a v2 or v1
    /// record of the same values drops it (τ = 0).
    #[test]
    fn thermal_tau_round_trips_and_older_versions_drop_it() {
        for tau in [0.0f32, 1e-3, 412.75, THERMAL_TAU_MAX_S] {
            let p = Params {
                thermal_tau_s: tau,
                ..golden_params()
            };
            let mut buf = [0u8; RECORD_LEN];
            p.encode(&mut buf).unwrap();
            assert_eq!(&buf[HEADER_LEN + 481..HEADER_LEN + 485], &tau.to_le_bytes());
            assert_eq!(Params::decode_with_len(&buf), Ok((p, RECORD_LEN)));
            let old = golden_params();
            assert_eq!(Params::decode(&record_as_v2(&buf)), Ok(old));
            assert_eq!(Params::decode(&record_as_v1(&buf)), Ok(old));
        }
    }

    /// An out-of-range or non-finite τ is refused by `validate`, by
    /// `encode` (nothing written) and by `decode` behind a good CRC.
    #[test]
    fn thermal_tau_out_of_range_is_rejected() {
        let range = Err(Error::OutOfRange("thermal time constant"));
        let nonfinite = Err(Error::NonFinite("thermal time constant"));
        let cases = [
            (-1e-6f32, range),
            (-0.0, Ok(())),
            (86_400.01, range),
            (1e9, range),
            (f32::NAN, nonfinite),
            (f32::INFINITY, nonfinite),
        ];
        let mut good = [0u8; RECORD_LEN];
        Params::factory().encode(&mut good).unwrap();
        for (tau, want) in cases {
            let p = Params {
                thermal_tau_s: tau,
                ..Params::factory()
            };
            assert_eq!(p.validate(), want, "{tau}");
            let mut buf = [0xA5u8; RECORD_LEN];
            if want.is_err() {
                assert_eq!(p.encode(&mut buf).map(|_| ()), want, "{tau}");
                assert_eq!(buf, [0xA5u8; RECORD_LEN], "nothing written");
            }
            let mut b = good;
            patch(&mut b, TAU_AT, &tau.to_le_bytes());
            assert_eq!(Params::decode(&b).map(|_| ()), want, "{tau}");
        }
    }

    /// An active table round-trips bit-exactly; a v1 record of the same
    /// values loses only the table.
    #[test]
    fn table_round_trips_and_v1_drops_it() {
        let mut p = golden_params();
        p.head.sensors[2].ext.table = active_table();
        let mut buf = [0u8; RECORD_LEN];
        p.encode(&mut buf).unwrap();
        let (q, len) = Params::decode_with_len(&buf).unwrap();
        assert_eq!((q, len), (p, RECORD_LEN));
        // sensor 2's table sits after its 15 v1 values
        let at = HEADER_LEN + 4 + 2 * SENSOR_LEN + 15 * 4;
        assert_eq!(&buf[at..at + 4], &(-12.0f32).to_le_bytes());
        assert_eq!(&buf[at + 28..at + 32], &1.25e-3f32.to_le_bytes());
        assert_eq!(Params::decode(&record_as_v1(&buf)), Ok(golden_params()));
    }

    /// Rewrites bytes and fixes the CRC, to reach the value checks.
    fn patch(buf: &mut [u8; RECORD_LEN], at: usize, bytes: &[u8]) {
        buf[at..at + bytes.len()].copy_from_slice(bytes);
        let crc = crc32(&buf[..RECORD_LEN - 4]);
        buf[RECORD_LEN - 4..].copy_from_slice(&crc.to_le_bytes());
    }

    #[test]
    fn value_errors_behind_a_good_crc() {
        let mut buf = [0u8; RECORD_LEN];
        Params::factory().encode(&mut buf).unwrap();
        let sensors_end = HEADER_LEN + 4 + SENSORS * SENSOR_LEN;
        let mut b = buf;
        patch(&mut b, sensors_end, &[7]);
        assert_eq!(Params::decode(&b), Err(Error::Decode("unknown front end")));
        let acq = sensors_end + SENSORS * TRANSFER_LEN;
        let mut b = buf;
        patch(&mut b, acq + 8, &[9]);
        assert_eq!(Params::decode(&b), Err(Error::Decode("unknown method")));
        let mut b = buf;
        patch(&mut b, acq, &50u32.to_le_bytes());
        assert_eq!(Params::decode(&b), Err(Error::OutOfRange("period")));
        let mut b = buf;
        patch(&mut b, TAU_AT - 2, &[0]);
        assert_eq!(Params::decode(&b), Err(Error::OutOfRange("node id")));
        let mut b = buf;
        patch(&mut b, TAU_AT - 1, &[4]);
        assert_eq!(Params::decode(&b), Err(Error::OutOfRange("bit rate")));
        let mut b = buf;
        patch(&mut b, HEADER_LEN + 4, &f32::NAN.to_le_bytes());
        assert_eq!(Params::decode(&b), Err(Error::NonFinite("zero point")));
        let mut b = buf;
        // dir.z of sensor 1 from cos 30° to 0.5: |dir| = 0.707
        patch(&mut b, HEADER_LEN + 4 + 20, &0.5f32.to_le_bytes());
        assert_eq!(Params::decode(&b), Err(Error::OutOfRange("beam direction")));
        let mut b = buf;
        patch(&mut b, HEADER_LEN + 4 + 28, &f32::INFINITY.to_le_bytes());
        assert_eq!(Params::decode(&b), Err(Error::NonFinite("extension")));
    }

    #[test]
    fn bad_table_behind_a_good_crc_is_rejected() {
        let mut p = golden_params();
        p.head.sensors[1].ext.table = active_table();
        let mut buf = [0u8; RECORD_LEN];
        p.encode(&mut buf).unwrap();
        let knots = HEADER_LEN + 4 + SENSOR_LEN + 15 * 4;
        let coeffs = knots + TABLE_KNOTS * 4;
        let knot = |b: &mut [u8; RECORD_LEN], k: usize, v: f32| {
            patch(b, knots + 4 * k, &v.to_le_bytes());
        };
        // descending knots with active coefficients
        let mut b = buf;
        knot(&mut b, 1, -20.0);
        let want = Err(Error::OutOfRange("linearity table knots"));
        assert_eq!(Params::decode(&b), want);
        // coinciding knots
        let mut b = buf;
        knot(&mut b, 3, 0.0);
        assert_eq!(Params::decode(&b), want);
        // a knot beyond ±1000 mm
        let mut b = buf;
        knot(&mut b, 4, 1000.5);
        assert_eq!(Params::decode(&b), want);
        // a value beyond 1 mm
        let mut b = buf;
        patch(&mut b, coeffs + 4, &(-1.5f32).to_le_bytes());
        let want = Err(Error::OutOfRange("linearity table values"));
        assert_eq!(Params::decode(&b), want);
        // a non-finite knot
        let mut b = buf;
        knot(&mut b, 0, f32::NAN);
        assert_eq!(Params::decode(&b), Err(Error::NonFinite("extension")));
        // inactive (all coefficients zero): descending knots are ignored
        let mut b = buf;
        patch(&mut b, coeffs, &[0u8; TABLE_COEFFS * 4]);
        knot(&mut b, 0, 500.0);
        let q = Params::decode(&b).unwrap();
        assert!(!q.head.sensors[1].ext.table.is_active());
        assert_eq!(q.head.sensors[1].ext.table.knots[0], 500.0);
        // encode refuses the same table
        p.head.sensors[1].ext.table.knots.swap(0, 1);
        assert_eq!(
            p.encode(&mut buf),
            Err(Error::OutOfRange("linearity table knots"))
        );
    }

    #[test]
    fn validate_table_limits() {
        let mut t = active_table();
        assert_eq!(validate_table(&t), Ok(()));
        t.knots = [-1000.0, -1.0, 0.0, 1.0, 1000.0];
        t.coeffs = [1.0, -1.0, 0.0];
        assert_eq!(validate_table(&t), Ok(()));
        t.coeffs[2] = f32::INFINITY;
        assert_eq!(validate_table(&t), Err(Error::NonFinite("linearity table")));
        let mut t = LinTable::none();
        t.knots = [5.0, 5.0, -1e6, 0.0, 0.0];
        assert_eq!(validate_table(&t), Ok(()));
        t.knots[2] = f32::NAN;
        assert_eq!(validate_table(&t), Err(Error::NonFinite("linearity table")));
    }

    #[test]
    fn validate_rejects_bad_configuration() {
        let mut p = Params::factory();
        p.acq.os_log2 = 8;
        p.acq.os_shift = 2;
        assert_eq!(p.validate(), Err(Error::OutOfRange("oversampling shift")));
        let mut p = Params::factory();
        p.transfer[2] = Transfer::current(5.0, 20.0, 80.0);
        assert_eq!(p.validate(), Err(Error::OutOfRange("shunt")));
        let mut p = Params::factory();
        p.transfer[1] = Transfer::voltage(0.0, 20.0, 80.0);
        assert_eq!(p.validate(), Err(Error::OutOfRange("divider ratio")));
        let mut p = Params::factory();
        p.transfer[0].mm_hi = p.transfer[0].mm_lo;
        assert_eq!(p.validate(), Err(Error::OutOfRange("measuring range")));
        let mut p = Params::factory();
        p.transfer[3].sig_hi = 4.5;
        assert_eq!(p.validate(), Err(Error::OutOfRange("signal span")));
        let mut p = Params::factory();
        p.acq.max_rms_mm = 0.0;
        assert_eq!(p.validate(), Err(Error::OutOfRange("residual limit")));
        // encode refuses what validate refuses
        let mut buf = [0u8; RECORD_LEN];
        assert_eq!(p.encode(&mut buf), Err(Error::OutOfRange("residual limit")));
        assert_eq!(
            Params::factory().encode(&mut buf[..10]),
            Err(Error::BufferTooSmall)
        );
    }

    /// Active tables (ascending knots within ±1000 mm, coefficients up to
    /// the 1 mm limit) and inactive ones (zero coefficients, knots any
    /// finite values in any order).
    fn arb_table() -> impl Strategy<Value = LinTable<f32>> {
        let active = (
            -1000.0f32..0.0,
            prop::array::uniform4(0.01f32..250.0),
            prop::array::uniform3(-1.0f32..=1.0),
        )
            .prop_filter_map("inactive", |(k0, steps, coeffs)| {
                let mut knots = [k0; TABLE_KNOTS];
                for i in 1..TABLE_KNOTS {
                    knots[i] = knots[i - 1] + steps[i - 1];
                }
                let t = LinTable { knots, coeffs };
                (t.is_active() && t.knots_valid()).then_some(t)
            });
        let inactive = prop::array::uniform5(-1e30f32..1e30).prop_map(|knots| LinTable {
            knots,
            coeffs: [0.0; TABLE_COEFFS],
        });
        prop_oneof![Just(LinTable::none()), active, inactive]
    }

    fn arb_ext() -> impl Strategy<Value = Extension<f32>> {
        (
            prop::array::uniform9(-1.0f32..1.0),
            prop::array::uniform2(-1.0f32..1.0),
            arb_table(),
        )
            .prop_map(|(a, spot, table)| Extension {
                d_ref: a[0] * 50.0 + 50.0,
                gain: a[1] * 1e-2,
                nonlinearity: [a[2] * 1e-3, a[3] * 1e-4],
                table,
                incidence: a[4] * 0.1,
                spot: spot.map(|x| x * SPOT_MAX_MM),
                crosstalk: a[5] * 0.01,
                thermal: a[6] * 0.01,
                temp_ref: a[7] * 10.0 + 20.0,
                drift: a[8] * 1e-4,
            })
    }

    fn arb_sensor() -> impl Strategy<Value = Sensor<f32>> {
        (
            prop::array::uniform3(-100.0f32..100.0),
            prop::array::uniform3(-1.0f32..1.0),
            arb_ext(),
        )
            .prop_filter_map("zero direction", |(z, d, ext)| {
                let mut s = Sensor::new(Vector3::from(z), Vector3::from(d)).ok()?;
                s.ext = ext;
                Some(s)
            })
    }

    fn arb_transfer() -> impl Strategy<Value = Transfer> {
        (any::<bool>(), 0.0f32..1.0, 0.0f32..500.0, 0.1f32..500.0).prop_map(|(cur, k, lo, span)| {
            if cur {
                Transfer::current(10.0 + k * 990.0, lo, lo + span)
            } else {
                Transfer::voltage(0.01 + k * 0.99, lo + span, lo)
            }
        })
    }

    pub(crate) fn arb_params() -> impl Strategy<Value = Params> {
        (
            any::<u32>(),
            prop::array::uniform4(arb_sensor()),
            prop::array::uniform4(arb_transfer()),
            (
                100u32..=100_000,
                0u8..=8,
                0u8..=4,
                1800u16..=3600,
                any::<bool>(),
            ),
            (
                0u16..=60_000,
                any::<u16>(),
                0.0f32..1000.0,
                0u16..=60_000,
                1e-4f32..100.0,
            ),
            (1u8..=127, 0u8..4),
            prop_oneof![Just(0.0f32), 0.0f32..=THERMAL_TAU_MAX_S],
        )
            .prop_map(|(stamp, sensors, transfer, a, b, c, tau)| Params {
                stamp,
                head: Head4::new(sensors),
                transfer,
                acq: Acquisition {
                    period_us: a.0,
                    os_log2: a.1,
                    os_shift: (a.1 + a.2).min(8),
                    vref_mv: a.3,
                    method: if a.4 {
                        Method::Chen
                    } else {
                        Method::LeastSquares
                    },
                    stuck_samples: b.0,
                    stuck_counts: b.1,
                    jump_mm: b.2,
                    jump_hold: b.3,
                    max_rms_mm: b.4,
                },
                can: CanConfig {
                    node_id: c.0,
                    bitrate: Bitrate::from_code(c.1).unwrap(),
                },
                thermal_tau_s: tau,
            })
    }

    /// `p` with every spot coefficient zero (what an older record keeps).
    fn without_spot(mut p: Params) -> Params {
        for s in p.head.sensors.iter_mut() {
            s.ext.spot = [0.0; 2];
        }
        p
    }

    proptest! {
        #[test]
        fn round_trip(p in arb_params()) {
            let mut buf = [0u8; RECORD_LEN];
            prop_assert_eq!(p.encode(&mut buf), Ok(RECORD_LEN));
            prop_assert_eq!(Params::decode(&buf), Ok(p));
        }

        #[test]
        fn any_single_bit_flip_is_rejected(p in arb_params(), bit in 0usize..RECORD_LEN * 8) {
            let mut buf = [0u8; RECORD_LEN];
            p.encode(&mut buf).unwrap();
            buf[bit / 8] ^= 1 << (bit % 8);
            prop_assert!(Params::decode(&buf).is_err());
        }

        #[test]
        fn v1_of_any_params_decodes_without_table(p in arb_params()) {
            let mut buf = [0u8; RECORD_LEN];
            p.encode(&mut buf).unwrap();
            let mut want = without_spot(p);
            want.thermal_tau_s = 0.0;
            for s in want.head.sensors.iter_mut() {
                s.ext.table = LinTable::none();
            }
            prop_assert_eq!(Params::decode_with_len(&record_as_v1(&buf)), Ok((want, V1_RECORD_LEN)));
        }

        #[test]
        fn v2_of_any_params_decodes_without_lag(p in arb_params()) {
            let mut buf = [0u8; RECORD_LEN];
            p.encode(&mut buf).unwrap();
            let want = Params { thermal_tau_s: 0.0, ..without_spot(p) };
            prop_assert_eq!(Params::decode_with_len(&record_as_v2(&buf)), Ok((want, V2_RECORD_LEN)));
        }

        #[test]
        fn v3_of_any_params_decodes_without_spot_terms(p in arb_params()) {
            let mut buf = [0u8; RECORD_LEN];
            p.encode(&mut buf).unwrap();
            let want = without_spot(p);
            prop_assert_eq!(Params::decode_with_len(&record_as_v3(&buf)), Ok((want, V3_RECORD_LEN)));
        }

        #[test]
        fn any_single_bit_flip_of_a_v2_record_is_rejected(
            p in arb_params(),
            bit in 0usize..V2_RECORD_LEN * 8,
        ) {
            let mut buf = [0u8; RECORD_LEN];
            p.encode(&mut buf).unwrap();
            let mut v2 = record_as_v2(&buf);
            v2[bit / 8] ^= 1 << (bit % 8);
            prop_assert!(Params::decode(&v2).is_err());
        }

        #[test]
        fn any_single_bit_flip_of_a_v1_record_is_rejected(
            p in arb_params(),
            bit in 0usize..V1_RECORD_LEN * 8,
        ) {
            let mut buf = [0u8; RECORD_LEN];
            p.encode(&mut buf).unwrap();
            let mut v1 = record_as_v1(&buf);
            v1[bit / 8] ^= 1 << (bit % 8);
            prop_assert!(Params::decode(&v1).is_err());
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
            // Either an error or a record that validates.
            if let Ok(p) = Params::decode(&bytes) {
                prop_assert!(p.validate().is_ok());
            }
        }

        #[test]
        fn valid_header_random_body_never_panics(
            body in prop::collection::vec(any::<u8>(), PAYLOAD_LEN),
            which in 0u8..3,
        ) {
            // A header that passes (any version), a random payload and a
            // matching CRC: the value checks must reject or accept without
            // panicking.
            let (version, payload) = match which {
                0 => (VERSION_1, V1_PAYLOAD_LEN),
                1 => (VERSION_2, V2_PAYLOAD_LEN),
                _ => (VERSION, PAYLOAD_LEN),
            };
            let len = HEADER_LEN + payload + 4;
            let mut buf = [0u8; RECORD_LEN];
            buf[..4].copy_from_slice(&MAGIC);
            buf[4..6].copy_from_slice(&version.to_le_bytes());
            buf[6..8].copy_from_slice(&(payload as u16).to_le_bytes());
            buf[HEADER_LEN..len - 4].copy_from_slice(&body[..payload]);
            let crc = crc32(&buf[..len - 4]);
            buf[len - 4..len].copy_from_slice(&crc.to_le_bytes());
            if let Ok((p, n)) = Params::decode_with_len(&buf[..len]) {
                prop_assert_eq!(n, len);
                prop_assert!(p.validate().is_ok());
            }
        }
    }
}
