//! Planes, unit vectors and tangent bases in the TCS.
//!
//! A plane is stored in Hesse normal form `n·x + d = 0` with `|n| = 1`
//! (Chen eq. 1 after normalisation: the exchange format allows `(a, b, c)` of
//! any length and the tools scale `d` with it). Tangent bases give the two
//! degrees of freedom of a unit vector (see [`tangent_basis`]).

use nalgebra::Vector3;

use crate::{finite, Error, Real, Result};

/// Squared length below which a direction is treated as zero.
pub(crate) fn zero_len_sq<T: Real>() -> T {
    T::lit(1e-20)
}

/// Normalises `v`, rejecting non-finite components and (near) zero length.
///
/// `what` names the input in the error.
pub fn unit<T: Real>(v: Vector3<T>, what: &'static str) -> Result<Vector3<T>> {
    for c in v.iter() {
        finite(*c, what)?;
    }
    let n2 = v.norm_squared();
    if n2.is_finite_real() {
        if !(n2 > zero_len_sq::<T>()) {
            return Err(Error::ZeroLength(what));
        }
        return Ok(v / n2.fast_sqrt());
    }
    // Components so large that their squares overflow (|v| > ~1.8e19 in
    // f32): scale by the largest component first.
    let m = v.x.abs().max(v.y.abs()).max(v.z.abs());
    let w = v / m;
    Ok(w / w.norm_squared().fast_sqrt())
}

/// A plane `n·x + d = 0` in the TCS with unit normal `n` (Chen eq. 1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane<T: Real> {
    /// Unit normal.
    pub n: Vector3<T>,
    /// Signed offset: `-d` is the distance of the plane from the origin
    /// along `n`.
    pub d: T,
}

impl<T: Real> Plane<T> {
    /// Builds the plane `a·x + b·y + c·z + d = 0`, normalising `(a, b, c)`
    /// and scaling `d` with it (exchange format, `poses.csv`).
    ///
    /// # Errors
    /// [`Error::NonFinite`] for NaN/infinite coefficients,
    /// [`Error::ZeroLength`] when `(a, b, c)` is (nearly) zero.
    pub fn from_abcd(a: T, b: T, c: T, d: T) -> Result<Self> {
        let d = finite(d, "plane offset d")?;
        let raw = Vector3::new(a, b, c);
        let n = unit(raw, "plane normal")?;
        // |raw| from the unit vector, without squaring (no overflow).
        let k = if n.x.abs() >= n.y.abs() && n.x.abs() >= n.z.abs() {
            raw.x / n.x
        } else if n.y.abs() >= n.z.abs() {
            raw.y / n.y
        } else {
            raw.z / n.z
        };
        Ok(Self {
            n,
            d: finite(d / k, "plane offset d")?,
        })
    }

    /// The plane through `point` with (not necessarily unit) normal `normal`.
    ///
    /// # Errors
    /// As [`Plane::from_abcd`].
    pub fn through(point: Vector3<T>, normal: Vector3<T>) -> Result<Self> {
        for x in point.iter() {
            finite(*x, "plane point")?;
        }
        let n = unit(normal, "plane normal")?;
        Ok(Self {
            n,
            d: -n.dot(&point),
        })
    }

    /// Signed distance of `p` from the plane (positive on the side `n`
    /// points to).
    #[inline]
    pub fn signed_distance(&self, p: &Vector3<T>) -> T {
        self.n.dot(p) + self.d
    }

    /// The same plane with the normal flipped (`-n·x - d = 0`).
    #[inline]
    pub fn flipped(&self) -> Self {
        Self {
            n: -self.n,
            d: -self.d,
        }
    }

    /// The plane expressed in another frame: `rot`/`trans` map points of the
    /// current frame to the new one (`x' = rot·x + trans`).
    pub fn transformed(&self, rot: &nalgebra::Matrix3<T>, trans: &Vector3<T>) -> Self {
        let n = rot * self.n;
        Self {
            n,
            d: self.d - n.dot(trans),
        }
    }
}

/// An orthonormal pair `(e1, e2)` perpendicular to the unit vector `u`, so
/// that `(e1, e2, u)` is right-handed.
///
/// This is how a beam direction gets its **two** degrees of freedom: a unit
/// vector varies only in its tangent plane, `u' = normalise(u + α e1 + β e2)`.
/// Chen's model (eq. 5-9) perturbs all three components `m, n, q` of the
/// direction, but the distance of eq. 3 does not change when the direction
/// is scaled, so one of the three is unobservable; the 5-DOF form removes it.
///
/// `e1 = normalise(ẑ × u)` (the azimuthal direction for a beam on a cone
/// around the spindle, so `α` is a tilt around the cone and `β` a tilt
/// towards or away from the axis), or `x̂ × u` when `u` is within ~25° of ±z,
/// where ẑ × u is too short to be well conditioned.
pub fn tangent_basis<T: Real>(u: &Vector3<T>) -> (Vector3<T>, Vector3<T>) {
    let reference = if u.z.abs() < T::lit(0.9) {
        Vector3::z()
    } else {
        Vector3::x()
    };
    let e1 = reference.cross(u);
    // `u` is unit and `reference` is at least ~25° away from it, so the
    // cross product has length >= sin(25°); normalising cannot divide by 0.
    let e1 = e1 / e1.norm_squared().fast_sqrt();
    let e2 = u.cross(&e1);
    (e1, e2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn plane_normalisation_scales_offset() {
        let p = Plane::from_abcd(0.0, 0.0, 2.0, -10.0).unwrap();
        assert_relative_eq!(p.n, Vector3::new(0.0, 0.0, 1.0));
        assert_relative_eq!(p.d, -5.0);
        assert_relative_eq!(p.signed_distance(&Vector3::new(1.0, 2.0, 5.0)), 0.0);
    }

    #[test]
    fn huge_components_do_not_overflow() {
        let u = unit(Vector3::new(3e30f32, 4e30, 0.0), "v").unwrap();
        assert_relative_eq!(u, Vector3::new(0.6f32, 0.8, 0.0), epsilon = 1e-6);
        let p = Plane::from_abcd(0.0f64, 3e200, 4e200, 5e200).unwrap();
        assert_relative_eq!(p.n, Vector3::new(0.0, 0.6, 0.8), epsilon = 1e-12);
        assert_relative_eq!(p.d, 1.0, epsilon = 1e-12);
        // an offset that overflows when normalised is an error, not inf
        assert_eq!(
            Plane::from_abcd(0.0f32, 0.0, 1e-9, 1e30),
            Err(Error::NonFinite("plane offset d"))
        );
    }

    #[test]
    fn plane_rejects_bad_input() {
        assert_eq!(
            Plane::from_abcd(0.0, 0.0, 0.0, 1.0),
            Err(Error::ZeroLength("plane normal"))
        );
        assert_eq!(
            Plane::from_abcd(f64::NAN, 0.0, 1.0, 1.0),
            Err(Error::NonFinite("plane normal"))
        );
        assert_eq!(
            Plane::from_abcd(0.0, 0.0, 1.0, f64::INFINITY),
            Err(Error::NonFinite("plane offset d"))
        );
    }

    #[test]
    fn tangent_basis_is_orthonormal_and_right_handed() {
        for u in [
            Vector3::new(0.5, 0.0, 0.8660254037844386),
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(0.0, 0.0, -1.0),
            Vector3::new(1.0, 0.0, 0.0),
            Vector3::new(-0.3, 0.4, -0.2),
        ] {
            let u = unit(u, "u").unwrap();
            let (e1, e2) = tangent_basis(&u);
            assert_relative_eq!(e1.norm(), 1.0, epsilon = 1e-12);
            assert_relative_eq!(e2.norm(), 1.0, epsilon = 1e-12);
            assert_relative_eq!(e1.dot(&u), 0.0, epsilon = 1e-12);
            assert_relative_eq!(e2.dot(&u), 0.0, epsilon = 1e-12);
            assert_relative_eq!(e1.dot(&e2), 0.0, epsilon = 1e-12);
            assert_relative_eq!(e1.cross(&e2), u, epsilon = 1e-12);
        }
    }

    #[test]
    fn transformed_plane_contains_transformed_points() {
        let p = Plane::from_abcd(0.0173, -0.3071, 0.9515, 34.1218).unwrap();
        let rot = nalgebra::Rotation3::from_euler_angles(0.1, -0.2, 0.3).into_inner();
        let t = Vector3::new(1.0, -2.0, 3.0);
        let q = p.transformed(&rot, &t);
        // a point on p
        let x = -p.n * p.d + Vector3::new(0.0, 0.9515, 0.3071) * 7.0;
        assert_relative_eq!(p.signed_distance(&x), 0.0, epsilon = 1e-9);
        assert_relative_eq!(q.signed_distance(&(rot * x + t)), 0.0, epsilon = 1e-9);
    }
}
