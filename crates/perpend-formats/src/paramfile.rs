//! The calibration parameter file (JSON): what `perpend calibrate --out`
//! writes and what the board's stored parameter record is built from.
//!
//! Per sensor: the calibrated zero point `E_i` [mm, TCS], the unit beam
//! direction `u_i`, the extension coefficients of
//! [`perpend_core::ext::Extension`] (all zero for the paper's model), the
//! correction relative to the nominal head (Chen's `Δx … Δq`), the 1σ of the
//! zero point and direction components, the residual RMS, the number of
//! readings and the identifiability verdict.
//!
//! ```json
//! { "format": "perpend-calibration", "version": 1, "method": "lsq",
//!   "model": "base", "poses": 100,
//!   "sensors": [ { "sensor": 1, "zero_mm": [..], "dir": [..],
//!                  "ext": { "d_ref_mm": 0, "gain": 0, ...,
//!                           "linearity_table": { "knots_mm": [..5], "values_mm": [..3] } },
//!                  "correction": { "zero_mm": [..], "dir": [..] },
//!                  "sigma": { "zero_mm": [..], "dir": [..] },
//!                  "residual_rms_mm": 0.012, "readings": 100,
//!                  "identifiability": { "status": "ok", ... } } ] }
//! ```
//!
//! Optionally, per sensor, the analog transfer function the board holds in
//! 0x2201..0x2204 (`perpend node pull` writes it, `perpend node push`
//! writes it back; `calibrate` does not produce it):
//! `"transfer": { "kind": "4-20mA", "scale": 100.0, "mm_at_low": 30.0,
//! "mm_at_high": 70.0 }` (kind `4-20mA` on a shunt of `scale` Ω, or
//! `0-10V` through a divider of ratio `scale`; the distances at 4 mA / 0 V
//! and at 20 mA / 10 V).
//!
//! `thermal_tau_s` (top level, seconds): the head's thermal time
//! constant: the thermal extension of every sensor is applied to the head
//! temperature passed through a first-order lag of this time constant
//! ([`perpend_core::lag`]; the board's object 0x2105,
//! `perpend_core::params::Params::thermal_tau_s`). 0..=86400; absent means
//! 0, no lag, and a file without lag is written without it, so files read
//! and write as before.
//!
//! `calibration_stamp` (top level, optional, written by `perpend node
//! pull`): the board's calibration stamp 0x2011 when the file was pulled,
//! `{"record_hash": "a1b2c3d4", "utc": "2026-11-27T10:58:43Z", "utc_s":
//! 1795777123, "store_count": 3}` (the first 4 bytes of the SHA-256 of the
//! pushed record, the push's UTC time, the board's store count). It only
//! says where the values came from: push ignores it (it stamps the board
//! with the file it pushes), so a pulled file pushes again.
//!
//! `spot_mm` (in `ext`, two numbers [mm]: the spot bias of the incidence
//! correction per unit of `tan²γ·cos φ` and `tan²γ·sin φ`,
//! [`perpend_core::ext`], "Incidence") is present only when fitted; files
//! without it read as before (no spot terms).
//!
//! `linearity_table` (the natural-spline table of
//! [`perpend_core::ext::LinTable`], knots about `d_ref_mm`) is present only
//! when a table was fitted; files without it read as before.
//!
//! The reader ([`ParamFile::read`]) rejects anything else with a message
//! naming the file and the problem (serde's line/column for syntax and
//! type errors; the sensor and field for values out of range). Unknown
//! fields are errors, so a typo cannot silently drop a coefficient.

use std::path::Path;

use anyhow::{anyhow, bail, Context as _, Result};
use nalgebra::Vector3;
use perpend_core::ext::{Extension, LinTable, TABLE_COEFFS, TABLE_KNOTS};
use perpend_core::head::{Head, Sensor};
use serde::{Deserialize, Serialize};

/// Value of the `format` field.
pub const FORMAT: &str = "perpend-calibration";
/// Current `version`.
pub const VERSION: u32 = 1;
/// Largest `thermal_tau_s` \[s\] (the board's limit,
/// `perpend_core::params::THERMAL_TAU_MAX_S`).
pub const THERMAL_TAU_MAX_S: f64 = perpend_core::params::THERMAL_TAU_MAX_S as f64;

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

/// Refuses a `thermal_tau_s` the board would not hold: not finite, or
/// outside 0..=[`THERMAL_TAU_MAX_S`].
fn check_tau(tau: f64) -> Result<()> {
    if !(tau.is_finite() && (0.0..=THERMAL_TAU_MAX_S).contains(&tau)) {
        bail!(
            "thermal_tau_s = {tau}: the thermal time constant must be a number of seconds \
             in 0..={THERMAL_TAU_MAX_S} (0 = no lag)"
        );
    }
    Ok(())
}

/// Extension coefficients of one sensor (see [`perpend_core::ext`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExtParams {
    /// Reference distance of gain and linearity [mm].
    pub d_ref_mm: f64,
    /// Relative scale error [-].
    pub gain: f64,
    /// Quadratic and cubic linearity error [mm⁻¹, mm⁻²].
    pub nonlinearity: [f64; 2],
    /// Incidence bias [mm per unit of 1/cos γ − 1].
    pub incidence_mm: f64,
    /// Spot bias [mm per unit of tan²γ·cos φ and tan²γ·sin φ], φ the
    /// azimuth of the surface's tilt about the beam
    /// ([`perpend_core::ext`], "Incidence"), when fitted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spot_mm: Option<[f64; 2]>,
    /// Crosstalk fraction from the previously converted channel [-].
    pub crosstalk: f64,
    /// Thermal drift [mm/°C].
    pub thermal_mm_per_c: f64,
    /// Reference temperature [°C].
    pub temp_ref_c: f64,
    /// Drift with time [mm/s].
    pub drift_mm_per_s: f64,
    /// Linearity table, when one was fitted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub linearity_table: Option<TableParams>,
}

/// The linearity table of one sensor ([`perpend_core::ext::LinTable`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TableParams {
    /// Knots [mm] about `d_ref_mm`, strictly ascending.
    pub knots_mm: [f64; TABLE_KNOTS],
    /// Values [mm] of the spline at the interior knots (0 at the end knots).
    pub values_mm: [f64; TABLE_COEFFS],
}

impl From<&Extension<f64>> for ExtParams {
    fn from(e: &Extension<f64>) -> Self {
        Self {
            d_ref_mm: e.d_ref,
            gain: e.gain,
            nonlinearity: e.nonlinearity,
            incidence_mm: e.incidence,
            spot_mm: e.has_spot().then_some(e.spot),
            crosstalk: e.crosstalk,
            thermal_mm_per_c: e.thermal,
            temp_ref_c: e.temp_ref,
            drift_mm_per_s: e.drift,
            linearity_table: e.table.is_active().then_some(TableParams {
                knots_mm: e.table.knots,
                values_mm: e.table.coeffs,
            }),
        }
    }
}

impl From<&ExtParams> for Extension<f64> {
    fn from(p: &ExtParams) -> Self {
        Extension {
            d_ref: p.d_ref_mm,
            gain: p.gain,
            nonlinearity: p.nonlinearity,
            incidence: p.incidence_mm,
            spot: p.spot_mm.unwrap_or([0.0; 2]),
            crosstalk: p.crosstalk,
            thermal: p.thermal_mm_per_c,
            temp_ref: p.temp_ref_c,
            drift: p.drift_mm_per_s,
            table: p.linearity_table.map_or_else(LinTable::none, |t| LinTable {
                knots: t.knots_mm,
                coeffs: t.values_mm,
            }),
        }
    }
}

/// A zero point and direction triple (corrections or their 1σ).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Triples {
    /// x, y, z [mm].
    pub zero_mm: [f64; 3],
    /// m, n, q [-].
    pub dir: [f64; 3],
}

/// Identifiability verdict of one sensor's pose set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Identifiability {
    /// `ok`, `weak` or `not-identifiable`.
    pub status: String,
    /// Condition number of the column-scaled normal matrix.
    pub condition: f64,
    /// Tilt range of the plane normals about x [deg].
    pub tilt_x_range_deg: f64,
    /// Same about y [deg].
    pub tilt_y_range_deg: f64,
    /// Range of the sensor's readings [mm].
    pub standoff_range_mm: f64,
    /// The verdict in words.
    pub message: String,
}

impl From<&perpend_core::calib::Diagnostic<f64>> for Identifiability {
    fn from(d: &perpend_core::calib::Diagnostic<f64>) -> Self {
        Self {
            status: d.status.name().into(),
            condition: d.condition,
            tilt_x_range_deg: d.tilt_x_range_deg,
            tilt_y_range_deg: d.tilt_y_range_deg,
            standoff_range_mm: d.standoff_range_mm,
            message: d.to_string(),
        }
    }
}

/// Transfer-function kind: 4-20 mA on a shunt.
pub const TRANSFER_CURRENT: &str = "4-20mA";
/// Transfer-function kind: 0-10 V through a divider.
pub const TRANSFER_VOLTAGE: &str = "0-10V";

/// The analog transfer function of one channel (the board's 0x2201..).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransferParams {
    /// [`TRANSFER_CURRENT`] or [`TRANSFER_VOLTAGE`].
    pub kind: String,
    /// Shunt resistance [Ω] (4-20 mA) or divider ratio (0-10 V).
    pub scale: f64,
    /// Distance at 4 mA / 0 V [mm].
    pub mm_at_low: f64,
    /// Distance at 20 mA / 10 V [mm].
    pub mm_at_high: f64,
}

/// Calibrated parameters of one sensor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorParams {
    /// 1-based sensor number (ADC scan order).
    pub sensor: usize,
    /// Zero point `E_i` [mm, TCS].
    pub zero_mm: [f64; 3],
    /// Unit beam direction `u_i`.
    pub dir: [f64; 3],
    /// Extension coefficients.
    pub ext: ExtParams,
    /// Correction relative to the nominal head: `Δx, Δy, Δz` and
    /// `Δm, Δn, Δq` of the unit directions (Chen Table 2/6 layout).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub correction: Option<Triples>,
    /// 1σ of the zero point and direction components.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma: Option<Triples>,
    /// 1σ of the extension coefficients, in the order of `model`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sigma_ext: Vec<f64>,
    /// Residual RMS of the fit [mm].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub residual_rms_mm: Option<f64>,
    /// Readings the estimate used (for the EKF: until its stop).
    #[serde(default)]
    pub readings: usize,
    /// Identifiability of the pose set (least squares only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub identifiability: Option<Identifiability>,
    /// The channel's analog transfer function, when known (read from a
    /// board by `perpend node pull`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transfer: Option<TransferParams>,
}

impl SensorParams {
    /// Checks one sensor's entry: finite geometry and extension, a unit
    /// direction, ascending table knots, non-negative 1σ and residual, a
    /// known transfer kind.
    ///
    /// # Errors
    /// A message naming the sensor and the field.
    fn validate(&self) -> Result<()> {
        let (s, id) = (self, self.sensor);
        let finite = |v: &[f64], what: &str| -> Result<()> {
            if v.iter().all(|x| x.is_finite()) {
                Ok(())
            } else {
                bail!("sensor {id}: {what} must be finite numbers")
            }
        };
        finite(&s.zero_mm, "zero_mm")?;
        finite(&s.dir, "dir")?;
        let e = &s.ext;
        finite(
            &[
                e.d_ref_mm,
                e.gain,
                e.nonlinearity[0],
                e.nonlinearity[1],
                e.incidence_mm,
                e.crosstalk,
                e.thermal_mm_per_c,
                e.temp_ref_c,
                e.drift_mm_per_s,
            ],
            "ext",
        )?;
        if let Some(spot) = &e.spot_mm {
            finite(spot, "ext.spot_mm")?;
            let max = f64::from(perpend_core::params::SPOT_MAX_MM);
            if spot.iter().any(|c| c.abs() > max) {
                bail!(
                    "sensor {id}: ext.spot_mm {spot:?} exceeds ±{max} mm per unit of tan²γ \
                     (the board's bound): no sensor has such a spot bias; refit the run"
                );
            }
        }
        if let Some(t) = &e.linearity_table {
            finite(&t.knots_mm, "linearity_table.knots_mm")?;
            finite(&t.values_mm, "linearity_table.values_mm")?;
            let table = LinTable {
                knots: t.knots_mm,
                coeffs: t.values_mm,
            };
            if !table.knots_valid() {
                bail!("sensor {id}: linearity_table.knots_mm must be strictly ascending");
            }
        }
        let len = Vector3::from(s.dir).norm();
        if (len - 1.0).abs() > 1e-6 {
            bail!("sensor {id}: dir has length {len}, expected a unit vector");
        }
        if let Some(sig) = &s.sigma {
            if !sig
                .zero_mm
                .iter()
                .chain(sig.dir.iter())
                .all(|x| x.is_finite() && *x >= 0.0)
            {
                bail!("sensor {id}: sigma must be non-negative finite numbers");
            }
        }
        if let Some(t) = &s.transfer {
            if t.kind != TRANSFER_CURRENT && t.kind != TRANSFER_VOLTAGE {
                bail!(
                    "sensor {id}: transfer kind '{}' is neither '{TRANSFER_CURRENT}' nor \
                 '{TRANSFER_VOLTAGE}'",
                    t.kind
                );
            }
            finite(&[t.scale, t.mm_at_low, t.mm_at_high], "transfer")?;
        }
        if let Some(r) = s.residual_rms_mm {
            if !(r.is_finite() && r >= 0.0) {
                bail!("sensor {id}: residual_rms_mm must be a non-negative number");
            }
        }
        Ok(())
    }

    /// Drift is a nuisance of the calibration run (issue 11 item 8): it
    /// is estimated so that it does not bias the zero point and beam, but
    /// never extrapolated; the board has no clock shared with the run, and
    /// a linear drift carried on for hours would grow without bound. This
    /// refers the parameters to the **end** of the run: the reading excess
    /// `c = drift·t_end` is folded into the zero point (a constant excess
    /// `c` along the unit beam `u` is the zero point moved by `−c·u`) and
    /// the drift coefficient becomes 0. Returns `c` \[mm\]. In use, drift
    /// after the run is not corrected; `perpend diagnose` on a later run
    /// shows whether it goes on.
    pub fn fold_drift(&mut self, t_end_s: f64) -> f64 {
        let c = self.ext.drift_mm_per_s * t_end_s;
        let n = self.dir.iter().map(|v| v * v).sum::<f64>().sqrt();
        if n > 0.0 {
            for (z, u) in self.zero_mm.iter_mut().zip(self.dir) {
                *z -= c * u / n;
            }
        }
        self.ext.drift_mm_per_s = 0.0;
        c
    }

    /// The sensor with its extension.
    ///
    /// # Errors
    /// Zero or non-finite direction / zero point.
    pub fn to_sensor(&self) -> Result<Sensor<f64>> {
        let mut s = Sensor::new(Vector3::from(self.zero_mm), Vector3::from(self.dir))
            .map_err(|e| anyhow!("sensor {}: {e}", self.sensor))?;
        s.ext = Extension::from(&self.ext);
        Ok(s)
    }

    /// Parameters of `s` (numbered `sensor`), with the correction relative
    /// to `nominal` when given.
    pub fn from_sensor(sensor: usize, s: &Sensor<f64>, nominal: Option<&Sensor<f64>>) -> Self {
        Self {
            sensor,
            zero_mm: s.zero.into(),
            dir: s.dir.into(),
            ext: ExtParams::from(&s.ext),
            correction: nominal.map(|n| Triples {
                zero_mm: (s.zero - n.zero).into(),
                dir: (s.dir - n.dir).into(),
            }),
            sigma: None,
            sigma_ext: Vec::new(),
            residual_rms_mm: None,
            readings: 0,
            identifiability: None,
            transfer: None,
        }
    }
}

/// The board's calibration stamp (0x2011) as `perpend node pull` found it
/// (module docs); informational, ignored by push.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationStamp {
    /// The first 4 bytes of the pushed record's SHA-256, 8 hex digits.
    pub record_hash: String,
    /// `utc_s` in ISO 8601 (`2026-11-27T10:58:43Z`).
    pub utc: String,
    /// UTC seconds since 1970 of the push.
    pub utc_s: u32,
    /// The board's count of calibration stores.
    pub store_count: u32,
}

/// The whole parameter file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParamFile {
    /// Always [`FORMAT`].
    pub format: String,
    /// Always [`VERSION`].
    pub version: u32,
    /// `lsq`, `ekf`, `truth` (simulator) or `nominal`.
    pub method: String,
    /// `base` (the paper's model) or the extension terms fitted, joined by
    /// `+` (e.g. `gain`).
    pub model: String,
    /// Poses of the calibration run.
    #[serde(default)]
    pub poses: usize,
    /// The head's thermal time constant \[s\] (0 = no lag; module docs).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub thermal_tau_s: f64,
    /// Sensors 1..N in order.
    pub sensors: Vec<SensorParams>,
    /// The board's calibration stamp when pulled (module docs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration_stamp: Option<CalibrationStamp>,
}

impl ParamFile {
    /// An empty file for `method` / `model`.
    pub fn new(method: &str, model: &str, poses: usize) -> Self {
        Self {
            format: FORMAT.into(),
            version: VERSION,
            method: method.into(),
            model: model.into(),
            poses,
            thermal_tau_s: 0.0,
            sensors: Vec::new(),
            calibration_stamp: None,
        }
    }

    /// The simulator's true head, with corrections relative to `nominal`.
    pub fn truth(truth: &[Sensor<f64>], nominal: &[Sensor<f64>]) -> Self {
        let mut f = Self::new("truth", "base", 0);
        f.sensors = truth
            .iter()
            .enumerate()
            .map(|(i, s)| SensorParams::from_sensor(i + 1, s, nominal.get(i)))
            .collect();
        f
    }

    /// Checks everything the firmware relies on.
    ///
    /// # Errors
    /// A message naming the sensor and the field.
    pub fn validate(&self) -> Result<()> {
        if self.format != FORMAT {
            bail!("format is '{}', expected '{FORMAT}'", self.format);
        }
        if self.version != VERSION {
            bail!(
                "version {} is not supported (expected {VERSION})",
                self.version
            );
        }
        check_tau(self.thermal_tau_s)?;
        if let Some(st) = &self.calibration_stamp {
            let h = &st.record_hash;
            if h.len() != 8 || !h.bytes().all(|b| b.is_ascii_hexdigit()) {
                bail!("calibration_stamp.record_hash '{h}' is not 8 hex digits");
            }
        }
        if self.sensors.is_empty() {
            bail!("no sensors");
        }
        for (i, s) in self.sensors.iter().enumerate() {
            let id = s.sensor;
            if id != i + 1 {
                bail!(
                    "sensors must be listed as 1..{} in order: entry {} is sensor {id}",
                    self.sensors.len(),
                    i + 1
                );
            }
            s.validate()?;
        }
        Ok(())
    }

    /// Parses and validates a parameter file; `name` labels errors.
    ///
    /// # Errors
    /// Syntax/type errors with line and column (physical lines whatever
    /// the line ending, see [`crate::exchange::json_text`]), or validation
    /// errors.
    pub fn parse(text: &str, name: &str) -> Result<Self> {
        let f: ParamFile = serde_json::from_str(&crate::exchange::json_text(text))
            .with_context(|| format!("{name}: malformed"))?;
        f.validate().with_context(|| format!("{name}: invalid"))?;
        Ok(f)
    }

    /// Reads and validates a parameter file.
    ///
    /// # Errors
    /// I/O, syntax and validation errors naming the file.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("{}: cannot read", path.display()))?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Writes the file (pretty JSON).
    ///
    /// # Errors
    /// I/O errors.
    pub fn write(&self, path: &Path) -> Result<()> {
        let text = serde_json::to_string_pretty(self)?;
        std::fs::write(path, text + "\n")
            .with_context(|| format!("cannot write {}", path.display()))
    }

    /// The sensors (with extensions), in order.
    ///
    /// # Errors
    /// Invalid directions.
    pub fn sensors(&self) -> Result<Vec<Sensor<f64>>> {
        self.sensors.iter().map(SensorParams::to_sensor).collect()
    }

    /// The head of `N` sensors.
    ///
    /// # Errors
    /// When the file has a different number of sensors, or invalid values.
    pub fn to_head<const N: usize>(&self) -> Result<Head<f64, N>> {
        self.validate()?;
        let v = self.sensors()?;
        let arr: [Sensor<f64>; N] = v.try_into().map_err(|v: Vec<Sensor<f64>>| {
            anyhow!("the file has {} sensors, the head needs {N}", v.len())
        })?;
        Ok(Head::new(arr))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn file() -> ParamFile {
        let head = perpend_core::head::Head4::cone(50.0, 0.5, 0.0, 0.0).unwrap();
        ParamFile::truth(&head.sensors, &head.sensors)
    }

    /// A file without `thermal_tau_s` reads as τ = 0 and is written
    /// without it (byte for byte as before); a τ round-trips.
    #[test]
    fn thermal_tau_is_optional_and_round_trips() {
        let f = file();
        let text = serde_json::to_string_pretty(&f).unwrap();
        assert!(!text.contains("thermal_tau_s"));
        let back = ParamFile::parse(&text, "p.json").unwrap();
        assert_eq!((back.thermal_tau_s, &back), (0.0, &f));
        let mut g = f.clone();
        g.thermal_tau_s = 612.5;
        let text = serde_json::to_string_pretty(&g).unwrap();
        assert!(text.contains("\"thermal_tau_s\": 612.5"), "{text}");
        assert_eq!(ParamFile::parse(&text, "p.json").unwrap(), g);
    }

    /// The optional calibration stamp: absent by default (files write as
    /// before), round-trips, a malformed hash is refused.
    #[test]
    fn calibration_stamp_is_optional_and_round_trips() {
        let f = file();
        assert!(!serde_json::to_string(&f)
            .unwrap()
            .contains("calibration_stamp"));
        let mut g = f.clone();
        g.calibration_stamp = Some(CalibrationStamp {
            record_hash: "a1b2c3d4".into(),
            utc: "2026-11-27T10:58:43Z".into(),
            utc_s: 1_795_777_123,
            store_count: 3,
        });
        let text = serde_json::to_string_pretty(&g).unwrap();
        assert!(text.contains("\"record_hash\": \"a1b2c3d4\""), "{text}");
        assert_eq!(ParamFile::parse(&text, "p.json").unwrap(), g);
        let bad = text.replace("a1b2c3d4", "a1b2c3d");
        let e = format!("{:#}", ParamFile::parse(&bad, "p.json").unwrap_err());
        assert!(e.contains("not 8 hex digits"), "{e}");
    }

    /// Out of range, negative or non-finite: refused with the file and the
    /// field named.
    #[test]
    fn thermal_tau_out_of_range_is_refused_naming_file_and_field() {
        for bad in ["-1", "86400.5", "1e300"] {
            let text = serde_json::to_string(&file()).unwrap().replacen(
                '{',
                &format!("{{\"thermal_tau_s\": {bad}, "),
                1,
            );
            let e = format!("{:#}", ParamFile::parse(&text, "cell/p.json").unwrap_err());
            assert!(
                e.contains("cell/p.json") && e.contains("thermal_tau_s"),
                "{e}"
            );
            assert!(e.contains("0..=86400"), "{e}");
        }
        let mut f = file();
        f.thermal_tau_s = f64::NAN;
        let e = f.validate().unwrap_err().to_string();
        assert!(e.contains("thermal_tau_s = NaN"), "{e}");
        f.thermal_tau_s = THERMAL_TAU_MAX_S;
        f.validate().unwrap();
    }

    /// The spot terms: absent by default (files write as before) and read
    /// as zero; fitted ones round-trip through the file to the extension;
    /// a non-finite or oversized value is refused naming the sensor.
    #[test]
    fn spot_terms_are_optional_and_round_trip() {
        let f = file();
        let text = serde_json::to_string_pretty(&f).unwrap();
        assert!(!text.contains("spot_mm"));
        let s = ParamFile::parse(&text, "p.json")
            .unwrap()
            .sensors()
            .unwrap();
        assert!(s.iter().all(|x| x.ext.spot == [0.0; 2]));
        let mut g = f.clone();
        g.sensors[2].ext.spot_mm = Some([0.125, -0.0625]);
        let text = serde_json::to_string_pretty(&g).unwrap();
        assert!(text.contains("\"spot_mm\""), "{text}");
        let back = ParamFile::parse(&text, "p.json").unwrap();
        assert_eq!(back, g);
        let ext = back.sensors().unwrap()[2].ext;
        assert_eq!(ext.spot, [0.125, -0.0625]);
        assert_eq!(ExtParams::from(&ext).spot_mm, Some([0.125, -0.0625]));
        let bad = text.replace("0.125", "12.5");
        let e = format!("{:#}", ParamFile::parse(&bad, "p.json").unwrap_err());
        assert!(e.contains("sensor 3") && e.contains("spot_mm"), "{e}");
        g.sensors[2].ext.spot_mm = Some([f64::NAN, 0.0]);
        let e = g.validate().unwrap_err().to_string();
        assert!(e.contains("spot_mm"), "{e}");
    }
}
