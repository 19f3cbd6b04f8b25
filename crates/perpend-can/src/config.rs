//! Typed views of the application objects: the defaults a device starts
//! from, the calibration and configuration records the application reads,
//! and the measurement it publishes.
//!
//! Every value here is `f32`/integer because that is what the object
//! dictionary holds (REAL32); conversions to the core's generic types
//! ([`SensorCalibration::to_sensor`]) go through [`perpend_core::Real`].

use perpend_core::ext::{Extension, LinTable, TABLE_COEFFS, TABLE_KNOTS};
use perpend_core::head::{Head4, Sensor};
use perpend_core::normal::Method;
use perpend_core::params::{Bitrate, Frontend, Params, Transfer};
use perpend_core::Real;

/// Vendor-ID placeholder of builds without `PERPEND_VENDOR_ID`:
/// 0xAFFF_5050 ("PP"). CiA assigns every vendor-ID (0x0000_0000 to
/// 0xAFFE_FFFF) and reserves no range for tests or unregistered use; this
/// value lies in 0xAFFF_0000..=0xFFFE_FFFF, which CiA lists as *reserved*
/// (assigned to nobody), so it cannot collide with a registered vendor.
/// A product shipped to integrators must be built with its CiA-assigned
/// ID: `PERPEND_VENDOR_ID=0x... cargo xtask fw`.
pub const VENDOR_ID_PLACEHOLDER: u32 = 0xAFFF_5050;

/// The vendor-ID (0x1018 sub 1), fixed at build time: the environment
/// variable `PERPEND_VENDOR_ID` (decimal or `0x` hex, not 0) when the crate
/// is compiled, else [`VENDOR_ID_PLACEHOLDER`]. A malformed or zero value
/// is a compile error.
pub const VENDOR_ID: u32 = match option_env!("PERPEND_VENDOR_ID") {
    Some(s) => match parse_u32(s.as_bytes()) {
        Some(v) if v != 0 => v,
        _ => panic!("PERPEND_VENDOR_ID: expected a non-zero decimal or 0x hex u32"),
    },
    None => VENDOR_ID_PLACEHOLDER,
};

/// Device type 0x1000: 0x0000_0000, "no standardized device profile"
/// (CiA 301 §7.5.2.1; the additional information is then 0 too). CiA 404
/// (measuring devices) was considered: its analog-input function blocks
/// (0x6100.. field values, 0x6130 process values, 0x6110 sensor type,
/// 0x6131 physical unit coded per CiA 303-2, ...) are not implemented,
/// and announcing profile 404 (0x0194) would make a profile-aware master
/// look for them. The measurement lives in the manufacturer area
/// (0x2001..0x2008, docs/can.md).
pub const DEVICE_TYPE: u32 = 0;

/// Parses a decimal or `0x` hexadecimal `u32` (const, for build-time
/// settings).
pub const fn parse_u32(s: &[u8]) -> Option<u32> {
    let (radix, start) = if s.len() > 2 && s[0] == b'0' && (s[1] == b'x' || s[1] == b'X') {
        (16u64, 2)
    } else {
        (10u64, 0)
    };
    if s.len() <= start {
        return None;
    }
    let mut v: u64 = 0;
    let mut i = start;
    while i < s.len() {
        let d = match s[i] {
            b'0'..=b'9' => (s[i] - b'0') as u64,
            b'a'..=b'f' => (s[i] - b'a' + 10) as u64,
            b'A'..=b'F' => (s[i] - b'A' + 10) as u64,
            b'_' => {
                i += 1;
                continue;
            }
            _ => return None,
        };
        if d >= radix {
            return None;
        }
        v = v * radix + d;
        if v > u32::MAX as u64 {
            return None;
        }
        i += 1;
    }
    Some(v as u32)
}

/// A 32-bit serial number (0x1018 sub 4) from the MCU's 96-bit unique ID
/// (STM32G4 UID at 0x1FFF_7590, little-endian bytes): FNV-1a over the 12
/// bytes. Every UID bit influences the result (XOR-folding the three words
/// would cancel patterns between lot number and wafer coordinates); two
/// boards collide with probability 2^-32 per pair.
pub const fn serial_from_uid(uid: &[u8; 12]) -> u32 {
    let mut h: u32 = 0x811C_9DC5;
    let mut i = 0;
    while i < 12 {
        h ^= uid[i] as u32;
        h = h.wrapping_mul(0x0100_0193);
        i += 1;
    }
    h
}

/// Identity object 0x1018.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Identity {
    /// Sub 1: vendor-ID assigned by CiA ([`VENDOR_ID`]).
    pub vendor_id: u32,
    /// Sub 2: product code.
    pub product_code: u32,
    /// Sub 3: revision number (major << 16 | minor).
    pub revision: u32,
    /// Sub 4: serial number (unique per board, e.g. from the MCU UID).
    pub serial: u32,
}

/// Number of values of a sensor calibration object (0x2101..0x2104 sub
/// 1..=25).
pub const CAL_VALUES: usize = 15 + TABLE_KNOTS + TABLE_COEFFS + 2;

/// First sub-index of the linearity table's knots in 0x2101..0x2104.
pub const CAL_SUB_KNOTS: u8 = 16;
/// First sub-index of the linearity table's values in
/// 0x2101..0x2104.
pub const CAL_SUB_COEFFS: u8 = CAL_SUB_KNOTS + TABLE_KNOTS as u8;
/// First sub-index of the two spot coefficients (cos φ, sin φ) in
/// 0x2101..0x2104: right after the linearity table's values.
pub const CAL_SUB_SPOT: u8 = CAL_SUB_COEFFS + TABLE_COEFFS as u8;

/// Calibration of one sensor: objects 0x2101..0x2104, one per sensor.
/// Sub-index order is the field order below (sub 1 = `zero[0]` ...
/// sub 15 = `drift`, sub 16..20 the table's knots, sub 21..23 its
/// values, sub 24..25 the spot coefficients). Units: mm, mm/°C, °C, mm/s, mm⁻¹ as in
/// [`perpend_core::ext::Extension`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorCalibration {
    /// Sub 1-3: zero point `E_i` x, y, z [mm, TCS].
    pub zero: [f32; 3],
    /// Sub 4-6: beam direction x, y, z (normalised by the application).
    pub dir: [f32; 3],
    /// Sub 7: reference distance of gain and non-linearity \[mm\].
    pub d_ref: f32,
    /// Sub 8: relative gain error [-].
    pub gain: f32,
    /// Sub 9: quadratic non-linearity [mm⁻¹].
    pub nl2: f32,
    /// Sub 10: cubic non-linearity [mm⁻²].
    pub nl3: f32,
    /// Sub 11: incidence bias \[mm\].
    pub incidence: f32,
    /// Sub 12: cross-talk from the previously converted channel [-].
    pub crosstalk: f32,
    /// Sub 13: thermal drift [mm/°C].
    pub thermal: f32,
    /// Sub 14: reference temperature of `thermal` [°C].
    pub temp_ref: f32,
    /// Sub 15: drift with time [mm/s].
    pub drift: f32,
    /// Sub 16-20: knots `ξ_0..ξ_4` of the linearity table \[mm\] about
    /// `d_ref` ([`perpend_core::ext::LinTable`]).
    pub knots: [f32; TABLE_KNOTS],
    /// Sub 21-23: values `v_0..v_2` \[mm\] of the linearity table at its
    /// interior knots (all zero: no table, the knots are ignored).
    pub coeffs: [f32; TABLE_COEFFS],
    /// Sub 24-25: spot coefficients of the incidence correction \[mm per
    /// unit of tan²γ\]: the bias `spot[0]·tan²γ·cos φ + spot[1]·tan²γ·sin φ`
    /// ([`perpend_core::ext::Extension::spot`]; |spot| ≤ 10 mm as the
    /// stored record).
    pub spot: [f32; 2],
}

impl SensorCalibration {
    /// The [`CAL_VALUES`] values in sub-index order (sub 1 first).
    pub fn to_array(&self) -> [f32; CAL_VALUES] {
        let [k0, k1, k2, k3, k4] = self.knots;
        let [c0, c1, c2] = self.coeffs;
        [
            self.zero[0],
            self.zero[1],
            self.zero[2],
            self.dir[0],
            self.dir[1],
            self.dir[2],
            self.d_ref,
            self.gain,
            self.nl2,
            self.nl3,
            self.incidence,
            self.crosstalk,
            self.thermal,
            self.temp_ref,
            self.drift,
            k0,
            k1,
            k2,
            k3,
            k4,
            c0,
            c1,
            c2,
            self.spot[0],
            self.spot[1],
        ]
    }

    /// From the [`CAL_VALUES`] values in sub-index order.
    pub fn from_array(v: &[f32; CAL_VALUES]) -> Self {
        Self {
            zero: [v[0], v[1], v[2]],
            dir: [v[3], v[4], v[5]],
            d_ref: v[6],
            gain: v[7],
            nl2: v[8],
            nl3: v[9],
            incidence: v[10],
            crosstalk: v[11],
            thermal: v[12],
            temp_ref: v[13],
            drift: v[14],
            knots: [v[15], v[16], v[17], v[18], v[19]],
            coeffs: [v[20], v[21], v[22]],
            spot: [v[23], v[24]],
        }
    }

    /// From a core sensor (any float type; values are rounded to `f32`).
    pub fn from_sensor<T: Real>(s: &Sensor<T>) -> Self {
        let f = |x: T| x.to_f64() as f32;
        Self {
            zero: [f(s.zero.x), f(s.zero.y), f(s.zero.z)],
            dir: [f(s.dir.x), f(s.dir.y), f(s.dir.z)],
            d_ref: f(s.ext.d_ref),
            gain: f(s.ext.gain),
            nl2: f(s.ext.nonlinearity[0]),
            nl3: f(s.ext.nonlinearity[1]),
            incidence: f(s.ext.incidence),
            crosstalk: f(s.ext.crosstalk),
            thermal: f(s.ext.thermal),
            temp_ref: f(s.ext.temp_ref),
            drift: f(s.ext.drift),
            knots: s.ext.table.knots.map(f),
            coeffs: s.ext.table.coeffs.map(f),
            spot: s.ext.spot.map(f),
        }
    }

    /// The core sensor these values describe (direction normalised).
    ///
    /// # Errors
    /// [`perpend_core::Error`] for a non-finite zero point or a zero-length
    /// or non-finite direction; [`perpend_core::Error::OutOfRange`] for an
    /// active linearity table whose knots are not finite and strictly
    /// ascending ([`SensorCalibration::table_valid`]).
    pub fn to_sensor<T: Real>(&self) -> perpend_core::Result<Sensor<T>> {
        let c = |x: f32| T::lit(x as f64);
        let v3 = |a: [f32; 3]| nalgebra::Vector3::new(c(a[0]), c(a[1]), c(a[2]));
        let mut s = Sensor::new(v3(self.zero), v3(self.dir))?;
        if !self.table_valid() {
            return Err(perpend_core::Error::OutOfRange("linearity table knots"));
        }
        s.ext = self.extension();
        Ok(s)
    }

    /// The linearity table (sub 16..23) as the core's type.
    pub fn table<T: Real>(&self) -> LinTable<T> {
        let c = |x: f32| T::lit(x as f64);
        LinTable {
            knots: self.knots.map(c),
            coeffs: self.coeffs.map(c),
        }
    }

    /// Whether the linearity table is usable: inactive (every coefficient
    /// zero, the knots are then ignored) or with finite, strictly
    /// ascending knots ([`LinTable::knots_valid`]).
    pub fn table_valid(&self) -> bool {
        let t = self.table::<f32>();
        !t.is_active() || t.knots_valid()
    }

    /// The extension coefficients (sub 7..25) as the core's type.
    pub fn extension<T: Real>(&self) -> Extension<T> {
        let c = |x: f32| T::lit(x as f64);
        Extension {
            d_ref: c(self.d_ref),
            gain: c(self.gain),
            nonlinearity: [c(self.nl2), c(self.nl3)],
            table: self.table(),
            incidence: c(self.incidence),
            spot: self.spot.map(c),
            crosstalk: c(self.crosstalk),
            thermal: c(self.thermal),
            temp_ref: c(self.temp_ref),
            drift: c(self.drift),
        }
    }
}

/// How a sensor's analog output becomes millimetres: objects
/// 0x2201..0x2204.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TransferFunction {
    /// Sub 1: 0 = 4-20 mA on a shunt, 1 = 0-10 V on a divider.
    pub kind: u8,
    /// Sub 2: shunt resistance \[Ω\] (kind 0) or divider ratio
    /// `V_pin / V_sensor` in (0, 1] (kind 1).
    pub scale: f32,
    /// Sub 3: distance at 4 mA / 0 V \[mm\].
    pub mm_at_low: f32,
    /// Sub 4: distance at 20 mA / 10 V \[mm\].
    pub mm_at_high: f32,
}

/// Transfer-function kind: 4-20 mA current loop on a shunt.
pub const TF_CURRENT_4_20MA: u8 = 0;
/// Transfer-function kind: 0-10 V on a resistive divider.
pub const TF_VOLTAGE_0_10V: u8 = 1;

/// Acquisition settings: object 0x2300.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Acquisition {
    /// Sub 1: sample period \[µs\], 100..=100000.
    pub period_us: u32,
    /// Sub 2: oversampling ratio, power of two in 1..=256.
    pub oversampling: u16,
    /// Sub 3: plane method, 0 = Chen (eq. 18-19), 1 = least squares.
    pub method: u8,
    /// Sub 4: largest acceptable plane RMS residual \[mm\].
    pub residual_limit_mm: f32,
}

/// Plane method code: Chen eq. 18-19.
pub const METHOD_CHEN: u8 = 0;
/// Plane method code: total least squares.
pub const METHOD_LEAST_SQUARES: u8 = 1;

impl Acquisition {
    /// The core's plane method for sub 3 (anything but 0 is least squares;
    /// the object dictionary only accepts 0 and 1).
    pub fn plane_method(&self) -> perpend_core::normal::Method {
        if self.method == METHOD_CHEN {
            perpend_core::normal::Method::Chen
        } else {
            perpend_core::normal::Method::LeastSquares
        }
    }
}

/// Surface model code (0x2310 sub 1): plane (the micro-plane, unchanged).
pub const SURFACE_PLANE: u8 = 0;
/// Surface model code: sphere of the signed radius of sub 2.
pub const SURFACE_SPHERE: u8 = 1;
/// Surface model code: circular cylinder of the signed radius of sub 2 and
/// the axis direction of subs 3-5.
pub const SURFACE_CYLINDER: u8 = 2;
/// Largest |radius| of 0x2310 sub 2 \[mm\] (the fit runs in `f32` up to
/// ~10⁴ mm; a larger radius is a plane for the board).
pub const SURFACE_RADIUS_MAX_MM: f32 = 100_000.0;
/// Smallest |radius| of 0x2310 sub 2 \[mm\]: abort 0x06090030 below it
/// (zero included).
pub const SURFACE_RADIUS_MIN_MM: f32 = 10.0;
/// Default radius of 0x2310 sub 2 \[mm\] (unused by the plane model).
pub const SURFACE_RADIUS_DEFAULT_MM: f32 = 1000.0;
/// Smallest length of the cylinder axis (0x2310 subs 3-5) with the
/// cylinder model selected: abort 0x06090030 below it.
pub const SURFACE_AXIS_MIN_LEN: f32 = 1e-3;

/// Nominal surface under the head: object 0x2310 (issue 14), applied to
/// every sample ([`perpend_core::surface`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceModel {
    /// Sub 1: [`SURFACE_PLANE`], [`SURFACE_SPHERE`] or [`SURFACE_CYLINDER`].
    pub model: u8,
    /// Sub 2: signed radius \[mm\], `> 0` convex, `< 0` concave.
    pub radius_mm: f32,
    /// Subs 3-5: direction of the cylinder's axis in the TCS.
    pub axis: [f32; 3],
}

impl SurfaceModel {
    /// The core's shape.
    ///
    /// # Errors
    /// [`perpend_core::Error::OutOfRange`] for an unknown model, a radius
    /// outside [`SURFACE_RADIUS_MIN_MM`]..=[`SURFACE_RADIUS_MAX_MM`] in
    /// magnitude (or not finite), or a cylinder axis shorter than
    /// [`SURFACE_AXIS_MIN_LEN`] (the dictionary refuses all of these on
    /// write; a stored image is checked the same way).
    pub fn to_shape(&self) -> Result<perpend_core::surface::Shape<f32>, perpend_core::Error> {
        use perpend_core::surface::Shape;
        let radius = self.radius_mm;
        let radius_ok =
            radius.abs() >= SURFACE_RADIUS_MIN_MM && radius.abs() <= SURFACE_RADIUS_MAX_MM;
        match self.model {
            SURFACE_PLANE => Ok(Shape::Plane),
            SURFACE_SPHERE if radius_ok => Ok(Shape::Sphere { radius }),
            SURFACE_CYLINDER if radius_ok => {
                let axis = nalgebra::Vector3::from(self.axis);
                if axis.norm() >= SURFACE_AXIS_MIN_LEN {
                    Ok(Shape::Cylinder { radius, axis })
                } else {
                    Err(perpend_core::Error::OutOfRange("cylinder axis"))
                }
            }
            SURFACE_SPHERE | SURFACE_CYLINDER => {
                Err(perpend_core::Error::OutOfRange("surface radius"))
            }
            _ => Err(perpend_core::Error::OutOfRange("surface model")),
        }
    }
}

/// Communication settings: object 0x2400. Both take effect at the next
/// reset (communication or node).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Communication {
    /// Sub 1: node-id, 1..=127.
    pub node_id: u8,
    /// Sub 2: bit rate [kbit/s]: 125, 250, 500 or 1000.
    pub bit_rate_kbps: u16,
}

/// Bit rates accepted by 0x2400 sub 2 [kbit/s].
pub const BIT_RATES_KBPS: [u16; 4] = [125, 250, 500, 1000];

/// Everything a device starts from: identity, strings, and the default
/// (factory) values of every persisted object. 0x1011 "load" restores these.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Defaults {
    /// 0x1000 device type ([`DEVICE_TYPE`]).
    pub device_type: u32,
    /// 0x1008 manufacturer device name.
    pub device_name: &'static str,
    /// 0x1009 manufacturer hardware version.
    pub hardware_version: &'static str,
    /// 0x100A manufacturer software version.
    pub software_version: &'static str,
    /// 0x1018 identity.
    pub identity: Identity,
    /// 0x1017 producer heartbeat time \[ms\] (0 = off).
    pub heartbeat_ms: u16,
    /// SDO server timeout of a segmented transfer \[µs\] (not an object).
    pub sdo_timeout_us: u64,
    /// Duration of one ADC scan without oversampling \[ns\] (not an
    /// object): a write to 0x2300 sub 1 (period) or sub 2 (oversampling)
    /// is refused with SDO abort 0x06090030 when `oversampling ·
    /// adc_scan_ns` would exceed the period (the scan would not finish
    /// before the next trigger). 0 = no such check (the nominal defaults:
    /// the board sets its figure, `perpend_board::scan::SCAN_NS`).
    pub adc_scan_ns: u32,
    /// 0x2101..0x2104 calibration of sensors 1..4.
    pub calibration: [SensorCalibration; 4],
    /// 0x2201..0x2204 transfer functions of sensors 1..4.
    pub transfer: [TransferFunction; 4],
    /// 0x2300 acquisition.
    pub acquisition: Acquisition,
    /// 0x2105 the head's thermal time constant \[s\] (0 = no lag;
    /// `perpend_core::params::Params::thermal_tau_s`).
    pub thermal_tau_s: f32,
    /// 0x2400 sub 2 bit rate [kbit/s] (sub 1 defaults to the node-id passed
    /// to [`crate::Device::new`]).
    pub bit_rate_kbps: u16,
}

impl TransferFunction {
    /// From the core's stored transfer function (its signal span is implied
    /// by the kind: 4-20 mA or 0-10 V).
    pub fn from_transfer(t: &Transfer) -> Self {
        let (kind, scale) = match t.frontend {
            Frontend::Shunt { ohm } => (TF_CURRENT_4_20MA, ohm),
            Frontend::Divider { ratio } => (TF_VOLTAGE_0_10V, ratio),
        };
        Self {
            kind,
            scale,
            mm_at_low: t.mm_lo,
            mm_at_high: t.mm_hi,
        }
    }

    /// The core's transfer function. The signal span is 4-20 mA (kind 0) or
    /// 0-10 V (kind 1), unless `base` has the same kind, whose span is kept
    /// (e.g. a live-zero 1-10 V sensor configured in the stored record).
    pub fn to_transfer(&self, base: &Transfer) -> Transfer {
        let mut t = if self.kind == TF_VOLTAGE_0_10V {
            Transfer::voltage(self.scale, self.mm_at_low, self.mm_at_high)
        } else {
            Transfer::current(self.scale, self.mm_at_low, self.mm_at_high)
        };
        if core::mem::discriminant(&t.frontend) == core::mem::discriminant(&base.frontend) {
            t.sig_lo = base.sig_lo;
            t.sig_hi = base.sig_hi;
        }
        t
    }
}

/// The bit rate [kbit/s] of a core bit-rate setting.
pub const fn kbps_of(b: Bitrate) -> u16 {
    match b {
        Bitrate::K125 => 125,
        Bitrate::K250 => 250,
        Bitrate::K500 => 500,
        Bitrate::M1 => 1000,
    }
}

/// The core bit-rate setting of `kbps` (`None` unless 125/250/500/1000).
pub const fn bitrate_of(kbps: u16) -> Option<Bitrate> {
    match kbps {
        125 => Some(Bitrate::K125),
        250 => Some(Bitrate::K250),
        500 => Some(Bitrate::K500),
        1000 => Some(Bitrate::M1),
        _ => None,
    }
}

impl Defaults {
    /// The product's nominal defaults: [`Defaults::from_params`] of
    /// [`Params::factory`] (the design head, 4-20 mA sensors, 1 kHz, least
    /// squares; see there), heartbeat 1000 ms, SDO timeout 1 s, no ADC
    /// scan-time check (`adc_scan_ns` 0), identity
    /// with vendor-ID [`VENDOR_ID`], product code "PERP" and serial 0 (the
    /// board sets it with [`Defaults::with_serial`]: the firmware from the
    /// MCU UID, [`serial_from_uid`]).
    pub fn nominal() -> Self {
        Self::from_params(&Params::factory())
    }

    /// Defaults whose calibration and configuration objects hold the
    /// values of `p` (what 0x1011 "load" restores), with the nominal
    /// identity, strings and timing. The node-id is passed to
    /// [`crate::Device::new`] separately (usually `p.can.node_id`).
    pub fn from_params(p: &Params) -> Self {
        Self {
            device_type: DEVICE_TYPE,
            device_name: "perpend normal sensor",
            hardware_version: "perpend board rev A",
            software_version: concat!("perpend ", env!("CARGO_PKG_VERSION")),
            identity: Identity {
                vendor_id: VENDOR_ID,
                product_code: 0x5045_5250,
                revision: 0x0001_0000,
                serial: 0,
            },
            heartbeat_ms: 1000,
            sdo_timeout_us: 1_000_000,
            adc_scan_ns: 0,
            calibration: p.head.sensors.map(|s| SensorCalibration::from_sensor(&s)),
            transfer: p.transfer.map(|t| TransferFunction::from_transfer(&t)),
            acquisition: Acquisition::from_params(&p.acq),
            thermal_tau_s: p.thermal_tau_s,
            bit_rate_kbps: kbps_of(p.can.bitrate),
        }
    }

    /// The defaults with serial number `serial` (0x1018 sub 4).
    pub const fn with_serial(mut self, serial: u32) -> Self {
        self.identity.serial = serial;
        self
    }

    /// The defaults with the calibration replaced by `head` (e.g. the
    /// virtual board's or a calibrated head).
    pub fn with_head<T: Real>(mut self, head: &Head4<T>) -> Self {
        for (c, s) in self.calibration.iter_mut().zip(head.sensors.iter()) {
            *c = SensorCalibration::from_sensor(s);
        }
        self
    }
}

impl Acquisition {
    /// From the core's acquisition settings (oversampling ratio
    /// `2^os_log2`).
    pub fn from_params(a: &perpend_core::params::Acquisition) -> Self {
        Self {
            period_us: a.period_us,
            oversampling: 1u16 << a.os_log2.min(8),
            method: match a.method {
                Method::Chen => METHOD_CHEN,
                Method::LeastSquares => METHOD_LEAST_SQUARES,
            },
            residual_limit_mm: a.max_rms_mm,
        }
    }

    /// Onto the core's acquisition settings `base` (fields without an
    /// object are kept; the oversampling shift is raised if needed so that
    /// `os_log2 − os_shift ≤ 4`).
    pub fn to_params(
        &self,
        base: &perpend_core::params::Acquisition,
    ) -> perpend_core::params::Acquisition {
        let log2 = (self.oversampling.max(1).trailing_zeros() as u8).min(8);
        let shift = if log2 > base.os_shift + 4 {
            log2 - 4
        } else {
            base.os_shift
        };
        perpend_core::params::Acquisition {
            period_us: self.period_us,
            os_log2: log2,
            os_shift: shift,
            method: self.plane_method(),
            max_rms_mm: self.residual_limit_mm,
            ..*base
        }
    }
}

/// One sample of the measurement objects 0x2001..0x2006, as the application
/// publishes it with [`crate::Device::set_measurement`]. Angles in degrees.
/// Unavailable quantities are 0 (see [`crate::status`]): never NaN.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measurement {
    /// 0x2001 sub 1-3: unit normal towards the head (TCS).
    pub normal: [f32; 3],
    /// 0x2002 sub 1: θ1 \[deg\].
    pub theta1_deg: f32,
    /// 0x2002 sub 2: θ2 \[deg\].
    pub theta2_deg: f32,
    /// 0x2002 sub 3: θ \[deg\].
    pub theta_deg: f32,
    /// 0x2003 sub 1: pitch \[deg\].
    pub pitch_deg: f32,
    /// 0x2003 sub 2: yaw \[deg\].
    pub yaw_deg: f32,
    /// 0x2004 sub 1-4: distances \[mm\] as converted from each channel.
    pub distances_mm: [f32; 4],
    /// 0x2005: status word ([`crate::status`]).
    pub status: u32,
    /// 0x2006: plane RMS residual \[mm\].
    pub rms_mm: f32,
}

impl Measurement {
    /// A sample with no data: every value 0, status `status`.
    pub fn invalid(status: u32) -> Self {
        Self {
            normal: [0.0; 3],
            theta1_deg: 0.0,
            theta2_deg: 0.0,
            theta_deg: 0.0,
            pitch_deg: 0.0,
            yaw_deg: 0.0,
            distances_mm: [0.0; 4],
            status,
            rms_mm: 0.0,
        }
    }

    /// From a core measurement (angles converted to degrees), the corrected
    /// distances and the status word.
    pub fn from_core<T: Real>(
        m: &perpend_core::normal::Measurement<T>,
        distances_mm: [f32; 4],
        status: u32,
    ) -> Self {
        let f = |x: T| x.to_f64() as f32;
        let deg = |x: T| x.to_f64().to_degrees() as f32;
        Self {
            normal: [
                f(m.plane.normal.x),
                f(m.plane.normal.y),
                f(m.plane.normal.z),
            ],
            theta1_deg: deg(m.deviation.theta1),
            theta2_deg: deg(m.deviation.theta2),
            theta_deg: deg(m.deviation.theta),
            pitch_deg: deg(m.attitude.pitch),
            yaw_deg: deg(m.attitude.yaw),
            distances_mm,
            status,
            rms_mm: f(m.plane.rms),
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn build_time_identity() {
        assert_eq!(parse_u32(b"0xAFFF_5050"), Some(0xAFFF_5050));
        assert_eq!(parse_u32(b"1234"), Some(1234));
        assert_eq!(parse_u32(b"0x1_0000_0000"), None);
        assert_eq!(parse_u32(b"0x"), None);
        assert_eq!(parse_u32(b"12a"), None);
        assert_ne!(VENDOR_ID, 0);
        let d = Defaults::nominal().with_serial(0x1234_5678);
        assert_eq!(d.identity.serial, 0x1234_5678);
        assert_eq!(d.identity.vendor_id, VENDOR_ID);
        assert_eq!(d.device_type, DEVICE_TYPE);
        // every UID byte matters
        let a = serial_from_uid(&[0; 12]);
        for i in 0..12 {
            let mut u = [0u8; 12];
            u[i] = 1;
            assert_ne!(serial_from_uid(&u), a);
        }
    }

    #[test]
    fn calibration_array_round_trip() {
        let a: [f32; CAL_VALUES] = core::array::from_fn(|i| i as f32 * 1.5 - 3.0);
        let c = SensorCalibration::from_array(&a);
        assert_eq!(c.to_array(), a);
        // sub 16..20 are the knots, 21..23 the coefficients
        assert_eq!(c.knots[0], a[CAL_SUB_KNOTS as usize - 1]);
        assert_eq!(c.coeffs[0], a[CAL_SUB_COEFFS as usize - 1]);
        assert_eq!(c.coeffs[TABLE_COEFFS - 1], a[CAL_SUB_SPOT as usize - 2]);
        // sub 24..25 the spot coefficients, the last values
        assert_eq!(c.spot, [a[CAL_VALUES - 2], a[CAL_VALUES - 1]]);
        assert_eq!(CAL_SUB_SPOT as usize + 1, CAL_VALUES);
    }

    fn table_sensor() -> Sensor<f64> {
        let mut s = Params::factory().head.sensors[2].cast::<f64>();
        s.ext.d_ref = 45.0;
        s.ext.table = LinTable {
            knots: [-6.0, -3.0, 0.0, 2.0, 6.0],
            coeffs: [1e-3, -2e-3, 1.5e-3],
        };
        s
    }

    /// The table goes from a core sensor through the object values and
    /// back unchanged (values exact in `f32`).
    #[test]
    fn table_round_trips_through_the_calibration() {
        let s = table_sensor();
        let c = SensorCalibration::from_sensor(&s);
        assert_eq!(c.knots, [-6.0, -3.0, 0.0, 2.0, 6.0]);
        let back = c.to_sensor::<f64>().unwrap();
        let tol = |a: f64, b: f64| (a - b).abs() <= 1e-9 * b.abs().max(1.0);
        assert_eq!(back.ext.table.knots, s.ext.table.knots);
        for (a, b) in back.ext.table.coeffs.iter().zip(s.ext.table.coeffs) {
            assert!(tol(*a, b), "{a} {b}");
        }
        // the correction the board applies is the core's, within f32
        let ctx = perpend_core::ext::Context::default();
        let want = s.ext.correct(47.0, None, 1.0, &ctx);
        let got = c.extension::<f64>().correct(47.0, None, 1.0, &ctx);
        assert_relative_eq!(got, want, epsilon = 1e-6);
        assert!(got != 47.0);
    }

    /// An active table with knots not strictly ascending is refused; the
    /// same knots without coefficients are ignored.
    #[test]
    fn bad_table_is_refused_only_when_active() {
        let mut c = SensorCalibration::from_sensor(&table_sensor());
        c.knots[3] = c.knots[2];
        assert!(!c.table_valid());
        assert_eq!(
            c.to_sensor::<f32>().unwrap_err(),
            perpend_core::Error::OutOfRange("linearity table knots")
        );
        c.knots = [0.0; TABLE_KNOTS];
        c.knots[1] = f32::NAN;
        assert!(c.to_sensor::<f32>().is_err());
        c.coeffs = [0.0; TABLE_COEFFS];
        assert!(c.table_valid());
        assert!(!c.to_sensor::<f32>().unwrap().ext.table.is_active());
    }

    #[test]
    fn nominal_head_matches_cone() {
        let d = Defaults::nominal();
        let s1 = d.calibration[1].to_sensor::<f64>().unwrap();
        assert_relative_eq!(s1.zero.y, 50.0, epsilon = 1e-5);
        assert_relative_eq!(s1.dir.z, 30f64.to_radians().cos(), epsilon = 1e-6);
        assert_eq!(d.calibration[0].temp_ref, 20.0);
    }

    #[test]
    fn params_round_trip_through_the_typed_views() {
        let mut p = Params::factory();
        p.transfer[2] = Transfer::voltage(0.25, 10.0, 60.0);
        p.acq.os_log2 = 6;
        p.acq.os_shift = 2;
        p.acq.method = Method::Chen;
        p.can.bitrate = Bitrate::K250;
        p.thermal_tau_s = 45.5;
        let d = Defaults::from_params(&p);
        assert_eq!(d.thermal_tau_s, 45.5);
        assert_eq!(Defaults::nominal().thermal_tau_s, 0.0);
        assert_eq!(d.acquisition.oversampling, 64);
        assert_eq!(d.acquisition.method, METHOD_CHEN);
        assert_eq!(d.bit_rate_kbps, 250);
        assert_eq!(d.transfer[2].kind, TF_VOLTAGE_0_10V);
        let back: [Transfer; 4] =
            core::array::from_fn(|i| d.transfer[i].to_transfer(&p.transfer[i]));
        assert_eq!(back, p.transfer);
        assert_eq!(d.acquisition.to_params(&p.acq), p.acq);
        // oversampling beyond the shift window raises the shift
        let a = Acquisition {
            oversampling: 256,
            ..d.acquisition
        }
        .to_params(&p.acq);
        assert_eq!((a.os_log2, a.os_shift), (8, 4));
        assert!(a.validate().is_ok());
        for (c, s) in d.calibration.iter().zip(p.head.sensors.iter()) {
            assert_eq!(c.to_sensor::<f32>().unwrap().zero, s.zero);
        }
        assert_eq!(bitrate_of(kbps_of(Bitrate::M1)), Some(Bitrate::M1));
        assert_eq!(bitrate_of(300), None);
    }
}
