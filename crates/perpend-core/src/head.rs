//! The sensor head: zero point `E_i` and unit beam direction `u_i` of every
//! laser displacement sensor, in the TCS.
//!
//! Chen writes a sensor as `Φ_i = [x_i, y_i, z_i, m_i, n_i, q_i]` (§3.1) and
//! perturbs all six numbers. A direction has only two degrees of freedom:
//! eq. 3 gives the same distance for `(m, n, q)` and `k·(m, n, q)`, so one
//! combination of `Δm, Δn, Δq` cannot be identified from readings. Here a
//! sensor has **5 degrees of freedom**: the zero point (3) and a unit
//! direction updated in its tangent plane (2, see
//! [`crate::geometry::tangent_basis`]). Chen's 6-parameter form is still
//! available for the paper's EKF ([`crate::model::chen_jacobian`]), which is
//! harmless there because the Kalman gain never moves along the null
//! direction, and its directions are normalised before use.

use nalgebra::{SVector, Vector3};

use crate::ext::Extension;
use crate::geometry::{tangent_basis, unit};
use crate::{finite, Real, Result};

/// Number of parameters of one sensor in the 5-DOF form:
/// `[Δx, Δy, Δz, α, β]` (mm, mm, mm, rad, rad).
pub const DOF: usize = 5;

/// One laser displacement sensor of the head.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sensor<T: Real> {
    /// Zero point `E_i` [mm]: where the reading is 0 along the beam.
    pub zero: Vector3<T>,
    /// Unit beam direction `u_i`.
    pub dir: Vector3<T>,
    /// Reading corrections beyond the paper's model (identity by default).
    pub ext: Extension<T>,
}

impl<T: Real> Sensor<T> {
    /// A sensor at `zero` looking along `dir` (any non-zero length; it is
    /// normalised as the exchange format requires).
    ///
    /// # Errors
    /// [`crate::Error::NonFinite`] / [`crate::Error::ZeroLength`] for bad input.
    pub fn new(zero: Vector3<T>, dir: Vector3<T>) -> Result<Self> {
        for c in zero.iter() {
            finite(*c, "zero point")?;
        }
        Ok(Self {
            zero,
            dir: unit(dir, "beam direction")?,
            ext: Extension::identity(),
        })
    }

    /// Spot point of a (corrected) reading `d`: `S = E + d·u` (Chen eq. 17,
    /// with the direction normalised).
    #[inline]
    pub fn spot(&self, d: T) -> Vector3<T> {
        self.zero + self.dir * d
    }

    /// The tangent basis `(e1, e2)` in which this sensor's direction
    /// parameters `α, β` are expressed.
    #[inline]
    pub fn basis(&self) -> (Vector3<T>, Vector3<T>) {
        tangent_basis(&self.dir)
    }

    /// Applies a 5-DOF update `δ = [Δx, Δy, Δz, α, β]`:
    /// `E' = E + Δ`, `u' = normalise(u + α e1 + β e2)`: a retraction onto
    /// the unit sphere, to first order a tilt of the beam by `α` [rad]
    /// towards `e1` and `β` towards `e2`.
    ///
    /// # Errors
    /// [`crate::Error::NonFinite`] if the update holds NaN/inf.
    pub fn retract(&self, delta: &SVector<T, DOF>) -> Result<Self> {
        let (e1, e2) = self.basis();
        let zero = self.zero + Vector3::new(delta[0], delta[1], delta[2]);
        let dir = unit(
            self.dir + e1 * delta[3] + e2 * delta[4],
            "updated direction",
        )?;
        for c in zero.iter() {
            finite(*c, "updated zero point")?;
        }
        Ok(Self {
            zero,
            dir,
            ext: self.ext,
        })
    }

    /// The 5-DOF difference `self - reference`, expressed in the tangent
    /// basis of `reference` (the inverse of [`Sensor::retract`] to first
    /// order; exact for the position part).
    pub fn delta_from(&self, reference: &Self) -> SVector<T, DOF> {
        let (e1, e2) = reference.basis();
        let dp = self.zero - reference.zero;
        // Project the new direction on the tangent plane, scaled so that
        // retract(reference, delta) reproduces it: u' ∝ u + α e1 + β e2.
        let c = self.dir.dot(&reference.dir);
        let (a, b) = if c > T::zero() {
            (self.dir.dot(&e1) / c, self.dir.dot(&e2) / c)
        } else {
            (self.dir.dot(&e1), self.dir.dot(&e2))
        };
        SVector::<T, DOF>::from([dp.x, dp.y, dp.z, a, b])
    }

    /// Converts to another float type (e.g. host `f64` parameters to the
    /// board's `f32`).
    pub fn cast<U: Real>(&self) -> Sensor<U> {
        let c = |x: T| U::lit(x.to_f64());
        Sensor {
            zero: Vector3::new(c(self.zero.x), c(self.zero.y), c(self.zero.z)),
            dir: Vector3::new(c(self.dir.x), c(self.dir.y), c(self.dir.z)),
            ext: self.ext.cast(),
        }
    }
}

/// A head of `N` sensors. Sensor `i` (0-based here, 1-based in files and on
/// the bus) is also the `i`-th channel of the ADC scan.
///
/// For Chen's averaged cross products (eq. 18) the sensors must be numbered
/// in order around the spindle (either sense); the least-squares plane does
/// not care.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Head<T: Real, const N: usize> {
    /// The sensors, in ADC scan order.
    pub sensors: [Sensor<T>; N],
}

/// The product's head: four sensors.
pub type Head4<T> = Head<T, 4>;

impl<T: Real, const N: usize> Head<T, N> {
    /// A head from its sensors.
    pub fn new(sensors: [Sensor<T>; N]) -> Self {
        Self { sensors }
    }

    /// Mean of the unit beam directions of the sensors selected by `mask`
    /// (bit `i` = sensor `i`).
    pub fn mean_dir(&self, mask: u32) -> Vector3<T> {
        let mut acc = Vector3::zeros();
        for (i, s) in self.sensors.iter().enumerate() {
            if mask & (1 << i) != 0 {
                acc += s.dir;
            }
        }
        acc
    }

    /// Converts every sensor to another float type.
    pub fn cast<U: Real>(&self) -> Head<U, N> {
        Head {
            sensors: core::array::from_fn(|i| self.sensors[i].cast()),
        }
    }
}

impl<T: Real> Head4<T> {
    /// An ideal cone head: four sensors with zero points on a circle of
    /// `radius` [mm] in the plane `z = z0`, at azimuths `azimuth0 + k·90°`
    /// (k = 0..3, counter-clockwise seen from the head looking along +z,
    /// i.e. in the usual x-y sense), beams tilted towards the spindle axis
    /// by the cone half-angle `lambda` and pointing along +z (the feed).
    ///
    /// This is Tian's detection system (Fig. 3-4) with numbering in order
    /// around the axis, as Chen eq. 18 needs.
    ///
    /// # Errors
    /// [`crate::Error::NonFinite`] for non-finite arguments.
    pub fn cone(radius: T, lambda: T, z0: T, azimuth0: T) -> Result<Self> {
        finite(radius, "cone radius")?;
        finite(lambda, "cone angle")?;
        finite(z0, "cone z0")?;
        finite(azimuth0, "cone azimuth")?;
        let mut sensors = [Sensor::new(Vector3::zeros(), Vector3::z())?; 4];
        for (k, s) in sensors.iter_mut().enumerate() {
            let phi = azimuth0 + T::frac_pi_2() * T::lit(k as f64);
            let (sp, cp) = (phi.sin(), phi.cos());
            let zero = Vector3::new(radius * cp, radius * sp, z0);
            let dir = Vector3::new(-lambda.sin() * cp, -lambda.sin() * sp, lambda.cos());
            *s = Sensor::new(zero, dir)?;
        }
        Ok(Self { sensors })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn retract_then_delta_round_trips() {
        let s = Sensor::new(
            Vector3::new(50.0, 0.0, 0.0),
            Vector3::new(-0.5, 0.0, -0.866),
        )
        .unwrap();
        let d = SVector::<f64, 5>::from([0.3, -0.2, 0.1, 0.02, -0.03]);
        let t = s.retract(&d).unwrap();
        assert_relative_eq!(t.delta_from(&s), d, epsilon = 1e-12);
        assert_relative_eq!(t.dir.norm(), 1.0, epsilon = 1e-12);
    }

    #[test]
    fn cone_head_geometry() {
        let h = Head4::<f64>::cone(50.0, 30f64.to_radians(), 0.0, 0.0).unwrap();
        assert_relative_eq!(
            h.sensors[1].zero,
            Vector3::new(0.0, 50.0, 0.0),
            epsilon = 1e-12
        );
        assert_relative_eq!(
            h.sensors[0].dir,
            Vector3::new(-0.5, 0.0, 3f64.sqrt() / 2.0),
            epsilon = 1e-12
        );
        // all beams meet the axis at the same point z = r / tan(lambda)
        for s in &h.sensors {
            let t = 50.0 / 30f64.to_radians().sin();
            let p = s.spot(t);
            assert_relative_eq!(p.x, 0.0, epsilon = 1e-9);
            assert_relative_eq!(p.y, 0.0, epsilon = 1e-9);
        }
    }

    #[test]
    fn zero_direction_is_an_error() {
        assert_eq!(
            Sensor::new(Vector3::new(0.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.0)),
            Err(crate::Error::ZeroLength("beam direction"))
        );
    }
}
