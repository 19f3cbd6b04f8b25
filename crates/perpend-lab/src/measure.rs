//! `perpend measure`: for every row of a readings file, the surface normal
//! where the spindle axis meets the surface, Tian's θ1/θ2/θ (eq. 1-5),
//! Chen's pitch/yaw (eq. 22) and the fit residual, computed by the same
//! `perpend-core` code the board runs (`perpend-board`'s pipeline, from the
//! millimetres on): readings → spots with the calibrated head and its
//! extension corrections (Chen eq. 17, the row's temperature as context; no
//! time, as on the board: drift is never extrapolated) → micro-plane (least squares or Chen eq. 18-19) → with
//! `--surface sphere:R|cylinder:R:ax,ay,az` the curved model of
//! [`perpend_core::surface`] (issue 14) → angles.
//!
//! The readings file has the columns of `poses.csv`
//! ([`crate::exchange::parse_readings`]): the plane columns may be absent
//! and are ignored. A row the core cannot measure (fewer than three
//! readings, degenerate spots, an axis that misses the fitted surface) is
//! reported with its file, line and reason, and the others are measured;
//! a file of which no row can be measured is an error. The host computes
//! in `f64`; the board's `f32` agrees to < 0.001° (tested).

use std::fmt::Write as _;
use std::path::PathBuf;
use std::str::FromStr;

use anyhow::{anyhow, Result};
use nalgebra::Vector3;
use perpend_core::head::{Head, Sensor};
use perpend_core::normal::Method;
use perpend_core::surface::{measure, Shape, SurfaceMeasurement};
use serde::Serialize;

use crate::exchange::{read_readings, read_sensors, ExchangeError, ReadingRow, ReadingTable};
use crate::paramfile::ParamFile;

/// The nominal shape of the surface, as given on the command line:
/// `plane`, `sphere:R` or `cylinder:R:ax,ay,az` (R in mm, negative for a
/// concave surface; the cylinder's axis direction in the TCS).
#[derive(Debug, Clone, PartialEq)]
pub struct SurfaceSpec(pub Shape<f64>);

impl FromStr for SurfaceSpec {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let num = |x: &str, what: &str| -> std::result::Result<f64, String> {
            let v: f64 = x
                .trim()
                .parse()
                .map_err(|_| format!("{what} '{x}' is not a number"))?;
            if v.is_finite() {
                Ok(v)
            } else {
                Err(format!("{what} must be finite, got {x}"))
            }
        };
        let radius = |x: &str| -> std::result::Result<f64, String> {
            let r = num(x, "radius")?;
            if r == 0.0 {
                return Err("radius must not be 0 (use `plane`)".into());
            }
            Ok(r)
        };
        let parts: Vec<&str> = s.trim().split(':').collect();
        let shape = match parts.as_slice() {
            ["plane"] => Shape::Plane,
            ["sphere", r] => Shape::Sphere {
                radius: radius(r)?,
            },
            ["cylinder", r, axis] => {
                let c: Vec<&str> = axis.split(',').collect();
                let [x, y, z] = c.as_slice() else {
                    return Err(format!("cylinder axis '{axis}' must be ax,ay,az"));
                };
                let a = Vector3::new(num(x, "axis")?, num(y, "axis")?, num(z, "axis")?);
                if a.norm() < 1e-9 {
                    return Err("cylinder axis has zero length".into());
                }
                Shape::Cylinder {
                    radius: radius(r)?,
                    axis: a,
                }
            }
            _ => {
                return Err(format!(
                    "'{s}': expected plane, sphere:R or cylinder:R:ax,ay,az (R in mm, negative = concave)"
                ))
            }
        };
        Ok(Self(shape))
    }
}

impl std::fmt::Display for SurfaceSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.0 {
            Shape::Plane => write!(f, "plane"),
            Shape::Sphere { radius } => write!(f, "sphere:{radius}"),
            Shape::Cylinder { radius, axis } => {
                write!(f, "cylinder:{radius}:{},{},{}", axis.x, axis.y, axis.z)
            }
        }
    }
}

/// The micro-plane method.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlaneMethod {
    /// Total least squares (the board's default).
    Lsq,
    /// Chen eq. 18-19 (averaged cross products).
    Chen,
}

impl From<PlaneMethod> for Method {
    fn from(m: PlaneMethod) -> Self {
        match m {
            PlaneMethod::Lsq => Method::LeastSquares,
            PlaneMethod::Chen => Method::Chen,
        }
    }
}

/// Arguments of `perpend measure`.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// The nominal head (sensors.csv): the number of sensors, and the head
    /// itself when no --params is given.
    #[arg(long)]
    pub sensors: PathBuf,
    /// The calibrated head (params.json of `perpend calibrate --out`), with
    /// its extension coefficients.
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// The readings (poses.csv columns: pose, d1_mm..dN_mm, optional t_s,
    /// temp_c; the plane columns a, b, c, d_mm may be absent and are ignored).
    #[arg(long)]
    pub poses: PathBuf,
    /// Nominal shape of the surface: plane, sphere:R or cylinder:R:ax,ay,az
    /// (R in mm, positive convex, negative concave; the cylinder's axis
    /// direction in the TCS).
    #[arg(long, default_value = "plane", allow_hyphen_values = true)]
    pub surface: SurfaceSpec,
    /// Micro-plane method.
    #[arg(long, value_enum, default_value_t = PlaneMethod::Lsq)]
    pub method: PlaneMethod,
    /// Print one JSON object {file, head, surface, method, rows, measured, skipped}.
    #[arg(long)]
    pub json: bool,
}

/// The numbers of one measured row.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Measured {
    /// Sensors used (1-based).
    pub used: Vec<usize>,
    /// Fewer sensors than the head has.
    pub degraded: bool,
    /// Unit normal towards the head, where the spindle axis meets the surface.
    pub normal: [f64; 3],
    /// That point [mm, TCS].
    pub point_mm: [f64; 3],
    /// Tian θ1 [deg].
    pub theta1_deg: f64,
    /// Tian θ2 [deg].
    pub theta2_deg: f64,
    /// Tian θ [deg].
    pub theta_deg: f64,
    /// Chen pitch (about TCS x) [deg].
    pub pitch_deg: f64,
    /// Chen yaw (about TCS y) [deg].
    pub yaw_deg: f64,
    /// RMS orthogonal residual of the spots from the fitted surface [mm].
    pub rms_mm: f64,
    /// RMS residual of the micro-plane [mm] (equal to `rms_mm` for a plane).
    pub plane_rms_mm: f64,
    /// Gauss-Newton iterations of the curved fit (0 for a plane).
    pub iterations: usize,
}

impl Measured {
    fn of<const N: usize>(m: &SurfaceMeasurement<f64>) -> Self {
        let f = &m.fit;
        Self {
            used: (0..N)
                .filter(|i| f.plane.used & (1 << i) != 0)
                .map(|i| i + 1)
                .collect(),
            degraded: f.plane.degraded,
            normal: f.normal.into(),
            point_mm: f.point.into(),
            theta1_deg: m.deviation.theta1.to_degrees(),
            theta2_deg: m.deviation.theta2.to_degrees(),
            theta_deg: m.deviation.theta.to_degrees(),
            pitch_deg: m.attitude.pitch.to_degrees(),
            yaw_deg: m.attitude.yaw.to_degrees(),
            rms_mm: f.rms,
            plane_rms_mm: f.plane.rms,
            iterations: f.iterations,
        }
    }
}

/// One row of the output: the numbers, or why the row was not measured.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RowOut {
    /// Pose number.
    pub pose: i64,
    /// Line in the readings file.
    pub line: u64,
    /// The measurement (absent when `error` is set).
    #[serde(flatten)]
    pub measured: Option<Measured>,
    /// Why the row could not be measured.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

fn measure_n<const N: usize>(
    sensors: &[Sensor<f64>],
    table: &ReadingTable,
    shape: &Shape<f64>,
    method: Method,
) -> Result<Vec<RowOut>> {
    let arr: [Sensor<f64>; N] = sensors
        .to_vec()
        .try_into()
        .map_err(|_| anyhow!("internal: head of {} sensors, expected {N}", sensors.len()))?;
    let head = Head::new(arr);
    let one = |row: &ReadingRow| {
        let r: [Option<f64>; N] = core::array::from_fn(|i| row.readings.get(i).copied().flatten());
        // As on the board: the row's temperature, no time (drift is never
        // extrapolated, `SensorParams::fold_drift`).
        let ctx = perpend_core::ext::Context {
            t_s: None,
            ..row.context()
        };
        let m = measure(&head, &r, &ctx, method, shape);
        RowOut {
            pose: row.pose,
            line: row.line,
            measured: m.as_ref().ok().map(Measured::of::<N>),
            error: m.err().map(|e| e.to_string()),
        }
    };
    Ok(table.rows.iter().map(one).collect())
}

/// Measures every row of `table` with `sensors` (3 to 8 of them).
///
/// # Errors
/// A head of another size.
pub fn measure_table(
    sensors: &[Sensor<f64>],
    table: &ReadingTable,
    shape: &Shape<f64>,
    method: Method,
) -> Result<Vec<RowOut>> {
    match sensors.len() {
        3 => measure_n::<3>(sensors, table, shape, method),
        4 => measure_n::<4>(sensors, table, shape, method),
        5 => measure_n::<5>(sensors, table, shape, method),
        6 => measure_n::<6>(sensors, table, shape, method),
        7 => measure_n::<7>(sensors, table, shape, method),
        8 => measure_n::<8>(sensors, table, shape, method),
        n => Err(anyhow!(
            "measure handles heads of 3 to 8 sensors, this one has {n}"
        )),
    }
}

/// The head: the calibration when given (its sensor count must match
/// sensors.csv), else the nominal head; and its label.
fn head(a: &Args) -> Result<(Vec<Sensor<f64>>, String)> {
    let table = read_sensors(&a.sensors)?;
    let Some(p) = &a.params else {
        let nominal = table
            .sensors()
            .map_err(|e| anyhow!("{}: {e}", a.sensors.display()))?;
        return Ok((nominal, "nominal (sensors.csv, uncalibrated)".into()));
    };
    let f = ParamFile::read(p)?;
    if f.sensors.len() != table.len() {
        return Err(anyhow!(
            "{}: {} sensors, but {} has {}",
            p.display(),
            f.sensors.len(),
            a.sensors.display(),
            table.len()
        ));
    }
    let sensors = f.sensors().map_err(|e| anyhow!("{}: {e}", p.display()))?;
    Ok((
        sensors,
        format!("{} ({}, {})", p.display(), f.method, f.model),
    ))
}

/// Runs `perpend measure`.
///
/// # Errors
/// Malformed files (with file and line), a head of an unsupported size, a
/// file of which no row can be measured.
pub fn run(a: &Args) -> Result<()> {
    let (sensors, label) = head(a)?;
    let table = read_readings(&a.poses, Some(sensors.len()))?;
    let rows = measure_table(&sensors, &table, &a.surface.0, a.method.into())?;
    let file = a.poses.display().to_string();
    let measured = rows.iter().filter(|r| r.measured.is_some()).count();
    if measured == 0 {
        let first = rows
            .first()
            .and_then(|r| r.error.clone())
            .unwrap_or_default();
        return Err(ExchangeError {
            file,
            line: rows.first().map(|r| r.line),
            problem: format!("no pose could be measured ({first})"),
        }
        .into());
    }
    if a.json {
        let method = format!("{:?}", a.method).to_lowercase();
        let v = serde_json::json!({
            "file": file, "head": label, "surface": a.surface.to_string(),
            "method": method, "rows": rows, "measured": measured,
            "skipped": rows.len() - measured,
        });
        println!("{v}");
        return Ok(());
    }
    print!("{}", report(a, &label, &rows));
    for r in rows.iter().filter(|r| r.error.is_some()) {
        eprintln!(
            "warning: {file}, line {}: pose {} skipped: {}",
            r.line,
            r.pose,
            r.error.as_deref().unwrap_or("")
        );
    }
    Ok(())
}

fn report(a: &Args, label: &str, rows: &[RowOut]) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{}: {} rows; head {label}; surface {}; micro-plane {}",
        a.poses.display(),
        rows.len(),
        a.surface,
        format!("{:?}", a.method).to_lowercase()
    );
    let _ = writeln!(
        out,
        "normal towards the head where the spindle axis meets the surface; θ1 about x, θ2 about y (Tian eq. 1-5), pitch/yaw (Chen eq. 22)"
    );
    let _ = writeln!(
        out,
        " pose  sensors    θ1 [°]    θ2 [°]     θ [°]  pitch [°]   yaw [°]  rms [mm]        n_x        n_y        n_z"
    );
    for r in rows {
        let Some(m) = &r.measured else {
            let _ = writeln!(
                out,
                "{:>5}  skipped: {}",
                r.pose,
                r.error.as_deref().unwrap_or("")
            );
            continue;
        };
        let used: String = m.used.iter().map(|i| i.to_string()).collect();
        let _ = writeln!(
            out,
            "{:>5}  {:<7}  {:>8.4}  {:>8.4}  {:>8.4}  {:>9.4}  {:>8.4}  {:>8.4}  {:>9.6}  {:>9.6}  {:>9.6}",
            r.pose,
            used,
            m.theta1_deg,
            m.theta2_deg,
            m.theta_deg,
            m.pitch_deg,
            m.yaw_deg,
            m.rms_mm,
            m.normal[0],
            m.normal[1],
            m.normal[2]
        );
    }
    out
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn surface_specs_parse_and_print() {
        for (text, want) in [
            ("plane", Shape::Plane),
            ("sphere:500", Shape::Sphere { radius: 500.0 }),
            ("sphere:-1200.5", Shape::Sphere { radius: -1200.5 }),
            (
                "cylinder:800:1,0,0.1",
                Shape::Cylinder {
                    radius: 800.0,
                    axis: Vector3::new(1.0, 0.0, 0.1),
                },
            ),
        ] {
            let s: SurfaceSpec = text.parse().unwrap();
            assert_eq!(s.0, want);
            assert_eq!(s.to_string().parse::<SurfaceSpec>().unwrap(), s);
        }
        for (bad, msg) in [
            ("sphere", "expected plane"),
            ("sphere:0", "must not be 0"),
            ("sphere:abc", "not a number"),
            ("sphere:inf", "finite"),
            ("cylinder:500", "expected plane"),
            ("cylinder:500:1,0", "ax,ay,az"),
            ("cylinder:500:0,0,0", "zero length"),
            ("torus:5", "expected plane"),
        ] {
            let e = bad.parse::<SurfaceSpec>().unwrap_err();
            assert!(e.contains(msg), "{bad}: {e}");
        }
    }

    #[test]
    fn rows_that_cannot_be_measured_say_why() {
        let head = perpend_core::head::Head4::cone(45.0, 25f64.to_radians(), 0.0, 0.0).unwrap();
        let row = |pose, readings: Vec<Option<f64>>| ReadingRow {
            line: pose as u64 + 1,
            pose,
            readings,
            t_s: None,
            temp_c: None,
        };
        let table = ReadingTable {
            n_sensors: 4,
            rows: vec![
                row(1, vec![Some(66.0), Some(66.0), Some(66.0), Some(66.0)]),
                row(2, vec![Some(66.0), None, Some(66.0), None]),
            ],
        };
        let shape = Shape::Sphere { radius: 500.0 };
        let out = measure_table(&head.sensors, &table, &shape, Method::LeastSquares).unwrap();
        let m = out[0].measured.as_ref().unwrap();
        assert_eq!(m.used, vec![1, 2, 3, 4]);
        assert!(m.theta_deg < 1e-9);
        assert_eq!(out[1].measured, None);
        assert_eq!(
            out[1].error.as_deref(),
            Some("2 valid readings; a plane needs at least 3")
        );
        let v = serde_json::to_value(&out[1]).unwrap();
        assert_eq!(v["line"], 3);
        assert!(v.get("normal").is_none());
        assert!(measure_table(&head.sensors[..2], &table, &shape, Method::Chen).is_err());
    }
}
