//! Plausibility by physics, checked where the data are read: what the head
//! can measure, in which units, with what noise.
//!
//! * **Measuring range.** Each sensor reads distances in a range: the
//!   `range_min_mm` / `range_max_mm` columns of `sensors.csv`, or by
//!   default `0 … 2·t×`, where `t×` is the distance along the nominal beam
//!   from the zero point to the beam's closest approach to the spindle axis
//!   (for a cone head of radius `r` and half-angle `α`, `t× = r / sin α`:
//!   100 mm for the paper's head, 106 mm for the Tian-style one). A head is
//!   built so that the work surface is met before the beams cross (the
//!   spots would otherwise swap sides); twice that distance leaves room for
//!   every tilt a drilling head meets, and still catches a reading 10× or
//!   100× too large. A beam within 3° of the axis crosses it nowhere near:
//!   the default is then [`FAR_MM`]. A reading outside its sensor's range
//!   is left out and named (sensor, pose, line, value, range): it is an
//!   impossible reading, not a tracker blunder of its pose. A file with
//!   more than half of its readings outside is refused.
//! * **Units.** The nominal head and a pose's plane predict each reading
//!   (Chen eq. 3, `d = −(n·E + d₀)/(n·u)`) to within the head's build
//!   tolerance (a few mm). The readings multiplied by 1, 25.4 or 0.001 and
//!   the planes' offsets likewise are compared with that prediction (median
//!   absolute misfit over every reading of a beam not grazing its plane,
//!   |n·u| > 0.2): when another pair of units fits [`UNIT_GAIN`]× better
//!   than millimetres and millimetres miss by more than [`UNIT_MISFIT_MM`],
//!   the file is refused with "these look like inches/micrometres" and the
//!   factor that fixes it. The median makes it a statement about the file,
//!   not about a few wild readings. Planes through the TCP (offsets of a
//!   few mm) carry no unit to check: in inches they move the prediction
//!   by less than the head's tolerance. A file whose readings *and* planes are
//!   both in inches is not always caught (the prediction then scales with
//!   them except for the zero points' own offsets).
//! * **Noise.** A declared `sigma_mm` more than [`SIGMA_FACTOR`]× away from
//!   the noise measured in the run ([`sigma_warning`]) is a warning with
//!   both numbers (a 10 typed for 10 µm).
//!
//! The thresholds are checked on the simulator's clean runs (both heads,
//! several seeds: no warning, nothing left out, no refusal), see
//! `tests/plausible.rs`.

use std::fmt;

use nalgebra::Vector3;

use crate::exchange::{ExchangeError, PoseTable, ReadingTable, SensorRow, SensorTable};

/// Default end of the range [mm] of a beam (almost) parallel to the axis.
pub const FAR_MM: f64 = 1000.0;
/// How much better [-] another pair of units must fit than millimetres.
pub const UNIT_GAIN: f64 = 3.0;
/// Median misfit [mm] in millimetres below which the units are believed.
pub const UNIT_MISFIT_MM: f64 = 5.0;
/// Factor [-] between declared and measured noise that warns.
pub const SIGMA_FACTOR: f64 = 5.0;

/// A sensor's measuring range [mm].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Range {
    /// Start [mm].
    pub min_mm: f64,
    /// End [mm].
    pub max_mm: f64,
    /// Whether `sensors.csv` gave it (else the default of [`range_of`]).
    pub given: bool,
}

impl fmt::Display for Range {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}–{} mm", self.min_mm, round(self.max_mm))?;
        if !self.given {
            write!(f, " (default from the head's geometry; give range_min_mm, range_max_mm in sensors.csv)")?;
        }
        Ok(())
    }
}

fn round(x: f64) -> f64 {
    (x * 10.0).round() / 10.0
}

/// The range of one sensor: the columns of `sensors.csv` where given, the
/// default of the module header otherwise.
pub fn range_of(row: &SensorRow) -> Range {
    let e = Vector3::from(row.zero_mm);
    let u = Vector3::from(row.dir).normalize();
    let uxy = u.xy();
    // Closest approach of E + t·u to the z axis: t = −(E_xy·u_xy)/|u_xy|².
    let sin = uxy.norm();
    let t = -e.xy().dot(&uxy) / (sin * sin);
    let default_max = if sin > 3f64.to_radians().sin() && t.is_finite() && t > 0.0 {
        2.0 * t
    } else {
        FAR_MM
    };
    Range {
        min_mm: row.range_min_mm.unwrap_or(0.0),
        max_mm: row.range_max_mm.unwrap_or(default_max),
        given: row.range_min_mm.is_some() || row.range_max_mm.is_some(),
    }
}

/// A reading left out because it lies outside its sensor's range.
#[derive(Debug, Clone, PartialEq)]
pub struct LeftOut {
    /// 1-based sensor number.
    pub sensor: usize,
    /// Pose number.
    pub pose: i64,
    /// Line in the file.
    pub line: u64,
    /// The reading [mm].
    pub value_mm: f64,
    /// The sensor's range.
    pub range: Range,
}

impl fmt::Display for LeftOut {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "sensor {}, pose {} (line {}): reading {} mm outside the sensor's range {}",
            self.sensor, self.pose, self.line, self.value_mm, self.range
        )
    }
}

/// The warning lines for readings left out (none when nothing was).
pub fn left_out_lines(file: &str, left: &[LeftOut], total: usize) -> Vec<String> {
    if left.is_empty() {
        return Vec::new();
    }
    let mut v = vec![format!(
        "{file}: left out {} of {total} readings outside their sensor's measuring range (impossible readings, not tracker blunders):",
        left.len()
    )];
    v.extend(left.iter().map(|l| format!("  {l}")));
    v
}

/// What [`leave_out`] found: the readings left out, the readings seen, and
/// the most valid readings any row keeps.
struct Sorted {
    left: Vec<LeftOut>,
    total: usize,
    most_kept: usize,
}

/// Empties the readings outside their sensor's range (`sensors`' ranges,
/// [`range_of`]); `rows` yields (pose, line, readings).
fn leave_out<'a>(
    sensors: &SensorTable,
    rows: impl Iterator<Item = (i64, u64, &'a mut Vec<Option<f64>>)>,
) -> Sorted {
    let ranges: Vec<Range> = sensors.rows.iter().map(range_of).collect();
    let mut out = Sorted {
        left: Vec::new(),
        total: 0,
        most_kept: 0,
    };
    for (pose, line, readings) in rows {
        for (i, slot) in readings.iter_mut().enumerate() {
            let (Some(v), Some(range)) = (*slot, ranges.get(i)) else {
                continue;
            };
            out.total += 1;
            if v < range.min_mm || v > range.max_mm {
                out.left.push(LeftOut {
                    sensor: i + 1,
                    pose,
                    line,
                    value_mm: v,
                    range: *range,
                });
                *slot = None;
            }
        }
        out.most_kept = out.most_kept.max(readings.iter().flatten().count());
    }
    out
}

fn refuse(file: &str, problem: String) -> ExchangeError {
    ExchangeError {
        file: file.to_string(),
        line: None,
        problem,
    }
}

/// Refuses a run with more than half of its readings out of range (named
/// micrometres when most of them ÷ 1000 would be in range), or without a
/// pose of three readings left.
fn enough_left(file: &str, s: &Sorted) -> Result<(), ExchangeError> {
    let (left, total) = (&s.left, s.total);
    if left.len() * 2 > total {
        let micro = left
            .iter()
            .filter(|l| (l.range.min_mm..=l.range.max_mm).contains(&(l.value_mm / 1000.0)))
            .count()
            * 2
            > left.len();
        let hint = if micro {
            ": these look like micrometres; write the readings in millimetres (÷ 1000)"
        } else {
            ": check the units of the readings and the range_min_mm, range_max_mm columns of sensors.csv"
        };
        return Err(refuse(
            file,
            format!(
                "{} of {total} readings lie outside their sensor's measuring range (first: {}){hint}",
                left.len(),
                left.first().map(ToString::to_string).unwrap_or_default()
            ),
        ));
    }
    if s.most_kept < 3 {
        return Err(refuse(
            file,
            "no pose keeps three readings inside the sensors' ranges: a normal needs three".into(),
        ));
    }
    Ok(())
}

/// Checks a calibration run read from `file` against the nominal head:
/// units ([`check_units`]), then readings out of range are left out.
/// Returns the run, what was left out and the number of readings.
///
/// # Errors
/// Readings or planes in other units; more than half of the readings out
/// of range; no pose left with three readings.
pub fn check_run(
    file: &str,
    sensors: &SensorTable,
    mut poses: PoseTable,
) -> Result<(PoseTable, Vec<LeftOut>, usize), ExchangeError> {
    check_units(file, sensors, &poses)?;
    let rows = poses.rows.iter_mut();
    let s = leave_out(sensors, rows.map(|r| (r.pose, r.line, &mut r.readings)));
    enough_left(file, &s)?;
    Ok((poses, s.left, s.total))
}

/// Checks a readings file (no planes) against the head's ranges: readings
/// out of range are left out. Returns them and the number of readings.
///
/// # Errors
/// More than half of the readings out of range (micrometres named when
/// ÷ 1000 brings them in); no pose left with three readings.
pub fn check_readings(
    file: &str,
    sensors: &SensorTable,
    table: &mut ReadingTable,
) -> Result<(Vec<LeftOut>, usize), ExchangeError> {
    let rows = table.rows.iter_mut();
    let s = leave_out(sensors, rows.map(|r| (r.pose, r.line, &mut r.readings)));
    enough_left(file, &s)?;
    Ok((s.left, s.total))
}

/// Units a column may have been written in, as the factor to millimetres.
const UNITS: [(&str, f64); 3] = [
    ("millimetres", 1.0),
    ("inches", 25.4),
    ("micrometres", 0.001),
];

/// Median absolute misfit [mm] of the readings × `r` against the nominal
/// head's prediction from the planes with offsets × `p`.
fn misfit(sensors: &[(Vector3<f64>, Vector3<f64>)], poses: &PoseTable, r: f64, p: f64) -> f64 {
    let mut m: Vec<f64> = Vec::new();
    for row in &poses.rows {
        for ((e, u), x) in sensors.iter().zip(&row.readings) {
            let (Some(x), nu) = (x, row.plane.n.dot(u)) else {
                continue;
            };
            if nu.abs() > 0.2 {
                let pred = -(row.plane.n.dot(e) + p * row.plane.d) / nu;
                m.push((r * x - pred).abs());
            }
        }
    }
    if m.is_empty() {
        return 0.0;
    }
    m.sort_by(f64::total_cmp);
    m[m.len() / 2]
}

/// Refuses readings or plane offsets that the nominal head says are in
/// inches or micrometres (module header).
///
/// # Errors
/// The units that fit, the factor that fixes the file.
pub fn check_units(
    file: &str,
    sensors: &SensorTable,
    poses: &PoseTable,
) -> Result<(), ExchangeError> {
    let beams: Vec<(Vector3<f64>, Vector3<f64>)> = sensors
        .rows
        .iter()
        .map(|s| (Vector3::from(s.zero_mm), Vector3::from(s.dir).normalize()))
        .collect();
    let mm = misfit(&beams, poses, 1.0, 1.0);
    if mm <= UNIT_MISFIT_MM {
        return Ok(());
    }
    let mut best = (mm, 0, 0);
    for (ri, (_, r)) in UNITS.iter().enumerate() {
        for (pi, (_, p)) in UNITS.iter().enumerate() {
            let f = misfit(&beams, poses, *r, *p);
            if f < best.0 {
                best = (f, ri, pi);
            }
        }
    }
    let (f, ri, pi) = best;
    if (ri, pi) == (0, 0) || f * UNIT_GAIN > mm {
        return Ok(());
    }
    let n = sensors.len();
    let mut what = Vec::new();
    for (i, cols) in [
        (ri, format!("the readings d1_mm … d{n}_mm")),
        (pi, "the planes' d_mm".into()),
    ] {
        if i != 0 {
            let (unit, k) = UNITS[i];
            let fix = if k > 1.0 {
                format!("× {k}")
            } else {
                format!("÷ {}", 1.0 / k)
            };
            what.push(format!(
                "{cols}: these look like {unit}; write them in millimetres ({unit} {fix})"
            ));
        }
    }
    Err(refuse(
        file,
        format!(
            "{} (in those units the nominal head predicts the readings to {:.2} mm, in millimetres only to {:.1} mm)",
            what.join("; "),
            f,
            mm
        ),
    ))
}

/// A warning when the declared reading noise is more than [`SIGMA_FACTOR`]×
/// away from the one measured (`what`: how it was measured), with both
/// numbers; `one_sided`: the measure is an upper bound of the noise (a
/// residual RMS, which carries model and plane errors), so only a declared
/// value too large is a mistake.
pub fn sigma_warning(
    who: &str,
    declared_mm: f64,
    measured_mm: f64,
    what: &str,
    one_sided: bool,
) -> Option<String> {
    if !(declared_mm > 0.0 && measured_mm > 0.0) {
        return None;
    }
    let k = declared_mm / measured_mm;
    if k > SIGMA_FACTOR {
        Some(format!(
            "{who}: declared sigma_mm {declared_mm} mm is {k:.0}× the noise measured in the run ({:.1} µm, {what}): sigma_mm is in millimetres (10 µm is 0.01)",
            1000.0 * measured_mm
        ))
    } else if !one_sided && k * SIGMA_FACTOR < 1.0 {
        Some(format!(
            "{who}: the noise measured in the run ({:.1} µm, {what}) is {:.0}× the declared sigma_mm {declared_mm} mm",
            1000.0 * measured_mm,
            1.0 / k
        ))
    } else {
        None
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn row(zero: [f64; 3], dir: [f64; 3]) -> SensorRow {
        SensorRow {
            sensor: 1,
            zero_mm: zero,
            dir,
            sigma_mm: None,
            range_min_mm: None,
            range_max_mm: None,
        }
    }

    /// The paper's head crosses the axis 100 mm down its beams; a beam
    /// along the axis gets the far default; given columns win.
    #[test]
    fn default_range_is_twice_the_axis_crossing() {
        let r = range_of(&row([50.0, 0.0, 0.0], [-0.5, 0.0, 0.866]));
        assert!((r.max_mm - 2.0 * 50.0 / 0.5).abs() < 0.2, "{r:?}");
        assert!(!r.given && r.min_mm == 0.0);
        let r = range_of(&row([50.0, 0.0, 0.0], [0.0, 0.0, 1.0]));
        assert_eq!(r.max_mm, FAR_MM);
        let mut s = row([50.0, 0.0, 0.0], [-0.5, 0.0, 0.866]);
        s.range_min_mm = Some(20.0);
        s.range_max_mm = Some(70.0);
        let r = range_of(&s);
        assert_eq!((r.min_mm, r.max_mm, r.given), (20.0, 70.0, true));
    }

    #[test]
    fn sigma_warning_fires_beyond_five_times_only() {
        assert!(sigma_warning("s", 10.0, 0.01, "r", true)
            .unwrap()
            .contains("1000×"));
        assert!(sigma_warning("s", 0.04, 0.01, "r", true).is_none());
        assert!(sigma_warning("s", 0.001, 0.01, "r", true).is_none());
        assert!(sigma_warning("s", 0.001, 0.01, "r", false)
            .unwrap()
            .contains("10×"));
    }
}
