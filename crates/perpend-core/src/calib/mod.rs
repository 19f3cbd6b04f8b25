//! Calibration of the sensor head (Chen §3.2 EKF, batch least squares).
//!
//! A calibration run records many poses of the head against a datum plane
//! whose equation in the TCS is known from a laser tracker (Chen §3.1,
//! eq. 1). Each sensor's reading depends only on that sensor's own
//! parameters and the known plane, so the head's calibration separates into
//! one independent problem per sensor. Two estimators are offered:
//!
//! * [`ekf`] — the paper's extended Kalman filter exactly as written
//!   (Chen eq. 10-16): 6 states `ΔΦ = [Δx, Δy, Δz, Δm, Δn, Δq]`, scalar
//!   measurement, the stopping rule with `δ`. Fixed memory, `f32` or `f64`,
//!   one [`ekf::Ekf::update`] per reading: the board's online method.
//! * [`lsq`] — batch Gauss-Newton / Levenberg-Marquardt over all poses in the
//!   5-DOF parameterisation of [`crate::head`] with the analytic Jacobian of
//!   [`crate::model::jacobian`], optional linear extension columns
//!   ([`regress`]), covariance, residual RMS and an identifiability check
//!   ([`ident`]) that refuses pose sets which cannot determine the
//!   parameters and says what the pose set lacks.
//!
//! Both read the calibration data through the [`Poses`] trait, so the board
//! can hand over a fixed array ([`CalPose`]) and the host tool its own table
//! with any number of sensors, without copying and without an allocator.
//!
//! Limits: the plane equations are taken as exact (the tracker's fit error
//! enters as extra reading noise); readings must be finite and non-negative.

pub mod ekf;
pub mod ident;
pub(crate) mod linalg;
pub mod lsq;
pub mod regress;
#[cfg(test)]
pub(crate) mod testutil;

use crate::ext::Context;
use crate::geometry::Plane;
use crate::Real;

pub use ekf::{ekf_sensor, CovarianceUpdate, Ekf, EkfConfig, EkfFit, Innovation, JacobianAt};
pub use ident::{Diagnostic, Missing, Status, Thresholds};
pub use lsq::{assess, fit_head, fit_sensor, fit_sensor_base, LsqConfig, LsqError, LsqFit};
pub use regress::{ExtTerms, NoExtra, Regressors, Term};

/// Read access to the poses of a calibration run: for pose `k`, the datum
/// plane in the TCS, the reading of each sensor and the acquisition context
/// (time, temperature).
///
/// Callers only ask for `k < len()` and `sensor < sensors()`.
pub trait Poses<T: Real> {
    /// Number of poses.
    fn len(&self) -> usize;
    /// Whether there are no poses.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Number of sensors (readings per pose).
    fn sensors(&self) -> usize;
    /// The datum plane of pose `k` (unit normal, Chen eq. 1).
    fn plane(&self, k: usize) -> Plane<T>;
    /// Reading of `sensor` (0-based) in pose `k`, `None` when missing.
    fn reading(&self, k: usize, sensor: usize) -> Option<T>;
    /// Acquisition context of pose `k` (temperature, time); empty by default.
    fn context(&self, _k: usize) -> Context<T> {
        Context {
            temp_c: None,
            t_s: None,
        }
    }
}

/// One pose of a calibration run with `N` sensors, in fixed memory.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CalPose<T: Real, const N: usize> {
    /// The datum plane in the TCS.
    pub plane: Plane<T>,
    /// Readings [mm] of the sensors in scan order; `None` = no valid reading.
    pub readings: [Option<T>; N],
    /// Temperature and time of the acquisition, when known.
    pub ctx: Context<T>,
}

impl<T: Real, const N: usize> Poses<T> for [CalPose<T, N>] {
    fn len(&self) -> usize {
        <[CalPose<T, N>]>::len(self)
    }
    fn sensors(&self) -> usize {
        N
    }
    fn plane(&self, k: usize) -> Plane<T> {
        self[k].plane
    }
    fn reading(&self, k: usize, sensor: usize) -> Option<T> {
        self[k].readings.get(sensor).copied().flatten()
    }
    fn context(&self, k: usize) -> Context<T> {
        self[k].ctx
    }
}

/// Number of valid readings of `sensor` in `poses`.
pub fn count_readings<T: Real, P: Poses<T> + ?Sized>(poses: &P, sensor: usize) -> usize {
    (0..poses.len())
        .filter(|&k| poses.reading(k, sensor).is_some())
        .count()
}
