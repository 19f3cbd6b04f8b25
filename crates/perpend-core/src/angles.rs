//! Deviation of the spindle from the surface normal, attitude corrections
//! and Euler-angle solutions.
//!
//! ## Tian's axes in the TCS (the one mapping used everywhere)
//!
//! Tian (§4.1) puts the spindle approach direction on **+X'** of `$Tool_I`,
//! the sensor pair 1-2 in the X'Z' plane and the pair 3-4 in the X'Y'
//! plane. Our TCS has the feed on **+z**. The cyclic permutation
//!
//! ```text
//! Tian X' → TCS z,   Tian Y' → TCS x,   Tian Z' → TCS y
//! ```
//!
//! is a proper rotation, so Tian's right-handed rotations about Y'/Z' are
//! right-handed rotations about TCS x/y. Tian's outer normal `TH` (towards
//! the head) with TCS components `n = (n_x, n_y, n_z)`, `n_z < 0`, has Tian
//! components `(x0, y0, z0) ∝ (n_z, n_x, n_y)`; with `|O'T| = -x0`
//! (eq. 1-3):
//!
//! ```text
//! tan θ1 =  z0/|O'T| = n_y / (−n_z)     rotation about +Y' = +x
//! tan θ2 = −y0/|O'T| = −n_x / (−n_z)    rotation about +Z' = +y
//! θ = arctan √(tan²θ1 + tan²θ2) = arccos(−n_z)          (eq. 4)
//! t1 = arctan(cos θ2 · tan θ1) = arcsin(n_y)            (eq. 5)
//! ```
//!
//! Tian's sensors sit at: P1 on −y, P2 on +y (the X'Z' pair), P3 on −x,
//! P4 on +x (the X'Y' pair); see [`tian_direct`].
//!
//! ## Chen's attitude adjustment
//!
//! Chen eq. 20-22 rotate `e_z` onto the feed target `f = −n` (into the
//! surface) by `Rot(Y, θ)·Rot(X, ϕ)` (φ = 0): `θ = atan(f_x/f_z)`,
//! `ϕ = −asin(f_y)`. In Tian's terms `θ = θ2` and `ϕ = t1`: the two papers
//! agree. We call `ϕ` **pitch** (about TCS x) and `θ` **yaw** (about TCS y).

use nalgebra::{Matrix3, Vector3};

use crate::{finite, Error, Real, Result};

/// Tian's deviation angles [rad] (eq. 1-5).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Deviation<T: Real> {
    /// θ1: deviation in the plane of sensors 1-2 (TCS y-z), about +x.
    pub theta1: T,
    /// θ2: deviation in the plane of sensors 3-4 (TCS x-z), about +y.
    pub theta2: T,
    /// θ: total angle between the spindle axis and the normal (≥ 0).
    pub theta: T,
    /// t1: the second Euler angle of Tian's correction (eq. 5, 13).
    pub t1: T,
}

impl<T: Real> Deviation<T> {
    /// Deviation from the unit normal `n` oriented towards the head
    /// (Tian eq. 1-5 through the axis mapping in the module docs).
    ///
    /// # Errors
    /// [`Error::NonFinite`], [`Error::ZeroLength`], or
    /// [`Error::SurfaceFacesAway`] when `n_z ≥ 0`.
    pub fn from_normal(n: &Vector3<T>) -> Result<Self> {
        let n = crate::geometry::unit(*n, "normal")?;
        if !(n.z < T::zero()) {
            return Err(Error::SurfaceFacesAway);
        }
        let theta1 = n.y.atan2(-n.z);
        let theta2 = (-n.x).atan2(-n.z);
        // atan2 of the lateral and axial parts: exact near 0, where
        // acos(−n_z) loses half the digits.
        let theta = (n.x * n.x + n.y * n.y).fast_sqrt().atan2(-n.z);
        // asin(n_y) of the unit normal as atan2(n_y, √(n_x² + n_z²)): the
        // same angle, exact near ±90° too, and no `asinf` (libm's computes
        // in software f64 on the Cortex-M4F, issue 50 item 7).
        let t1 = n.y.atan2((n.x * n.x + n.z * n.z).fast_sqrt());
        Ok(Self {
            theta1,
            theta2,
            theta,
            t1,
        })
    }
}

/// Attitude correction [rad] that turns the spindle (+z) onto the inward
/// normal: `Rot(y, yaw)·Rot(x, pitch)·e_z = −n` (Chen eq. 20-22 with φ = 0).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Attitude<T: Real> {
    /// Rotation about TCS x (Chen's ϕ = −asin(f_y)), in (−π/2, π/2).
    pub pitch: T,
    /// Rotation about TCS y (Chen's θ = atan(f_x/f_z)), in (−π/2, π/2).
    pub yaw: T,
}

impl<T: Real> Attitude<T> {
    /// From the unit normal oriented towards the head (Chen eq. 22 applied to
    /// the feed target `f = −n`).
    ///
    /// # Errors
    /// As [`Deviation::from_normal`].
    pub fn from_normal(n: &Vector3<T>) -> Result<Self> {
        let n = crate::geometry::unit(*n, "normal")?;
        if !(n.z < T::zero()) {
            return Err(Error::SurfaceFacesAway);
        }
        let f = -n;
        Ok(Self {
            // −asin(f_y) of the unit f, as in `Deviation::from_normal`
            pitch: -f.y.atan2((f.x * f.x + f.z * f.z).fast_sqrt()),
            yaw: (f.x / f.z).atan(),
        })
    }

    /// The same angles from Tian's deviation: `pitch = t1`, `yaw = θ2`
    /// (module docs).
    pub fn from_deviation(dev: &Deviation<T>) -> Self {
        Self {
            pitch: dev.t1,
            yaw: dev.theta2,
        }
    }

    /// The rotation `Rot(y, yaw)·Rot(x, pitch)` (Chen eq. 20-21, φ = 0).
    pub fn rotation(&self) -> Matrix3<T> {
        rot_y(self.yaw) * rot_x(self.pitch)
    }
}

/// Elementary rotation about x (Chen eq. 21).
pub fn rot_x<T: Real>(a: T) -> Matrix3<T> {
    let (s, c) = (a.sin(), a.cos());
    Matrix3::new(
        T::one(),
        T::zero(),
        T::zero(),
        T::zero(),
        c,
        -s,
        T::zero(),
        s,
        c,
    )
}

/// Elementary rotation about y (Chen eq. 21).
pub fn rot_y<T: Real>(a: T) -> Matrix3<T> {
    let (s, c) = (a.sin(), a.cos());
    Matrix3::new(
        c,
        T::zero(),
        s,
        T::zero(),
        T::one(),
        T::zero(),
        -s,
        T::zero(),
        c,
    )
}

/// Elementary rotation about z (Chen eq. 21).
pub fn rot_z<T: Real>(a: T) -> Matrix3<T> {
    let (s, c) = (a.sin(), a.cos());
    Matrix3::new(
        c,
        -s,
        T::zero(),
        s,
        c,
        T::zero(),
        T::zero(),
        T::zero(),
        T::one(),
    )
}

/// Tian's direct formula for an ideal cone head (eq. 10-12).
///
/// `h = [h1, h2, h3, h4]` are the readings of Tian's sensors: P1 on −y and
/// P2 on +y of the TCS (the X'Z' pair), P3 on −x and P4 on +x (the X'Y'
/// pair); `lambda` is the cone half-angle between each beam and the spindle
/// axis, `l12`, `l34` the distances between the pairs' zero points (which
/// lie in one plane normal to the axis). Returns the [`Deviation`].
///
/// Exact for an ideal head: `tan θ1` is the slope of the surface's trace in
/// the plane of beams 1-2, and that trace is exactly what eq. 9 measures.
///
/// # Errors
/// [`Error::NonFinite`] for bad input; [`Error::DegenerateSpots`] when the
/// spots of a pair coincide (`l − (h_a + h_b) sin λ ≤ 0`: the beams crossed).
pub fn tian_direct<T: Real>(h: [T; 4], lambda: T, l12: T, l34: T) -> Result<Deviation<T>> {
    for x in h {
        finite(x, "reading")?;
    }
    finite(lambda, "cone angle")?;
    finite(l12, "l12")?;
    finite(l34, "l34")?;
    let (sl, cl) = (lambda.sin(), lambda.cos());
    let ab12 = l12 - (h[0] + h[1]) * sl; // eq. 8
    let ab34 = l34 - (h[2] + h[3]) * sl;
    if !(ab12 > T::zero()) || !(ab34 > T::zero()) {
        return Err(Error::DegenerateSpots);
    }
    let tan1 = (h[1] - h[0]) * cl / ab12; // eq. 9
    let tan2 = (h[2] - h[3]) * cl / ab34;
    let theta1 = tan1.atan(); // eq. 10
    let theta2 = tan2.atan(); // eq. 11
    let theta = (tan1 * tan1 + tan2 * tan2).sqrt().atan(); // eq. 12 (= eq. 4)
    let t1 = (theta2.cos() * tan1).atan(); // eq. 5
    Ok(Deviation {
        theta1,
        theta2,
        theta,
        t1,
    })
}

/// Euler angles `(a, b, c)` of `Euler(a, b, c) = Rot(z, a)·Rot(y, b)·Rot(x, c)`
/// (Tian eq. 13-15; the KUKA A, B, C convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Euler<T: Real> {
    /// Rotation about z [rad].
    pub a: T,
    /// Rotation about y [rad].
    pub b: T,
    /// Rotation about x [rad].
    pub c: T,
}

impl<T: Real> Euler<T> {
    /// The rotation matrix `Rot(z, a)·Rot(y, b)·Rot(x, c)` (eq. 13).
    pub fn matrix(&self) -> Matrix3<T> {
        rot_z(self.a) * rot_y(self.b) * rot_x(self.c)
    }
}

/// All Euler solutions of a rotation matrix (Tian eq. 16-19).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum EulerSolutions<T: Real> {
    /// `n_z ≠ ±1`: two distinct solutions, `cos b > 0` (eq. 16) first and
    /// `cos b < 0` (eq. 17) second.
    Regular([Euler<T>; 2]),
    /// `n_z = ∓1` (`b = ±π/2`): infinitely many solutions on the line
    /// `c = sign·a + offset` (eq. 18: sign = +1, b = π/2; eq. 19:
    /// sign = −1, b = −π/2). `particular` is the one with `a = 0`, as Tian
    /// recommends.
    Degenerate {
        /// The fixed middle angle ±π/2.
        b: T,
        /// +1 for eq. 18 (c = a + offset), −1 for eq. 19 (c = −a + offset).
        sign: T,
        /// The offset of the line.
        offset: T,
        /// The solution with `a = 0`.
        particular: Euler<T>,
    },
}

/// Tolerance on `|n_z| = 1` for the degenerate case and on orthonormality.
fn euler_tol<T: Real>() -> T {
    T::default_epsilon().sqrt() * T::lit(10.0)
}

/// Decomposes a rotation matrix `[n o a]` into Euler ZYX angles (Tian
/// eq. 16-19; the paper's matrix in eq. 15 prints `a_z` twice in its last
/// row: it is `[n_z o_z a_z]`).
///
/// # Errors
/// [`Error::NonFinite`], [`Error::NotARotation`] when `r` is not orthonormal
/// with determinant +1 within tolerance.
pub fn euler_solutions<T: Real>(r: &Matrix3<T>) -> Result<EulerSolutions<T>> {
    for x in r.iter() {
        finite(*x, "rotation matrix")?;
    }
    let tol = euler_tol::<T>();
    let err = (r.transpose() * r - Matrix3::identity()).abs().max();
    if !(err < tol) || !((r.determinant() - T::one()).abs() < tol) {
        return Err(Error::NotARotation);
    }
    let (nx, ny, nz) = (r[(0, 0)], r[(1, 0)], r[(2, 0)]);
    let (ox, oz) = (r[(0, 1)], r[(2, 1)]);
    let (ax, az) = (r[(0, 2)], r[(2, 2)]);
    let hyp = (nx * nx + ny * ny).sqrt();
    if hyp > tol {
        let sol = |b: T| {
            let cb = b.cos();
            Euler {
                a: (ny / cb).atan2(nx / cb),
                b,
                c: (oz / cb).atan2(az / cb),
            }
        };
        let b1 = (-nz).atan2(hyp); // eq. 16
        let b2 = (-nz).atan2(-hyp); // eq. 17
        Ok(EulerSolutions::Regular([sol(b1), sol(b2)]))
    } else if nz < T::zero() {
        // eq. 18: b = π/2, c = a + atan2(o_x, a_x)
        let offset = ox.atan2(ax);
        Ok(EulerSolutions::Degenerate {
            b: T::frac_pi_2(),
            sign: T::one(),
            offset,
            particular: Euler {
                a: T::zero(),
                b: T::frac_pi_2(),
                c: offset,
            },
        })
    } else {
        // eq. 19: b = −π/2, c = −a + atan2(−o_x, −a_x)
        let offset = (-ox).atan2(-ax);
        Ok(EulerSolutions::Degenerate {
            b: -T::frac_pi_2(),
            sign: -T::one(),
            offset,
            particular: Euler {
                a: T::zero(),
                b: -T::frac_pi_2(),
                c: offset,
            },
        })
    }
}

/// Tian's correction `Euler(θ2, t1, 0)` in his tool frame (X' = spindle,
/// eq. 13): it turns X' onto the inward normal.
pub fn tian_correction<T: Real>(dev: &Deviation<T>) -> Matrix3<T> {
    Euler {
        a: dev.theta2,
        b: dev.t1,
        c: T::zero(),
    }
    .matrix()
}

/// Tian's inverse solution of the robot target attitude (eq. 14-19):
/// `Euler(a', b', c') = Euler(a, b, c)·Euler(θ2, t1, 0)`, where `(a, b, c)`
/// is the robot's current attitude of Tian's tool frame (X' = spindle) in
/// its base frame.
///
/// # Errors
/// As [`euler_solutions`].
pub fn target_attitude<T: Real>(
    current: &Euler<T>,
    dev: &Deviation<T>,
) -> Result<EulerSolutions<T>> {
    finite(current.a, "attitude a")?;
    finite(current.b, "attitude b")?;
    finite(current.c, "attitude c")?;
    euler_solutions(&(current.matrix() * tian_correction(dev)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    fn n_from_slopes(sy: f64, sx: f64) -> Vector3<f64> {
        // surface z = z0 + sx·x + sy·y; outer normal (towards the head, -z)
        Vector3::new(sx, sy, -1.0).normalize()
    }

    #[test]
    fn golden_deviation_hand_derived() {
        // surface rising 1:10 towards +y (farther at +y): θ1 = atan(0.1) > 0
        let d = Deviation::from_normal(&n_from_slopes(0.1, 0.0)).unwrap();
        assert_relative_eq!(d.theta1, 0.1f64.atan(), epsilon = 1e-15);
        assert_relative_eq!(d.theta2, 0.0, epsilon = 1e-15);
        assert_relative_eq!(d.theta, 0.1f64.atan(), epsilon = 1e-15);
        // farther at -x: θ2 = atan(0.2) > 0 (Tian: h3 > h4 ⇒ θ2 > 0)
        let d = Deviation::from_normal(&n_from_slopes(0.0, -0.2)).unwrap();
        assert_relative_eq!(d.theta2, 0.2f64.atan(), epsilon = 1e-15);
        assert_relative_eq!(d.theta1, 0.0, epsilon = 1e-15);
        // both: θ from eq. 4
        let d = Deviation::from_normal(&n_from_slopes(0.1, -0.2)).unwrap();
        assert_relative_eq!(d.theta, (0.01f64 + 0.04).sqrt().atan(), epsilon = 1e-14);
        assert_relative_eq!(
            d.t1,
            (d.theta2.cos() * d.theta1.tan()).atan(),
            epsilon = 1e-14
        );
    }

    #[test]
    fn surface_facing_away_is_an_error() {
        assert_eq!(
            Deviation::from_normal(&Vector3::new(0.0, 0.1, 1.0)),
            Err(Error::SurfaceFacesAway)
        );
        assert_eq!(
            Attitude::from_normal(&Vector3::new(0.0, 0.0, 0.0)),
            Err(Error::ZeroLength("normal"))
        );
    }

    #[test]
    fn attitude_rotates_spindle_onto_inward_normal() {
        let n = n_from_slopes(0.13, -0.07);
        let att = Attitude::from_normal(&n).unwrap();
        let f = att.rotation() * Vector3::z();
        assert_relative_eq!(f, -n, epsilon = 1e-14);
        // Chen's angles are Tian's θ2 and t1
        let dev = Deviation::from_normal(&n).unwrap();
        assert_relative_eq!(att.yaw, dev.theta2, epsilon = 1e-14);
        assert_relative_eq!(att.pitch, dev.t1, epsilon = 1e-14);
        let via = Attitude::from_deviation(&dev);
        assert_relative_eq!(via.yaw, att.yaw, epsilon = 1e-14);
        assert_relative_eq!(via.pitch, att.pitch, epsilon = 1e-14);
    }

    #[test]
    fn tian_correction_turns_spindle_onto_normal_in_tian_axes() {
        let n = n_from_slopes(0.05, 0.11);
        let dev = Deviation::from_normal(&n).unwrap();
        // inward normal in Tian axes (X'=z, Y'=x, Z'=y)
        let f = -n;
        let f_tian = Vector3::new(f.z, f.x, f.y);
        let x2 = tian_correction(&dev) * Vector3::x();
        assert_relative_eq!(x2, f_tian, epsilon = 1e-14);
    }

    #[test]
    fn euler_regular_solutions_reproduce_matrix() {
        let e: Euler<f64> = Euler {
            a: 0.3,
            b: -0.7,
            c: 1.1,
        };
        let r = e.matrix();
        match euler_solutions(&r).unwrap() {
            EulerSolutions::Regular(s) => {
                assert_relative_eq!(s[0].a, e.a, epsilon = 1e-12);
                assert_relative_eq!(s[0].b, e.b, epsilon = 1e-12);
                assert_relative_eq!(s[0].c, e.c, epsilon = 1e-12);
                assert!(s[1].b.cos() < 0.0);
                assert_relative_eq!(s[1].matrix(), r, epsilon = 1e-12);
            }
            other => panic!("expected regular, got {other:?}"),
        }
    }

    #[test]
    fn euler_degenerate_cases() {
        for (b, sign) in [
            (core::f64::consts::FRAC_PI_2, 1.0),
            (-core::f64::consts::FRAC_PI_2, -1.0),
        ] {
            let e = Euler { a: 0.4, b, c: -0.2 };
            match euler_solutions(&e.matrix()).unwrap() {
                EulerSolutions::Degenerate {
                    b: bb,
                    sign: s,
                    offset,
                    particular,
                } => {
                    assert_relative_eq!(bb, b);
                    assert_relative_eq!(s, sign);
                    assert_relative_eq!(particular.matrix(), e.matrix(), epsilon = 1e-9);
                    // any a on the line works
                    let other = Euler {
                        a: -1.0,
                        b,
                        c: -sign + offset,
                    };
                    assert_relative_eq!(other.matrix(), e.matrix(), epsilon = 1e-9);
                }
                other => panic!("expected degenerate, got {other:?}"),
            }
        }
    }

    #[test]
    fn not_a_rotation_is_an_error() {
        let m = Matrix3::new(1.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0);
        assert_eq!(euler_solutions(&m), Err(Error::NotARotation));
        let m = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        assert_eq!(euler_solutions(&m), Err(Error::NotARotation));
    }

    #[test]
    fn target_attitude_aligns_spindle() {
        let n = n_from_slopes(-0.08, 0.12);
        let dev = Deviation::from_normal(&n).unwrap();
        let cur = Euler {
            a: 0.2,
            b: -0.1,
            c: 0.05,
        };
        let sol = target_attitude(&cur, &dev).unwrap();
        let EulerSolutions::Regular(s) = sol else {
            panic!("regular expected")
        };
        let want = cur.matrix() * tian_correction(&dev);
        for e in s {
            assert_relative_eq!(e.matrix(), want, epsilon = 1e-12);
        }
    }
}
