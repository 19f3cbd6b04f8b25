//! Identifiability of one sensor's parameters from a pose set, and what a
//! pose set lacks when it cannot identify them, in plain words.
//!
//! The numerical test is the condition number `κ` of the column-scaled
//! normal matrix `D^{-1/2} JᵀJ D^{-1/2}` (`D = diag JᵀJ`): scaling makes it
//! independent of units (mm vs rad) and of the parameters' sizes, and `κ`
//! above [`Thresholds::max_condition`] means some combination of the
//! parameters is not determined by the readings.
//!
//! What determines `κ` is the pose set's geometry (Chen eq. 3 in the form of
//! [`crate::model`], `d = −(n·E + D)/(n·u)`):
//!
//! * a zero-point shift `ΔE` changes the reading by `−n·ΔE/(n·u)`: with a
//!   constant plane normal `n` only one combination of the three components
//!   is seen. The components across the beam are separated only by
//!   **variation of the plane normal**, and each needs it about its own
//!   axis: tilting about x moves `n_y`, tilting about y moves `n_x`;
//! * a beam tilt `α` changes the reading by `−d·(n·e₁)/(n·u)`: the same
//!   regressor as the across-beam zero point, multiplied by the reading `d`.
//!   Direction and zero point are separated only by **variation of each
//!   sensor's reading** (standoff, or tilt that moves its spot).
//!
//! The pose set is summarised by the tilt ranges of the plane normals about
//! the TCS x and y axes and the range of each sensor's readings; the
//! thresholds of [`Thresholds::default`] come from the sensitivity study
//! documented there. When `κ` says "not identifiable", the summary names the
//! ranges below threshold; when every range is above threshold but `κ` is
//! still too large, it names the parameter that dominates the least
//! determined direction.

use core::fmt;

use nalgebra::{SMatrix, Vector3};

use super::linalg::sym_eigen;
use super::Poses;
use crate::head::Sensor;
use crate::Real;

/// Limits that decide identifiability and the advice printed with it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Thresholds<T: Real> {
    /// Largest acceptable condition number of the column-scaled normal
    /// matrix; above it the fit is refused.
    pub max_condition: T,
    /// Smallest tilt range [deg] of the plane normals about each of the TCS
    /// x and y axes that identifies the across-beam zero point well.
    pub min_tilt_deg: T,
    /// Smallest range [mm] of a sensor's readings that separates its beam
    /// direction from its zero point well.
    pub min_standoff_mm: T,
}

impl<T: Real> Default for Thresholds<T> {
    /// Values from the sensitivity study `perpend bench ident` (paper head,
    /// ζ = 0.01 mm, ξ = 0.02 mm, 100 poses, 10 seeds; test planes from the
    /// paper spread, ±5° about x and y, ±1.5 mm; "ratio" = mean normal
    /// error with the calibrated head / with the true head):
    ///
    /// | calibration tilt x / y [°], standoff [mm] | min reading range [mm] | condition | ratio |
    /// |---|---|---|---|
    /// | 0 / 10, 3     | 2.9  | 5.7e7 | 2784 |
    /// | 0.4 / 10, 3   | 2.8  | 1.5e5 | 2.39 |
    /// | 3 / 3, 0      | 1.6  | 3.2e6 | 4.82 |
    /// | 1 / 1, 3      | 2.9  | 2.6e4 | 3.31 |
    /// | 3 / 3, 3      | 3.4  | 4.2e3 | 1.46 |
    /// | 5 / 5, 3      | 4.3  | 2.4e3 | 1.18 |
    /// | 10 / 10, 0    | 5.4  | 2.8e4 | 1.18 |
    /// | 10 / 10, 2    | 5.9  | 3.2e3 | 1.05 |
    /// | 10 / 10, 3    | 6.7  | 1.6e3 | 1.04 |
    /// | 20 / 20, 3    | 11.3 | 1.0e3 | 1.01 |
    ///
    /// * `max_condition = 1e5`: pose sets with (almost) no tilt about one
    ///   axis or with neither tilt nor standoff variation lie above it
    ///   (1.5e5 … 5.7e7, normal error 2.4× … 2800× the floor) and are
    ///   refused; everything below is at worst weak.
    /// * `min_tilt_deg = 5`: from 5° on, the calibrated normal error is
    ///   within ~20% of the floor over a ±5° working range (10°: 4%).
    /// * `min_standoff_mm = 6`: each sensor's readings must span ≥ 6 mm
    ///   (tilt moves the spot too); below, the direction is determined
    ///   poorly (10°/10° with 0-2 mm standoff range: 5-18% above floor).
    ///
    /// The thresholds scale with the noise: with 3× lower noise the same
    /// accuracy needs ~3× smaller ranges.
    fn default() -> Self {
        Self {
            max_condition: T::lit(1e5),
            min_tilt_deg: T::lit(5.0),
            min_standoff_mm: T::lit(6.0),
        }
    }
}

/// Verdict on one sensor's pose set.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    /// Well conditioned and every range above its threshold.
    Ok,
    /// Identifiable (condition below the limit) but some range is below its
    /// threshold: the parameters are less precise than the data allows.
    Weak,
    /// The parameters cannot be identified; the fit was refused.
    NotIdentifiable,
}

impl Status {
    /// Lower-case name (`ok`, `weak`, `not-identifiable`).
    pub const fn name(self) -> &'static str {
        match self {
            Status::Ok => "ok",
            Status::Weak => "weak",
            Status::NotIdentifiable => "not-identifiable",
        }
    }
}

/// What a pose set lacks (bit set).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Missing(pub u8);

impl Missing {
    /// Tilt range about x below threshold.
    pub const TILT_X: u8 = 1;
    /// Tilt range about y below threshold.
    pub const TILT_Y: u8 = 2;
    /// Reading (standoff) range below threshold.
    pub const STANDOFF: u8 = 4;
    /// Fewer valid readings than parameters + 1.
    pub const READINGS: u8 = 8;

    /// Whether `bit` is set.
    pub const fn has(self, bit: u8) -> bool {
        self.0 & bit != 0
    }

    /// Whether nothing is missing.
    pub const fn is_empty(self) -> bool {
        self.0 == 0
    }
}

/// Summary of one sensor's pose set and the verdict on it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Diagnostic<T: Real> {
    /// Sensor (0-based).
    pub sensor: usize,
    /// Valid readings of the sensor.
    pub readings: usize,
    /// Parameters fitted (5 + extension columns).
    pub params: usize,
    /// Range [deg] of the plane normals' tilt about the TCS x axis, over the
    /// poses where the sensor has a reading.
    pub tilt_x_range_deg: T,
    /// Same about the TCS y axis.
    pub tilt_y_range_deg: T,
    /// Range [mm] of the sensor's readings.
    pub standoff_range_mm: T,
    /// Condition number of the column-scaled normal matrix (infinite when
    /// singular; 0 when not computed).
    pub condition: T,
    /// Parameter with the largest weight in the least determined direction.
    pub weakest: usize,
    /// Its name.
    pub weakest_name: &'static str,
    /// Ranges below threshold.
    pub missing: Missing,
    /// The verdict.
    pub status: Status,
    /// The thresholds applied.
    pub thresholds: Thresholds<T>,
}

/// Name of geometric parameter `j` of the 5-DOF form.
pub(crate) fn geometric_name(j: usize) -> &'static str {
    match j {
        0 => "zero point x",
        1 => "zero point y",
        2 => "zero point z",
        3 => "beam tilt along e1",
        4 => "beam tilt along e2",
        _ => "extension coefficient",
    }
}

/// Tilt ranges about x and y [deg] of the plane normals and the reading
/// range [mm] of `sensor`, over the poses where it has a reading; plus the
/// number of those readings.
pub fn pose_ranges<T: Real, P: Poses<T> + ?Sized>(
    poses: &P,
    sensor: usize,
    geom: &Sensor<T>,
) -> (T, T, T, usize) {
    // Mean normal, each oriented to face the sensor (n·u < 0).
    let facing = |k: usize| {
        let n = poses.plane(k).n;
        if n.dot(&geom.dir) > T::zero() {
            -n
        } else {
            n
        }
    };
    let mut sum = Vector3::zeros();
    let mut count = 0usize;
    let (mut dmin, mut dmax) = (T::zero(), T::zero());
    for k in 0..poses.len() {
        if let Some(d) = poses.reading(k, sensor) {
            sum += facing(k);
            if count == 0 {
                dmin = d;
                dmax = d;
            } else {
                dmin = dmin.min(d);
                dmax = dmax.max(d);
            }
            count += 1;
        }
    }
    let len = sum.norm();
    if count == 0 || !(len > T::zero()) {
        return (T::zero(), T::zero(), T::zero(), count);
    }
    let nbar = sum / len;
    // Frame (fx, fy, nbar) with fx the TCS x axis projected on the tangent
    // plane (y when the normal is close to x).
    let mut fx = Vector3::x() - nbar * nbar.x;
    if fx.norm_squared() < T::lit(0.01) {
        fx = Vector3::y() - nbar * nbar.y;
    }
    let fx = fx / fx.norm();
    let fy = nbar.cross(&fx);
    let (mut ax, mut bx, mut ay, mut by) = (T::zero(), T::zero(), T::zero(), T::zero());
    let mut first = true;
    for k in 0..poses.len() {
        if poses.reading(k, sensor).is_none() {
            continue;
        }
        let n = facing(k);
        let c = n.dot(&nbar);
        // Rotation about x moves the normal along fy, about y along fx.
        let tx = (-n.dot(&fy)).atan2(c);
        let ty = (-n.dot(&fx)).atan2(c);
        if first {
            (ax, bx, ay, by) = (tx, tx, ty, ty);
            first = false;
        } else {
            ax = ax.min(tx);
            bx = bx.max(tx);
            ay = ay.min(ty);
            by = by.max(ty);
        }
    }
    let deg = T::lit(180.0) / T::pi();
    ((bx - ax) * deg, (by - ay) * deg, dmax - dmin, count)
}

/// Condition number of the column-scaled `a` and the index of the parameter
/// with the largest weight in the eigenvector of the smallest eigenvalue.
pub(crate) fn scaled_condition<T: Real, const P: usize>(a: &SMatrix<T, P, P>) -> (T, usize) {
    let inf = T::lit(f64::INFINITY);
    let mut scale = [T::zero(); P];
    for (j, s) in scale.iter_mut().enumerate() {
        let d = a[(j, j)];
        if !(d > T::zero()) {
            // A parameter with no influence at all.
            return (inf, j);
        }
        *s = T::one() / d.sqrt();
    }
    let sa = SMatrix::<T, P, P>::from_fn(|i, j| a[(i, j)] * scale[i] * scale[j]);
    let (w, v) = sym_eigen(&sa);
    let (mut imin, mut imax) = (0usize, 0usize);
    for i in 1..P {
        if w[i] < w[imin] {
            imin = i;
        }
        if w[i] > w[imax] {
            imax = i;
        }
    }
    let mut weakest = 0usize;
    for j in 1..P {
        if v[(j, imin)].abs() > v[(weakest, imin)].abs() {
            weakest = j;
        }
    }
    let kappa = if w[imin] > T::zero() {
        w[imax] / w[imin]
    } else {
        inf
    };
    if kappa.is_finite_real() {
        (kappa, weakest)
    } else {
        (inf, weakest)
    }
}

impl<T: Real> Diagnostic<T> {
    /// Fills `missing` and `status` from the ranges, the readings count and
    /// the condition number.
    pub(crate) fn judge(&mut self) {
        let th = &self.thresholds;
        let mut m = 0u8;
        if self.tilt_x_range_deg < th.min_tilt_deg {
            m |= Missing::TILT_X;
        }
        if self.tilt_y_range_deg < th.min_tilt_deg {
            m |= Missing::TILT_Y;
        }
        if self.standoff_range_mm < th.min_standoff_mm {
            m |= Missing::STANDOFF;
        }
        if self.readings < self.params + 1 {
            m |= Missing::READINGS;
        }
        self.missing = Missing(m);
        self.status = if Missing(m).has(Missing::READINGS) || !(self.condition <= th.max_condition)
        {
            Status::NotIdentifiable
        } else if m != 0 {
            Status::Weak
        } else {
            Status::Ok
        };
    }

    fn write_missing(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let th = &self.thresholds;
        let mut sep = "";
        if self.missing.has(Missing::READINGS) {
            write!(
                f,
                "{}{} valid readings: need ≥ {}",
                sep,
                self.readings,
                self.params + 1
            )?;
            sep = "; ";
        }
        if self.missing.has(Missing::TILT_X) {
            write!(
                f,
                "{}tilt range {:.1}° about x: need ≥ {:.0}°",
                sep,
                self.tilt_x_range_deg.to_f64(),
                th.min_tilt_deg.to_f64()
            )?;
            sep = "; ";
        }
        if self.missing.has(Missing::TILT_Y) {
            write!(
                f,
                "{}tilt range {:.1}° about y: need ≥ {:.0}°",
                sep,
                self.tilt_y_range_deg.to_f64(),
                th.min_tilt_deg.to_f64()
            )?;
            sep = "; ";
        }
        if self.missing.has(Missing::STANDOFF) {
            write!(
                f,
                "{}standoff range {:.1} mm: need ≥ {:.0} mm",
                sep,
                self.standoff_range_mm.to_f64(),
                th.min_standoff_mm.to_f64()
            )?;
        }
        Ok(())
    }
}

impl<T: Real> fmt::Display for Diagnostic<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = self.sensor + 1;
        match self.status {
            Status::Ok => write!(
                f,
                "sensor {s}: identifiable (condition {:.1e}; tilt range {:.1}° about x, {:.1}° about y; standoff range {:.1} mm)",
                self.condition.to_f64(),
                self.tilt_x_range_deg.to_f64(),
                self.tilt_y_range_deg.to_f64(),
                self.standoff_range_mm.to_f64()
            ),
            Status::Weak => {
                write!(
                    f,
                    "sensor {s}: identifiable but weak (condition {:.1e}): ",
                    self.condition.to_f64()
                )?;
                self.write_missing(f)
            }
            Status::NotIdentifiable => {
                write!(
                    f,
                    "sensor {s}: the pose set cannot identify its parameters (condition {:.1e}, limit {:.0e}): ",
                    self.condition.to_f64(),
                    self.thresholds.max_condition.to_f64()
                )?;
                if self.missing.is_empty() {
                    write!(
                        f,
                        "the readings do not determine the {}",
                        self.weakest_name
                    )
                } else {
                    self.write_missing(f)
                }
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::calib::testutil::{paper_heads, plane};
    use crate::calib::CalPose;
    use crate::ext::Context;
    use crate::model::distance;
    use approx::assert_relative_eq;

    #[test]
    fn ranges_of_a_hand_made_pose_set() {
        let (nominal, _) = paper_heads();
        let poses: std::vec::Vec<CalPose<f64, 4>> =
            [(-2.0, 0.0, 30.0), (3.0, 0.0, 32.0), (0.0, 0.0, 31.0)]
                .iter()
                .map(|&(tx, ty, s)| {
                    let p = plane(tx, ty, s);
                    CalPose {
                        plane: p,
                        readings: core::array::from_fn(|i| {
                            Some(distance(&nominal.sensors[i], &p, i).unwrap())
                        }),
                        ctx: Context::default(),
                    }
                })
                .collect();
        let (tx, ty, so, n) = pose_ranges(poses.as_slice(), 0, &nominal.sensors[0]);
        assert_eq!(n, 3);
        assert_relative_eq!(tx, 5.0, epsilon = 0.05);
        assert_relative_eq!(ty, 0.0, epsilon = 1e-9);
        let d: std::vec::Vec<f64> = poses.iter().map(|p| p.readings[0].unwrap()).collect();
        let want =
            d.iter().cloned().fold(f64::MIN, f64::max) - d.iter().cloned().fold(f64::MAX, f64::min);
        assert_relative_eq!(so, want, epsilon = 1e-12);
    }

    #[test]
    fn verdicts_and_messages() {
        let mut d = Diagnostic::<f64> {
            sensor: 1,
            readings: 100,
            params: 5,
            tilt_x_range_deg: 0.4,
            tilt_y_range_deg: 8.0,
            standoff_range_mm: 7.0,
            condition: 2e5,
            weakest: 0,
            weakest_name: "zero point x",
            missing: Missing::default(),
            status: Status::Ok,
            thresholds: Thresholds::default(),
        };
        d.judge();
        assert_eq!(d.status, Status::NotIdentifiable);
        assert_eq!(
            std::format!("{d}"),
            "sensor 2: the pose set cannot identify its parameters (condition 2.0e5, limit 1e5): tilt range 0.4° about x: need ≥ 5°"
        );
        d.condition = 5e3;
        d.judge();
        assert_eq!(d.status, Status::Weak);
        d.tilt_x_range_deg = 8.0;
        d.judge();
        assert_eq!(d.status, Status::Ok);
        assert!(std::format!("{d}").starts_with("sensor 2: identifiable (condition 5.0e3"));
        d.condition = f64::INFINITY;
        d.judge();
        assert_eq!(d.status, Status::NotIdentifiable);
        assert!(std::format!("{d}").ends_with("the readings do not determine the zero point x"));
    }

    #[test]
    fn singular_matrix_has_infinite_condition() {
        let mut a = SMatrix::<f64, 3, 3>::identity();
        a[(1, 1)] = 0.0;
        assert_eq!(scaled_condition(&a), (f64::INFINITY, 1));
        let b = SMatrix::<f64, 2, 2>::new(1.0, 1.0, 1.0, 1.0);
        assert!(scaled_condition(&b).0 > 1e12);
    }
}
