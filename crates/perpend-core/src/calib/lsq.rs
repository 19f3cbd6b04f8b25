//! Batch least squares for one sensor: Gauss-Newton with Levenberg-Marquardt
//! damping over all poses, in the 5-DOF parameterisation (Chen eq. 3-9 with
//! the direction on the unit sphere, [`crate::head::Sensor::retract`]) plus
//! optional linear extension columns ([`super::regress`]).
//!
//! Each sensor's readings depend only on its own parameters and the known
//! plane (Chen eq. 5), so a head of N sensors is N independent problems of
//! `P = 5 + E` parameters. The solver minimises
//!
//! ```text
//! S(θ) = Σ_k (d_k − f(E, u; plane_k) − Σ_j c_j x_kj)²
//! ```
//!
//! over the poses `k` where the sensor has a reading (missing readings are
//! skipped), accumulating the `P×P` normal equations `JᵀJ δ = Jᵀr` pose by
//! pose in fixed memory with the analytic Jacobian
//! ([`crate::model::jacobian`]); the damped system
//! `(JᵀJ + λ diag JᵀJ) δ = Jᵀr` is solved by Cholesky.
//!
//! After convergence it returns the parameters, their covariance
//! `s²·(JᵀJ)⁻¹` with `s² = S/(m − P)` (the residual variance, so the 1σ
//! reflect the data's actual noise, tracker error included), the residual
//! RMS `sqrt(S/m)` and the identifiability verdict of [`super::ident`]. A
//! pose set that cannot identify the parameters is refused with
//! [`Error::NotIdentifiable`] and a [`Diagnostic`] that says what it lacks.
//!
//! Limits: the covariance is first order (valid while the parameter errors
//! are small against the pose geometry); observations for which the beam
//! misses the plane at the current estimate are skipped and counted.

use core::fmt;

use nalgebra::{SMatrix, SVector, Vector3};

use super::ident::{geometric_name, pose_ranges, scaled_condition, Diagnostic, Missing, Status};
use super::linalg::{cholesky, cholesky_inverse, cholesky_solve};
use super::regress::{NoExtra, Regressors};
use super::{Poses, Thresholds};
use crate::head::{Head, Sensor, DOF};
use crate::model::jacobian;
use crate::{finite, Error, Real};

/// Solver settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LsqConfig<T: Real> {
    /// Iteration budget (each iteration solves one damped system).
    pub max_iter: usize,
    /// Initial Levenberg-Marquardt damping `λ` (relative to `diag JᵀJ`).
    pub lambda0: T,
    /// Identifiability limits.
    pub thresholds: Thresholds<T>,
}

impl<T: Real> Default for LsqConfig<T> {
    fn default() -> Self {
        Self {
            max_iter: 100,
            lambda0: T::lit(1e-3),
            thresholds: Thresholds::default(),
        }
    }
}

/// A fitted sensor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LsqFit<T: Real, const P: usize> {
    /// The fitted geometry (zero point, unit direction); `ext` is the
    /// nominal sensor's (turn the coefficients into an extension with
    /// [`super::ExtTerms::extension`]).
    pub sensor: Sensor<T>,
    /// `[Δx, Δy, Δz, α, β]` of the fit relative to the nominal sensor
    /// ([`Sensor::delta_from`], nominal tangent basis), then the extension
    /// coefficients.
    pub params: SVector<T, P>,
    /// Covariance of `[Δx, Δy, Δz, α, β, c…]` at the solution, the angles in
    /// the tangent basis of the *fitted* direction
    /// ([`Sensor::basis`] of `sensor`).
    pub cov: SMatrix<T, P, P>,
    /// `sqrt(diag cov)`: 1σ of each parameter [mm, mm, mm, rad, rad, …].
    pub sigma: SVector<T, P>,
    /// Residual RMS [mm].
    pub rms: T,
    /// Readings used.
    pub used: usize,
    /// Readings skipped because the beam missed the plane at the estimate.
    pub skipped: usize,
    /// Damped solves performed.
    pub iterations: usize,
    /// Identifiability verdict (status `Ok` or `Weak`).
    pub diagnostic: Diagnostic<T>,
}

impl<T: Real, const P: usize> LsqFit<T, P> {
    /// 1σ of the zero point's x, y, z [mm].
    pub fn sigma_zero(&self) -> Vector3<T> {
        Vector3::new(self.sigma[0], self.sigma[1], self.sigma[2])
    }

    /// 1σ of the unit direction's components `(m, n, q)`, propagated from
    /// the two tangent angles: `Cov_u = B C Bᵀ`, `B = [e1 e2]`.
    pub fn sigma_dir(&self) -> Vector3<T> {
        let (e1, e2) = self.sensor.basis();
        let (c11, c12, c22) = (self.cov[(3, 3)], self.cov[(3, 4)], self.cov[(4, 4)]);
        Vector3::from_fn(|i, _| {
            let v = e1[i] * e1[i] * c11 + T::lit(2.0) * e1[i] * e2[i] * c12 + e2[i] * e2[i] * c22;
            v.max(T::zero()).sqrt()
        })
    }

    /// The extension coefficients (entries `5..P` of `params`).
    pub fn coefficients(&self) -> &[T] {
        &self.params.as_slice()[DOF..]
    }
}

/// A refused or failed fit: the error and the pose-set diagnostic.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LsqError<T: Real> {
    /// What went wrong ([`Error::NotIdentifiable`] for a pose set that
    /// cannot identify the parameters).
    pub error: Error,
    /// The pose set's summary (always filled; `condition` is 0 when the
    /// failure came before it was computed).
    pub diagnostic: Diagnostic<T>,
}

impl<T: Real> fmt::Display for LsqError<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.error {
            Error::NotIdentifiable(_) => write!(f, "{}", self.diagnostic),
            e => write!(f, "sensor {}: {}", self.diagnostic.sensor + 1, e),
        }
    }
}

#[cfg(any(test, feature = "std"))]
impl<T: Real> std::error::Error for LsqError<T> {}

/// Normal equations accumulated over the poses.
struct Normal<T: Real, const P: usize> {
    a: SMatrix<T, P, P>,
    g: SVector<T, P>,
    ssr: T,
    m: usize,
    skipped: usize,
}

fn accumulate<T, PS, R, const P: usize>(
    geom: &Sensor<T>,
    params: &SVector<T, P>,
    idx: usize,
    poses: &PS,
    regs: &R,
) -> crate::Result<Normal<T, P>>
where
    T: Real,
    PS: Poses<T> + ?Sized,
    R: Regressors<T>,
{
    let mut ne = Normal {
        a: SMatrix::<T, P, P>::zeros(),
        g: SVector::<T, P>::zeros(),
        ssr: T::zero(),
        m: 0,
        skipped: 0,
    };
    for k in 0..poses.len() {
        let Some(d) = poses.reading(k, idx) else {
            continue;
        };
        finite(d, "reading")?;
        if d < T::zero() {
            return Err(Error::NegativeDistance(idx));
        }
        let (f, j5) = match jacobian(geom, &poses.plane(k), idx) {
            Ok(v) => v,
            Err(Error::BeamParallelToPlane(_) | Error::PlaneBehindSensor(_)) => {
                ne.skipped += 1;
                continue;
            }
            Err(e) => return Err(e),
        };
        let mut row = SVector::<T, P>::zeros();
        for j in 0..DOF {
            row[j] = j5[j];
        }
        regs.fill(poses, k, idx, geom, &mut row.as_mut_slice()[DOF..]);
        let mut pred = f;
        for j in DOF..P {
            pred += params[j] * row[j];
        }
        let r = d - pred;
        ne.a += row * row.transpose();
        ne.g += row * r;
        ne.ssr += r * r;
        ne.m += 1;
    }
    Ok(ne)
}

/// Fits sensor `idx` (0-based) starting from `nominal`, with the extra
/// columns of `regs` (`P` must be `5 + regs.count()`).
///
/// # Errors
/// [`LsqError`] with [`Error::NotIdentifiable`] when the pose set cannot
/// identify the parameters (too few readings or condition above the limit),
/// [`Error::OutOfRange`] for a wrong `P`, [`Error::NonFinite`] /
/// [`Error::NegativeDistance`] for bad readings, [`Error::NoConvergence`]
/// when the iteration budget runs out.
pub fn fit_sensor<T, PS, R, const P: usize>(
    nominal: &Sensor<T>,
    idx: usize,
    poses: &PS,
    regs: &R,
    cfg: &LsqConfig<T>,
) -> Result<LsqFit<T, P>, LsqError<T>>
where
    T: Real,
    PS: Poses<T> + ?Sized,
    R: Regressors<T>,
{
    let (tx, ty, so, count) = pose_ranges(poses, idx, nominal);
    let mut diag = Diagnostic {
        sensor: idx,
        readings: count,
        params: P,
        tilt_x_range_deg: tx,
        tilt_y_range_deg: ty,
        standoff_range_mm: so,
        condition: T::zero(),
        weakest: 0,
        weakest_name: geometric_name(0),
        missing: Missing::default(),
        status: Status::Ok,
        thresholds: cfg.thresholds,
    };
    let fail = |error: Error, diagnostic: Diagnostic<T>| LsqError { error, diagnostic };
    if P != DOF + regs.count() {
        return Err(fail(Error::OutOfRange("parameter count"), diag));
    }
    let name = |j: usize| {
        if j < DOF {
            geometric_name(j)
        } else {
            regs.name(j - DOF)
        }
    };
    let mut geom = *nominal;
    let mut params = SVector::<T, P>::zeros();
    let mut ne = accumulate(&geom, &params, idx, poses, regs).map_err(|e| fail(e, diag))?;
    diag.readings = ne.m;
    let (kappa, weakest) = scaled_condition(&ne.a);
    diag.condition = kappa;
    diag.weakest = weakest;
    diag.weakest_name = name(weakest);
    diag.judge();
    if diag.status == Status::NotIdentifiable {
        return Err(fail(Error::NotIdentifiable(idx), diag));
    }

    let tiny = T::lit(ne.m as f64) * (T::default_epsilon() * T::lit(1e3)).powi(2);
    let mut lambda = cfg.lambda0;
    let mut iterations = 0usize;
    let mut converged = false;
    while iterations < cfg.max_iter {
        iterations += 1;
        let mut damped = ne.a;
        for j in 0..P {
            damped[(j, j)] += lambda * ne.a[(j, j)];
        }
        let step = match cholesky(&damped) {
            Some(l) => cholesky_solve(&l, &ne.g),
            None => {
                lambda *= T::lit(10.0);
                continue;
            }
        };
        let d5 = SVector::<T, DOF>::from_fn(|i, _| step[i]);
        let trial = geom.retract(&d5).ok().and_then(|g| {
            let mut p = params;
            for j in DOF..P {
                p[j] += step[j];
            }
            accumulate(&g, &p, idx, poses, regs)
                .ok()
                .map(|t| (g, p, t))
        });
        match trial {
            Some((g, p, t)) if t.m == ne.m && t.ssr.is_finite_real() && t.ssr <= ne.ssr => {
                let decrease = ne.ssr - t.ssr;
                let old = ne.ssr;
                geom = g;
                params = p;
                ne = t;
                lambda = (lambda / T::lit(10.0)).max(T::lit(1e-12));
                if decrease <= T::lit(1e-10) * old + tiny {
                    converged = true;
                    break;
                }
            }
            _ => {
                lambda *= T::lit(10.0);
                if lambda > T::lit(1e12) {
                    // No step decreases S any more: at the minimum to
                    // rounding.
                    converged = true;
                    break;
                }
            }
        }
    }
    if !converged {
        return Err(fail(Error::NoConvergence, diag));
    }

    let (kappa, weakest) = scaled_condition(&ne.a);
    diag.condition = kappa;
    diag.weakest = weakest;
    diag.weakest_name = name(weakest);
    diag.judge();
    if diag.status == Status::NotIdentifiable {
        return Err(fail(Error::NotIdentifiable(idx), diag));
    }
    let Some(l) = cholesky(&ne.a) else {
        return Err(fail(Error::NotIdentifiable(idx), diag));
    };
    let dof = ne.m.saturating_sub(P);
    let s2 = if dof > 0 {
        ne.ssr / T::lit(dof as f64)
    } else {
        T::zero()
    };
    let cov = cholesky_inverse(&l) * s2;
    let sigma = SVector::<T, P>::from_fn(|i, _| cov[(i, i)].max(T::zero()).sqrt());
    let delta = geom.delta_from(nominal);
    for j in 0..DOF {
        params[j] = delta[j];
    }
    let rms = if ne.m > 0 {
        (ne.ssr / T::lit(ne.m as f64)).sqrt()
    } else {
        T::zero()
    };
    let all_finite = params
        .iter()
        .chain(cov.iter())
        .chain(core::iter::once(&rms))
        .all(|x| x.is_finite_real());
    if !all_finite {
        return Err(fail(Error::NonFinite("fitted parameters"), diag));
    }
    Ok(LsqFit {
        sensor: geom,
        params,
        cov,
        sigma,
        rms,
        used: ne.m,
        skipped: ne.skipped,
        iterations,
        diagnostic: diag,
    })
}

/// [`fit_sensor`] with the paper's model (no extension columns).
///
/// # Errors
/// As [`fit_sensor`].
pub fn fit_sensor_base<T: Real, PS: Poses<T> + ?Sized>(
    nominal: &Sensor<T>,
    idx: usize,
    poses: &PS,
    cfg: &LsqConfig<T>,
) -> Result<LsqFit<T, DOF>, LsqError<T>> {
    fit_sensor(nominal, idx, poses, &NoExtra, cfg)
}

/// Fits every sensor of a head with the paper's model; each entry is that
/// sensor's fit or its error.
pub fn fit_head<T: Real, PS: Poses<T> + ?Sized, const N: usize>(
    nominal: &Head<T, N>,
    poses: &PS,
    cfg: &LsqConfig<T>,
) -> [Result<LsqFit<T, DOF>, LsqError<T>>; N] {
    core::array::from_fn(|i| fit_sensor_base(&nominal.sensors[i], i, poses, cfg))
}

/// The identifiability verdict of sensor `idx`'s pose set for the paper's
/// model, evaluated at the parameters `sensor` (no fit): used to judge a
/// pose set before or independently of the estimator (e.g. for the EKF).
///
/// # Errors
/// [`Error::NonFinite`] / [`Error::NegativeDistance`] for bad readings.
pub fn assess<T: Real, PS: Poses<T> + ?Sized>(
    sensor: &Sensor<T>,
    idx: usize,
    poses: &PS,
    thresholds: &Thresholds<T>,
) -> crate::Result<Diagnostic<T>> {
    let (tx, ty, so, _) = pose_ranges(poses, idx, sensor);
    let params = SVector::<T, DOF>::zeros();
    let ne = accumulate(sensor, &params, idx, poses, &NoExtra)?;
    let (kappa, weakest) = scaled_condition(&ne.a);
    let mut diag = Diagnostic {
        sensor: idx,
        readings: ne.m,
        params: DOF,
        tilt_x_range_deg: tx,
        tilt_y_range_deg: ty,
        standoff_range_mm: so,
        condition: kappa,
        weakest,
        weakest_name: geometric_name(weakest),
        missing: Missing::default(),
        status: Status::Ok,
        thresholds: *thresholds,
    };
    diag.judge();
    Ok(diag)
}
