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
//! ([`perpend_formats::exchange::parse_readings`]): the plane columns may be absent
//! and are ignored. A row the core cannot measure (fewer than three
//! readings, degenerate spots, an axis that misses the fitted surface) is
//! reported with its file, line and reason, and the others are measured;
//! a file of which no row can be measured is an error. The host computes
//! in `f64`; the board's `f32` agrees to < 0.001° (tested).
//!
//! Thermal lag: when the params file has `thermal_tau_s` τ > 0, the
//! temperature each row's correction sees is the head temperature passed
//! through the first-order lag of τ ([`perpend_core::lag::filter`], from
//! rest at the earliest row) over the rows' `t_s`, taken in time order
//! (not file order; equal times keep file order), as the board lags its
//! thermometer ([`lag_temperatures`]). Every row then needs `t_s` and
//! `temp_c`; a file without either column, or a row without either value,
//! is refused naming the file, the line and the column.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::str::FromStr;

use anyhow::{anyhow, Result};
use nalgebra::Vector3;
use perpend_core::head::{Head, Sensor};
use perpend_core::normal::Method;
use perpend_core::surface::{measure, Shape, SurfaceMeasurement};
use serde::Serialize;

use perpend_formats::exchange::{
    read_readings, read_sensors, ExchangeError, ReadingRow, ReadingTable, SensorTable,
};
use perpend_formats::paramfile::ParamFile;

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
/// sensors.csv), else the nominal head; and its label. `tau_s` receives
/// the file's thermal time constant (left as it is without --params).
fn head(a: &Args, tau_s: &mut f64) -> Result<(Vec<Sensor<f64>>, String, SensorTable)> {
    let table = read_sensors(&a.sensors)?;
    let Some(p) = &a.params else {
        let nominal = table
            .sensors()
            .map_err(|e| anyhow!("{}: {e}", a.sensors.display()))?;
        return Ok((nominal, "nominal (sensors.csv, uncalibrated)".into(), table));
    };
    let f = ParamFile::read(p)?;
    *tau_s = f.thermal_tau_s;
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
        table,
    ))
}

/// `table` with each row's `temp_c` replaced by the head temperature
/// passed through the first-order lag of time constant `tau_s` \[s\]
/// ([`perpend_core::lag::filter`] over the rows sorted by `t_s`, from
/// rest at the earliest; the rows keep their order). `tau_s ≤ 0` returns
/// the table as it is. `file` labels errors.
///
/// # Errors
/// With `tau_s > 0`, a row without `t_s` or `temp_c` (file, line, the
/// missing column).
pub fn lag_temperatures(table: &ReadingTable, tau_s: f64, file: &str) -> Result<ReadingTable> {
    if !(tau_s > 0.0) {
        return Ok(table.clone());
    }
    let mut tu = Vec::with_capacity(table.rows.len());
    for r in &table.rows {
        let missing = match (r.t_s, r.temp_c) {
            (Some(t), Some(u)) => {
                tu.push((t, u));
                continue;
            }
            (None, _) => "t_s",
            (Some(_), None) => "temp_c",
        };
        return Err(ExchangeError {
            file: file.into(),
            line: Some(r.line),
            problem: format!(
                "pose {} has no {missing}: with a thermal time constant (thermal_tau_s = \
                 {tau_s} s in the params file) every row needs t_s and temp_c, the \
                 temperature is lagged over time",
                r.pose
            ),
        }
        .into());
    }
    let mut order: Vec<usize> = (0..tu.len()).collect();
    order.sort_by(|&i, &j| tu[i].0.total_cmp(&tu[j].0));
    let t: Vec<f64> = order.iter().map(|&i| tu[i].0).collect();
    let u: Vec<f64> = order.iter().map(|&i| tu[i].1).collect();
    let mut y = vec![0.0; t.len()];
    perpend_core::lag::filter(&t, &u, tau_s, &mut y);
    let mut out = table.clone();
    for (k, &i) in order.iter().enumerate() {
        out.rows[i].temp_c = Some(y[k]);
    }
    Ok(out)
}

/// The schema of `perpend measure --json` (docs/json.md).
pub const SCHEMA: &str = perpend_formats::schema::MEASURE;

/// Warnings for a head whose corrections need a column the readings lack:
/// a thermal coefficient without `temp_c`, a drift without `t_s` (the
/// correction is then silently not applied to those rows).
pub fn missing_columns(sensors: &[Sensor<f64>], table: &ReadingTable, file: &str) -> Vec<String> {
    let mut w = Vec::new();
    let needs = |f: fn(&Sensor<f64>) -> bool| sensors.iter().any(f);
    let lacking = |f: fn(&ReadingRow) -> bool| table.rows.iter().filter(|r| f(r)).count();
    let checks: [(bool, usize, &str, &str); 2] = [
        (
            needs(|s| s.ext.thermal != 0.0),
            lacking(|r| r.temp_c.is_none()),
            "temp_c",
            "a thermal correction",
        ),
        (
            needs(|s| s.ext.drift != 0.0),
            lacking(|r| r.t_s.is_none()),
            "t_s",
            "a drift correction",
        ),
    ];
    for (needed, rows, col, what) in checks {
        if needed && rows > 0 {
            w.push(format!(
                "{file}: the head has {what} but {rows} of {} rows have no {col}: those rows are measured without it; add the {col} column",
                table.rows.len()
            ));
        }
    }
    w
}

/// Runs `perpend measure`.
///
/// # Errors
/// Malformed files (with file and line), a head of an unsupported size, a
/// file of which no row can be measured.
pub fn run(a: &Args) -> Result<()> {
    run_to(a, &mut std::io::stdout().lock())
}

/// What `measure` computed: the rows, the head's label, the file's name
/// and the warnings about the file.
struct Computed {
    rows: Vec<RowOut>,
    label: String,
    file: String,
    warnings: Vec<String>,
}

/// Reads the head and the readings, checks them ([`perpend_formats::plausible`],
/// [`missing_columns`]), lags the temperatures, measures every row.
///
/// # Errors
/// As [`run`].
fn compute(a: &Args) -> Result<Computed> {
    let mut tau_s = 0.0;
    let (sensors, mut label, nominal) = head(a, &mut tau_s)?;
    let mut table = read_readings(&a.poses, Some(sensors.len()))?;
    let file = a.poses.display().to_string();
    let (left, total) = perpend_formats::plausible::check_readings(&file, &nominal, &mut table)?;
    let mut warnings = perpend_formats::plausible::left_out_lines(&file, &left, total);
    warnings.extend(missing_columns(&sensors, &table, &file));
    // The lag only matters through a thermal coefficient: without one a
    // τ asks nothing of the file (no t_s / temp_c needed).
    if tau_s > 0.0 && sensors.iter().any(|s| s.ext.thermal != 0.0) {
        table = lag_temperatures(&table, tau_s, &file)?;
        label += &format!("; thermal lag τ = {tau_s} s");
    }
    let rows = measure_table(&sensors, &table, &a.surface.0, a.method.into())?;
    if !rows.iter().any(|r| r.measured.is_some()) {
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
    Ok(Computed {
        rows,
        label,
        file,
        warnings,
    })
}

/// Runs `perpend measure`, writing the report (or the JSON) to `out`;
/// warnings go to stderr with the text report, into the JSON with `--json`.
///
/// # Errors
/// As [`run`]; I/O errors of `out`.
pub fn run_to(a: &Args, out: &mut dyn std::io::Write) -> Result<()> {
    let Computed {
        rows,
        label,
        file,
        warnings,
    } = compute(a)?;
    let measured = rows.iter().filter(|r| r.measured.is_some()).count();
    if a.json {
        let method = format!("{:?}", a.method).to_lowercase();
        let v = serde_json::json!({
            "file": file, "head": label, "surface": a.surface.to_string(),
            "method": method, "rows": rows, "measured": measured,
            "skipped": rows.len() - measured, "warnings": warnings,
        });
        writeln!(out, "{}", perpend_formats::schema::to_json(SCHEMA, &v)?)?;
        return Ok(());
    }
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    write!(out, "{}", report(a, &label, &rows))?;
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

    /// τ > 0: the temperatures are lagged over `t_s` in time order, not
    /// file order (rows listed out of time order get the same values as
    /// sorted ones); τ = 0 leaves them; a missing t_s or temp_c is named.
    #[test]
    fn temperatures_are_lagged_in_time_order() {
        let row = |pose: i64, t: Option<f64>, u: Option<f64>| ReadingRow {
            line: pose as u64 + 2,
            pose,
            readings: vec![Some(66.0); 4],
            t_s: t,
            temp_c: u,
        };
        // a 20 → 30 °C step at t = 100 s, rows listed out of time order
        let times = [300.0, 0.0, 200.0, 100.0, 50.0];
        let temps = [30.0, 20.0, 30.0, 30.0, 20.0];
        let table = ReadingTable {
            n_sensors: 4,
            rows: (0..5)
                .map(|k| row(k as i64 + 1, Some(times[k]), Some(temps[k])))
                .collect(),
        };
        let tau = 120.0;
        let out = lag_temperatures(&table, tau, "p.csv").unwrap();
        let sorted_t = [0.0, 50.0, 100.0, 200.0, 300.0];
        let sorted_u = [20.0, 20.0, 30.0, 30.0, 30.0];
        let mut y = [0.0; 5];
        perpend_core::lag::filter(&sorted_t, &sorted_u, tau, &mut y);
        for (r, &t) in out.rows.iter().zip(&times) {
            let k = sorted_t.iter().position(|&x| x == t).unwrap();
            assert_eq!(r.temp_c, Some(y[k]), "t = {t}");
            assert_eq!(r.t_s, Some(t));
        }
        // the lag is visible: at 200 s the bodies are still below 30 °C
        assert!(out.rows[2].temp_c.unwrap() < 29.0);
        assert_eq!(out.rows[1].temp_c, Some(20.0));
        assert_eq!(lag_temperatures(&table, 0.0, "p.csv").unwrap(), table);
        let mut t2 = table.clone();
        t2.rows[3].t_s = None;
        let e = lag_temperatures(&t2, tau, "p.csv").unwrap_err().to_string();
        assert!(e.contains("p.csv, line 6: pose 4 has no t_s"), "{e}");
        let mut t3 = table;
        t3.rows[0].temp_c = None;
        let e = lag_temperatures(&t3, tau, "p.csv").unwrap_err().to_string();
        assert!(
            e.contains("line 3: pose 1 has no temp_c") && e.contains("thermal_tau_s"),
            "{e}"
        );
    }

    /// A 45 mm cone head at 25° and its sensors.csv in `dir`.
    fn cone_head_csv(dir: &std::path::Path) -> (perpend_core::head::Head4<f64>, PathBuf) {
        let head = perpend_core::head::Head4::cone(45.0, 25f64.to_radians(), 0.0, 0.0).unwrap();
        let path = dir.join("sensors.csv");
        let mut text = String::from("sensor,x_mm,y_mm,z_mm,m,n,q\n");
        for (i, s) in head.sensors.iter().enumerate() {
            let (z, d) = (s.zero, s.dir);
            text += &format!(
                "{},{},{},{},{},{},{}\n",
                i + 1,
                z.x,
                z.y,
                z.z,
                d.x,
                d.y,
                d.z
            );
        }
        std::fs::write(&path, text).unwrap();
        (head, path)
    }

    /// τ > 0 in a params file without any thermal coefficient: the lag
    /// cannot change a reading, so a poses file without `t_s` / `temp_c`
    /// is measured (it used to be refused for the missing column).
    #[test]
    fn a_lag_without_thermal_coefficients_needs_no_times() {
        let dir = tempfile::tempdir().unwrap();
        let (head, sensors) = cone_head_csv(dir.path());
        let mut pf = ParamFile::truth(&head.sensors, &head.sensors);
        pf.thermal_tau_s = 60.0;
        let params = dir.path().join("params.json");
        pf.write(&params).unwrap();
        let plane = perpend_core::geometry::Plane::from_abcd(0.0, 0.0, 1.0, -60.0).unwrap();
        let mut csv = String::from("pose,d1_mm,d2_mm,d3_mm,d4_mm\n1");
        for i in 0..4 {
            let d = perpend_core::model::distance(&head.sensors[i], &plane, i).unwrap();
            csv += &format!(",{d}");
        }
        let poses = dir.path().join("poses.csv");
        std::fs::write(&poses, csv + "\n").unwrap();
        let a = Args {
            sensors,
            params: Some(params),
            poses,
            surface: SurfaceSpec(Shape::Plane),
            method: PlaneMethod::Lsq,
            json: true,
        };
        run(&a).unwrap();
    }

    /// Through `run`: a params file with τ and a thermal coefficient,
    /// readings whose sensor 1 is long by the lagged temperature: measured
    /// flat with the lag, tilted without it; τ > 0 without a t_s column
    /// is an error naming the column.
    #[test]
    fn run_applies_the_thermal_lag() {
        let dir = tempfile::tempdir().unwrap();
        let (head, sensors_csv) = cone_head_csv(dir.path());
        let mut pf = ParamFile::truth(&head.sensors, &head.sensors);
        pf.sensors[0].ext.thermal_mm_per_c = 0.01;
        pf.sensors[0].ext.temp_ref_c = 20.0;
        pf.thermal_tau_s = 60.0;
        let params = dir.path().join("params.json");
        pf.write(&params).unwrap();
        // flat plane at 66 mm along the axis: every reading equal, sensor 1
        // long by 0.01 mm/°C times the lagged temperature above 20 °C
        let plane = perpend_core::geometry::Plane::from_abcd(0.0, 0.0, 1.0, -60.0).unwrap();
        let d: Vec<f64> = (0..4)
            .map(|i| perpend_core::model::distance(&head.sensors[i], &plane, i).unwrap())
            .collect();
        let t = [0.0, 30.0, 60.0, 90.0, 120.0];
        let u = [20.0, 30.0, 30.0, 30.0, 30.0];
        let mut y = [0.0; 5];
        perpend_core::lag::filter(&t, &u, 60.0, &mut y);
        // listed latest first: the lag follows t_s, not the file
        let row = |k: usize, with_t: bool| {
            let t_s = if with_t {
                format!(",{}", t[k])
            } else {
                String::new()
            };
            let d1 = d[0] + 0.01 * (y[k] - 20.0);
            format!("{},{d1},{},{},{}{t_s},{}\n", k + 1, d[1], d[2], d[3], u[k])
        };
        let mut csv = String::from("pose,d1_mm,d2_mm,d3_mm,d4_mm,t_s,temp_c\n");
        let mut no_t = String::from("pose,d1_mm,d2_mm,d3_mm,d4_mm,temp_c\n");
        for k in (0..5).rev() {
            csv += &row(k, true);
            no_t += &row(k, false);
        }
        let poses = dir.path().join("poses.csv");
        std::fs::write(&poses, &csv).unwrap();
        let a = Args {
            sensors: sensors_csv,
            params: Some(params.clone()),
            poses: poses.clone(),
            surface: SurfaceSpec(Shape::Plane),
            method: PlaneMethod::Lsq,
            json: false,
        };
        let mut tau = 0.0;
        let (s, label, _) = super::head(&a, &mut tau).unwrap();
        assert_eq!(tau, 60.0);
        assert!(label.contains("params.json"));
        let table = read_readings(&poses, Some(4)).unwrap();
        let lagged = lag_temperatures(&table, tau, "poses.csv").unwrap();
        let with = measure_table(&s, &lagged, &Shape::Plane, Method::LeastSquares).unwrap();
        let without = measure_table(&s, &table, &Shape::Plane, Method::LeastSquares).unwrap();
        let worst = |rows: &[RowOut]| {
            rows.iter()
                .map(|r| r.measured.as_ref().unwrap().theta_deg)
                .fold(0.0, f64::max)
        };
        assert!(worst(&with) < 1e-6, "{}", worst(&with));
        assert!(worst(&without) > 1e-3, "{}", worst(&without));
        run(&a).unwrap();
        // τ > 0 and no t_s column
        std::fs::write(&poses, no_t).unwrap();
        let e = format!("{:#}", run(&a).unwrap_err());
        assert!(e.contains("has no t_s") && e.contains("poses.csv"), "{e}");
    }
}
