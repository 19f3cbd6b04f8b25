//! The beam/plane measurement model (Chen §3.1) and its Jacobians.
//!
//! A sensor with zero point `E` and unit direction `u` looks at the plane
//! `n·x + D = 0` (eq. 1). Its beam is the line of eq. 2; the spot
//! `S = E + d·u` lies on the plane, so the distance of eq. 3 is
//!
//! ```text
//! d = -(n·E + D) / (n·u)
//! ```
//!
//! (eq. 1-3 solved in closed form). Its derivatives (eq. 7-9):
//!
//! ```text
//! ∂d/∂E = -n / (n·u)
//! ∂d/∂α = -d (n·e1) / (n·u),   ∂d/∂β = -d (n·e2) / (n·u)
//! ```
//!
//! for the 5-DOF update `u' = normalise(u + α e1 + β e2)`, and for Chen's
//! unnormalised direction `w = (m, n, q)`:
//! `∂d/∂w = d (w/|w|² - n/(n·w))`, which is orthogonal to `w` — the
//! unobservable direction of the 6-parameter form.
//!
//! Limits: the beam must not be parallel to the plane (`|n·u|` above
//! [`MIN_COS_INCIDENCE`], i.e. incidence below ~89.4°) and the plane must be
//! in front of the sensor (`d ≥ 0`).

use nalgebra::{SVector, Vector3};

use crate::geometry::Plane;
use crate::head::{Sensor, DOF};
use crate::{Error, Real, Result};

/// Smallest `|n·u|` (cosine of the angle between beam and plane normal)
/// for which the beam is considered to meet the plane.
pub const MIN_COS_INCIDENCE: f64 = 0.01;

fn check_incidence<T: Real>(nu: T, idx: usize) -> Result<()> {
    if !(nu.abs() >= T::lit(MIN_COS_INCIDENCE)) {
        return Err(Error::BeamParallelToPlane(idx));
    }
    Ok(())
}

/// Distance `d_i` sensor `idx` reads on `plane` (Chen eq. 1-3; the
/// extension corrections of the sensor are not applied: this is the
/// geometric distance).
///
/// # Errors
/// [`Error::BeamParallelToPlane`], [`Error::PlaneBehindSensor`].
pub fn distance<T: Real>(sensor: &Sensor<T>, plane: &Plane<T>, idx: usize) -> Result<T> {
    let nu = plane.n.dot(&sensor.dir);
    check_incidence(nu, idx)?;
    let d = -(plane.n.dot(&sensor.zero) + plane.d) / nu;
    if d < T::zero() {
        return Err(Error::PlaneBehindSensor(idx));
    }
    Ok(d)
}

/// Distance and its gradient with respect to the 5-DOF parameters
/// `[Δx, Δy, Δz, α, β]` of the sensor (Chen eq. 7-9 in the 5-DOF form).
///
/// # Errors
/// As [`distance`].
#[inline]
pub fn jacobian<T: Real>(
    sensor: &Sensor<T>,
    plane: &Plane<T>,
    idx: usize,
) -> Result<(T, SVector<T, DOF>)> {
    jacobian_in(sensor, &sensor.basis(), plane, idx)
}

/// [`jacobian`] with the sensor's tangent basis `(e₁, e₂)`
/// ([`Sensor::basis`]) given: a solver pass over many planes with one
/// geometry computes it once. The same arithmetic, the same result.
///
/// # Errors
/// As [`distance`].
pub fn jacobian_in<T: Real>(
    sensor: &Sensor<T>,
    (e1, e2): &(Vector3<T>, Vector3<T>),
    plane: &Plane<T>,
    idx: usize,
) -> Result<(T, SVector<T, DOF>)> {
    let nu = plane.n.dot(&sensor.dir);
    let d = distance(sensor, plane, idx)?;
    let k = -T::one() / nu;
    let j = SVector::<T, DOF>::from([
        k * plane.n.x,
        k * plane.n.y,
        k * plane.n.z,
        k * d * plane.n.dot(e1),
        k * d * plane.n.dot(e2),
    ]);
    Ok((d, j))
}

/// Chen's 6-parameter model: distance and gradient with respect to
/// `[x, y, z, m, n, q]` for zero point `zero` and unnormalised direction
/// `w = (m, n, q)` (eq. 3 and 9, used by the paper's EKF, eq. 11).
///
/// # Errors
/// [`Error::ZeroLength`] when `w` is zero, plus those of [`distance`].
pub fn chen_jacobian<T: Real>(
    zero: &Vector3<T>,
    w: &Vector3<T>,
    plane: &Plane<T>,
    idx: usize,
) -> Result<(T, SVector<T, 6>)> {
    let w2 = w.norm_squared();
    if !(w2 > crate::geometry::zero_len_sq::<T>()) {
        return Err(Error::ZeroLength("beam direction"));
    }
    let wlen = w2.sqrt();
    let nw = plane.n.dot(w);
    check_incidence(nw / wlen, idx)?;
    let c = plane.n.dot(zero) + plane.d;
    let d = -c * wlen / nw;
    if d < T::zero() {
        return Err(Error::PlaneBehindSensor(idx));
    }
    let ge = plane.n * (-wlen / nw);
    let gw = (w / w2 - plane.n / nw) * d;
    Ok((
        d,
        SVector::<T, 6>::from([ge.x, ge.y, ge.z, gw.x, gw.y, gw.z]),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    fn sensor() -> Sensor<f64> {
        Sensor::new(
            Vector3::new(51.3, 0.9, 1.1),
            Vector3::new(-0.4555, 0.0506, -0.8888),
        )
        .unwrap()
    }

    fn plane() -> Plane<f64> {
        Plane::from_abcd(0.0173, -0.3071, 0.9515, 34.1218).unwrap()
    }

    #[test]
    fn spot_of_predicted_distance_is_on_plane() {
        let s = sensor();
        let p = plane();
        let d = distance(&s, &p, 0).unwrap();
        assert!(d > 0.0);
        assert_relative_eq!(p.signed_distance(&s.spot(d)), 0.0, epsilon = 1e-10);
    }

    #[test]
    fn golden_distance_hand_derived() {
        // Beam straight down the z axis from the origin onto z = 40: d = 40.
        let s = Sensor::new(Vector3::zeros(), Vector3::new(0.0, 0.0, 1.0)).unwrap();
        let p = Plane::from_abcd(0.0, 0.0, 1.0, -40.0).unwrap();
        assert_relative_eq!(distance(&s, &p, 0).unwrap(), 40.0);
        // Tilted beam at 60° from the normal: d = 40 / cos 60° = 80.
        let s = Sensor::new(Vector3::zeros(), Vector3::new(3f64.sqrt(), 0.0, 1.0)).unwrap();
        assert_relative_eq!(distance(&s, &p, 0).unwrap(), 80.0, epsilon = 1e-12);
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let s = sensor();
        let p = plane();
        let (d0, j) = jacobian(&s, &p, 0).unwrap();
        let h = 1e-6;
        for k in 0..DOF {
            let mut dp = SVector::<f64, DOF>::zeros();
            dp[k] = h;
            let mut dm = SVector::<f64, DOF>::zeros();
            dm[k] = -h;
            let fp = distance(&s.retract(&dp).unwrap(), &p, 0).unwrap();
            let fm = distance(&s.retract(&dm).unwrap(), &p, 0).unwrap();
            let fd = (fp - fm) / (2.0 * h);
            assert_relative_eq!(j[k], fd, epsilon = 1e-6, max_relative = 1e-6);
        }
        assert_relative_eq!(d0, distance(&s, &p, 0).unwrap());
    }

    #[test]
    fn chen_jacobian_matches_finite_differences_and_has_null_direction() {
        let zero = Vector3::new(51.3, 0.9, 1.1);
        let w = Vector3::new(-0.4555, 0.0506, -0.8888); // not unit
        let p = plane();
        let (d0, j) = chen_jacobian(&zero, &w, &p, 0).unwrap();
        let h = 1e-6;
        for k in 0..6 {
            let bump = |sgn: f64| {
                let mut z = zero;
                let mut ww = w;
                if k < 3 {
                    z[k] += sgn * h;
                } else {
                    ww[k - 3] += sgn * h;
                }
                chen_jacobian(&z, &ww, &p, 0).unwrap().0
            };
            let fd = (bump(1.0) - bump(-1.0)) / (2.0 * h);
            assert_relative_eq!(j[k], fd, epsilon = 1e-6, max_relative = 1e-6);
        }
        // scale invariance: the gradient along w vanishes
        let gw = Vector3::new(j[3], j[4], j[5]);
        assert_relative_eq!(gw.dot(&w), 0.0, epsilon = 1e-10);
        // same distance as the 5-DOF model
        let s = Sensor::new(zero, w).unwrap();
        assert_relative_eq!(d0, distance(&s, &p, 0).unwrap(), epsilon = 1e-10);
    }

    #[test]
    fn parallel_beam_and_plane_behind_are_errors() {
        let s = Sensor::new(Vector3::zeros(), Vector3::new(1.0, 0.0, 0.0)).unwrap();
        let p = Plane::from_abcd(0.0, 0.0, 1.0, -40.0).unwrap();
        assert_eq!(distance(&s, &p, 2), Err(Error::BeamParallelToPlane(2)));
        let s = Sensor::new(Vector3::zeros(), Vector3::new(0.0, 0.0, -1.0)).unwrap();
        assert_eq!(distance(&s, &p, 1), Err(Error::PlaneBehindSensor(1)));
    }
}
