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
//! S(θ) = Σ_k (d_k − f(E, u; plane_k) − Σ_j c_j x_kj)² + Σ_j w_j c_j²
//! ```
//!
//! (`w_j = 0` unless the regressors ask for a ridge, [`Regressors::ridge`]:
//! then `w_j = ρ_j·(JᵀJ)_jj` of the nominal start, fixed during the fit,
//! so `ρ = 1` halves an orthogonal column's coefficient; a Gaussian prior
//! `c_j ~ N(0, s²/w_j)`, whose mean and covariance the fit then returns)
//!
//! over the poses `k` where the sensor has a reading (missing readings are
//! skipped), accumulating the `P×P` normal equations `JᵀJ δ = Jᵀr` pose by
//! pose in fixed memory with the analytic Jacobian
//! ([`crate::model::jacobian`]); the damped system
//! `(JᵀJ + λ diag JᵀJ) δ = Jᵀr` is solved by Cholesky.
//!
//! **Pivot form.** The readings are taken some 40 mm from the zero point, so
//! a beam tilt `α` and an across-beam zero-point shift of `−d̄·α` (`d̄` the
//! mean reading) change the readings almost identically: in the plain
//! `[ΔE, α, β]` steps the cost is a long curved valley and Levenberg-
//! Marquardt zig-zags along it for hundreds of iterations. The solver
//! therefore steps in `[Δp, α, β]`, where `p = E + d̄·u` is the point of the
//! beam at the mean reading and the beam tilts about it
//! (`E' = p + Δp − d̄·u'`); the columns become `∂d/∂α = −(d − d̄)(n·e1)/(n·u)`
//! and the problem is nearly linear and well conditioned (3-6 iterations).
//! The identifiability test uses this form too: what the pose set must
//! determine is the beam near where it is used, not the extrapolation to
//! its zero point. The reported covariance is mapped back to `[ΔE, α, β]`.
//!
//! After convergence it returns the parameters, their covariance
//! `s²·(JᵀJ + W)⁻¹` with `s² = S_data/(m − P)` (`W = diag w`, `S_data` the
//! first sum: the residual variance, so the 1σ reflect the data's actual
//! noise, tracker error included), the residual RMS `sqrt(S_data/m)` and the identifiability verdict of [`super::ident`]. A
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
use crate::model::jacobian_in;
use crate::{finite, Error, Real};

/// Solver settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LsqConfig<T: Real> {
    /// Iteration budget (each iteration solves one damped system). Well
    /// spread pose sets converge in 4-15 iterations; weakly identifiable
    /// ones (status `Weak`) creep along a flat curved valley and may need
    /// thousands.
    pub max_iter: usize,
    /// Initial Levenberg-Marquardt damping `λ` (relative to `diag JᵀJ`).
    pub lambda0: T,
    /// Identifiability limits.
    pub thresholds: Thresholds<T>,
}

impl<T: Real> Default for LsqConfig<T> {
    fn default() -> Self {
        Self {
            max_iter: 10_000,
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
    /// The ridge's share of the cost, `Σ_j w_j c_j²`.
    pen: T,
    m: usize,
    skipped: usize,
}

impl<T: Real, const P: usize> Normal<T, P> {
    /// The cost the solver minimises: squared residuals plus the ridge.
    fn cost(&self) -> T {
        self.ssr + self.pen
    }

    /// Adds the ridge `Σ_j w_j c_j²` (module docs) at `params`.
    fn with_ridge(mut self, w: &SVector<T, P>, params: &SVector<T, P>) -> Self {
        for j in DOF..P {
            self.a[(j, j)] += w[j];
            self.g[j] -= w[j] * params[j];
            self.pen += w[j] * params[j] * params[j];
        }
        self
    }
}

/// The weights `w_j = ρ_j·a_jj` of the columns' ridges (module docs) on
/// the normal matrix `a` of the start.
fn ridge_weights<T: Real, R: Regressors<T>, const P: usize>(
    regs: &R,
    a: &SMatrix<T, P, P>,
) -> SVector<T, P> {
    SVector::<T, P>::from_fn(|j, _| {
        if j < DOF {
            return T::zero();
        }
        let r = regs.ridge(j - DOF);
        if r.is_finite_real() && r > T::zero() {
            r * a[(j, j)]
        } else {
            T::zero()
        }
    })
}

fn accumulate<T, PS, R, const P: usize>(
    geom: &Sensor<T>,
    params: &SVector<T, P>,
    pivot: T,
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
        pen: T::zero(),
        m: 0,
        skipped: 0,
    };
    let basis = geom.basis();
    let (e1, e2) = basis;
    for k in 0..poses.len() {
        let Some(d) = poses.reading(k, idx) else {
            continue;
        };
        finite(d, "reading")?;
        if d < T::zero() {
            return Err(Error::NegativeDistance(idx));
        }
        let (f, j5) = match jacobian_in(geom, &basis, &poses.plane(k), idx) {
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
        // Pivot form: tilting the beam about the point `pivot` along it
        // moves the zero point by −pivot·(α e1 + β e2).
        let je = Vector3::new(j5[0], j5[1], j5[2]);
        row[3] -= pivot * je.dot(&e1);
        row[4] -= pivot * je.dot(&e2);
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

/// Mean of the valid readings of sensor `idx` (0 without readings): the
/// pivot about which the solver tilts the beam.
fn mean_reading<T: Real, PS: Poses<T> + ?Sized>(poses: &PS, idx: usize) -> T {
    let (mut sum, mut m) = (T::zero(), 0usize);
    for k in 0..poses.len() {
        if let Some(d) = poses.reading(k, idx) {
            if d.is_finite_real() {
                sum += d;
                m += 1;
            }
        }
    }
    if m > 0 {
        sum / T::lit(m as f64)
    } else {
        T::zero()
    }
}

/// Applies a pivot-form step `[Δp, α, β, …]`: the point `E + pivot·u` moves
/// by `Δp` and the beam tilts about it (`u' = normalise(u + α e1 + β e2)`),
/// so `E' = E + pivot·u + Δp − pivot·u'`.
fn pivot_retract<T: Real, const P: usize>(
    geom: &Sensor<T>,
    step: &SVector<T, P>,
    pivot: T,
) -> crate::Result<Sensor<T>> {
    let tilt = SVector::<T, DOF>::from([T::zero(), T::zero(), T::zero(), step[3], step[4]]);
    let mut s = geom.retract(&tilt)?;
    let dp = Vector3::new(step[0], step[1], step[2]);
    s.zero = geom.zero + geom.dir * pivot + dp - s.dir * pivot;
    for c in s.zero.iter() {
        finite(*c, "updated zero point")?;
    }
    Ok(s)
}

/// Sets the condition number and the weakest parameter of `diag` from the
/// normal matrix `a` and judges the pose set ([`Diagnostic::judge`]);
/// `false` when it cannot identify the parameters.
fn judge_condition<T: Real, R: Regressors<T>, const P: usize>(
    diag: &mut Diagnostic<T>,
    a: &SMatrix<T, P, P>,
    regs: &R,
) -> bool {
    let (kappa, weakest) = scaled_condition(a);
    diag.condition = kappa;
    diag.weakest = weakest;
    diag.weakest_name = if weakest < DOF {
        geometric_name(weakest)
    } else {
        regs.name(weakest - DOF)
    };
    diag.judge();
    diag.status != Status::NotIdentifiable
}

/// What stays fixed while [`fit_sensor`] iterates: sensor `idx`'s readings,
/// its extension columns, the pivot along the beam and the ridge weights.
struct Problem<'a, T: Real, PS: ?Sized, R, const P: usize> {
    idx: usize,
    poses: &'a PS,
    regs: &'a R,
    pivot: T,
    w: SVector<T, P>,
}

/// Where the iteration stands: the geometry, the extension coefficients
/// and the normal equations there (ridge included).
struct Iterate<T: Real, const P: usize> {
    geom: Sensor<T>,
    params: SVector<T, P>,
    ne: Normal<T, P>,
}

impl<T, PS, R, const P: usize> Problem<'_, T, PS, R, P>
where
    T: Real,
    PS: Poses<T> + ?Sized,
    R: Regressors<T>,
{
    /// The point a pivot-form `step` leads to from `at`, or `None` where
    /// the model cannot be evaluated there.
    fn trial(&self, at: &Iterate<T, P>, step: &SVector<T, P>) -> Option<Iterate<T, P>> {
        let geom = pivot_retract(&at.geom, step, self.pivot).ok()?;
        let mut params = at.params;
        for j in DOF..P {
            params[j] += step[j];
        }
        let ne = accumulate(&geom, &params, self.pivot, self.idx, self.poses, self.regs).ok()?;
        Some(Iterate {
            geom,
            ne: ne.with_ridge(&self.w, &params),
            params,
        })
    }

    /// Levenberg-Marquardt with Nielsen's damping update (gain ratio ρ of
    /// actual to predicted decrease) from `at`. Converged when an accepted
    /// step is statistically negligible: δᵀ(JᵀJ)δ below 1e-8 of the
    /// residual variance (the step is < 1e-4 σ of the parameters), or the
    /// decrease is at the rounding level. (`a` holds the ridge, so the
    /// damping and the step's size scale with it.) Returns the solution
    /// and the damped solves it took, `None` when the budget ran out.
    fn solve(&self, mut at: Iterate<T, P>, cfg: &LsqConfig<T>) -> Option<(Iterate<T, P>, usize)> {
        let tiny = T::lit(at.ne.m as f64) * (T::default_epsilon() * T::lit(1e3)).powi(2);
        let dof_s2 = T::lit(at.ne.m.saturating_sub(P).max(1) as f64);
        let mut lambda = cfg.lambda0;
        let mut nu = T::lit(2.0);
        for iterations in 1..=cfg.max_iter {
            let mut damped = at.ne.a;
            for j in 0..P {
                damped[(j, j)] += lambda * at.ne.a[(j, j)];
            }
            let Some(l) = cholesky(&damped) else {
                lambda *= nu;
                nu *= T::lit(2.0);
                continue;
            };
            let step = cholesky_solve(&l, &at.ne.g);
            let a_step = at.ne.a * step;
            let predicted = T::lit(2.0) * step.dot(&at.ne.g) - step.dot(&a_step);
            match self.trial(&at, &step) {
                Some(t)
                    if t.ne.m == at.ne.m
                        && t.ne.cost().is_finite_real()
                        && t.ne.cost() <= at.ne.cost() =>
                {
                    let decrease = at.ne.cost() - t.ne.cost();
                    let rho = if predicted > T::zero() {
                        decrease / predicted
                    } else {
                        T::one()
                    };
                    let small_step = step.dot(&a_step) <= T::lit(1e-8) * at.ne.cost() / dof_s2;
                    let small_decrease = decrease <= T::lit(1e-14) * at.ne.cost() + tiny;
                    at = t;
                    let f = T::one() - (T::lit(2.0) * rho - T::one()).powi(3);
                    lambda = (lambda * f.max(T::lit(1.0 / 3.0))).max(T::lit(1e-15));
                    nu = T::lit(2.0);
                    if small_step || small_decrease {
                        return Some((at, iterations));
                    }
                }
                _ => {
                    lambda *= nu;
                    nu *= T::lit(2.0);
                    if lambda > T::lit(1e15) {
                        // No step decreases S any more: at the minimum to
                        // rounding.
                        return Some((at, iterations));
                    }
                }
            }
        }
        None
    }
}

/// Fits sensor `idx` (0-based) starting from `nominal`, with the extra
/// columns of `regs` (`P` must be `5 + regs.count()`): the pose set judged
/// at the start, [`Problem::solve`], then [`finish`].
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
    let pivot = mean_reading(poses, idx);
    let params = SVector::<T, P>::zeros();
    let ne = accumulate(nominal, &params, pivot, idx, poses, regs).map_err(|e| fail(e, diag))?;
    diag.readings = ne.m;
    if !judge_condition(&mut diag, &ne.a, regs) {
        return Err(fail(Error::NotIdentifiable(idx), diag));
    }
    let problem = Problem {
        idx,
        poses,
        regs,
        pivot,
        w: ridge_weights(regs, &ne.a),
    };
    // At the start the coefficients are 0: the ridge adds to `a` only.
    let start = Iterate {
        geom: *nominal,
        ne: ne.with_ridge(&problem.w, &params),
        params,
    };
    let Some((at, iterations)) = problem.solve(start, cfg) else {
        return Err(fail(Error::NoConvergence, diag));
    };
    finish(at, iterations, nominal, &problem, diag)
}

/// The fit at the solution `at`: the pose set judged again on the data's
/// own normal matrix (the ridge would hide a pose set that lacks
/// something), the covariance mapped from the pivot form to `[ΔE, α, β]`,
/// the residual RMS.
///
/// # Errors
/// [`Error::NotIdentifiable`] with the diagnostic of the data's own
/// normal matrix, [`Error::NonFinite`] for a non-finite fit.
fn finish<T, PS, R, const P: usize>(
    at: Iterate<T, P>,
    iterations: usize,
    nominal: &Sensor<T>,
    problem: &Problem<'_, T, PS, R, P>,
    mut diag: Diagnostic<T>,
) -> Result<LsqFit<T, P>, LsqError<T>>
where
    T: Real,
    PS: Poses<T> + ?Sized,
    R: Regressors<T>,
{
    let Iterate {
        geom,
        mut params,
        ne,
    } = at;
    let data_a = ne.a - SMatrix::from_diagonal(&problem.w);
    let identifiable = judge_condition(&mut diag, &data_a, problem.regs);
    let fail = |error: Error| LsqError {
        error,
        diagnostic: diag,
    };
    let l = match cholesky(&ne.a) {
        Some(l) if identifiable => l,
        _ => return Err(fail(Error::NotIdentifiable(problem.idx))),
    };
    let dof = ne.m.saturating_sub(P);
    let s2 = if dof > 0 {
        ne.ssr / T::lit(dof as f64)
    } else {
        T::zero()
    };
    // Covariance of the pivot-form step, mapped to the zero-point form
    // [ΔE, α, β]: ΔE = Δp − pivot·(α e1 + β e2).
    let cov_pivot = cholesky_inverse(&l) * s2;
    let (e1, e2) = geom.basis();
    let mut t = SMatrix::<T, P, P>::identity();
    for i in 0..3 {
        t[(i, 3)] = -problem.pivot * e1[i];
        t[(i, 4)] = -problem.pivot * e2[i];
    }
    let cov = t * cov_pivot * t.transpose();
    let cov = (cov + cov.transpose()) * T::lit(0.5);
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
        return Err(fail(Error::NonFinite("fitted parameters")));
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
    let pivot = mean_reading(poses, idx);
    let ne = accumulate(sensor, &params, pivot, idx, poses, &NoExtra)?;
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

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
mod tests {
    use super::*;
    use crate::calib::regress::{ExtTerms, Term};
    use crate::calib::testutil::{paper_heads, random_heads, run, Spread, PAPER};
    use crate::calib::CalPose;
    use approx::assert_relative_eq;
    use rand::rngs::StdRng;
    use rand::SeedableRng;

    #[test]
    fn exact_recovery_from_noiseless_data() {
        let (nominal, truth) = paper_heads();
        let poses = run(&truth, PAPER, 100, 0.0, 7);
        for i in 0..4 {
            let fit = fit_sensor_base(
                &nominal.sensors[i],
                i,
                poses.as_slice(),
                &LsqConfig::default(),
            )
            .unwrap();
            assert_relative_eq!(fit.sensor.zero, truth.sensors[i].zero, epsilon = 1e-8);
            assert_relative_eq!(fit.sensor.dir, truth.sensors[i].dir, epsilon = 1e-10);
            assert!(fit.rms < 1e-9, "rms {}", fit.rms);
            assert_eq!(fit.used, 100);
            assert!(fit.iterations <= 20, "{} iterations", fit.iterations);
            assert_eq!(fit.diagnostic.status, Status::Ok);
            // params = delta from nominal, in the nominal basis
            let back = nominal.sensors[i]
                .retract(&SVector::<f64, 5>::from_fn(|j, _| fit.params[j]))
                .unwrap();
            assert_relative_eq!(back.zero, fit.sensor.zero, epsilon = 1e-9);
            assert_relative_eq!(back.dir, fit.sensor.dir, epsilon = 1e-9);
        }
    }

    #[test]
    fn pivot_columns_match_finite_differences() {
        let (nominal, truth) = paper_heads();
        let poses = run(&truth, PAPER, 10, 0.0, 3);
        let s = nominal.sensors[1];
        let pivot = 31.5;
        let ne = accumulate(
            &s,
            &SVector::<f64, 5>::zeros(),
            pivot,
            1,
            poses.as_slice(),
            &NoExtra,
        )
        .unwrap();
        // Jᵀr at zero step vs finite differences of the cost along each
        // pivot-form coordinate: dS/dδ_j = −2 (Jᵀr)_j.
        let cost = |step: &SVector<f64, 5>| {
            let g = pivot_retract(&s, step, pivot).unwrap();
            accumulate(
                &g,
                &SVector::<f64, 5>::zeros(),
                pivot,
                1,
                poses.as_slice(),
                &NoExtra,
            )
            .unwrap()
            .ssr
        };
        let h = 1e-6;
        for j in 0..5 {
            let mut e = SVector::<f64, 5>::zeros();
            e[j] = h;
            let fd = (cost(&e) - cost(&(-e))) / (2.0 * h);
            assert_relative_eq!(fd, -2.0 * ne.g[j], max_relative = 1e-5, epsilon = 1e-6);
        }
    }

    #[test]
    fn recovered_parameters_are_within_3_sigma() {
        // 40 random heads × 4 sensors × 5 parameters; the error is
        // expressed in the fitted sensor's basis, like the covariance.
        let mut rng = StdRng::seed_from_u64(2024);
        let spread = Spread {
            cx: 0.0,
            cy: 0.0,
            rx: 20.0,
            ry: 20.0,
            s: 35.0,
            rs: 10.0,
        };
        let (mut inside, mut inside1, mut total) = (0usize, 0usize, 0usize);
        for h in 0..40 {
            let (nominal, truth) = random_heads(&mut rng);
            let poses = run(&truth, spread, 60, 0.01, 100 + h);
            for i in 0..4 {
                let fit = fit_sensor_base(
                    &nominal.sensors[i],
                    i,
                    poses.as_slice(),
                    &LsqConfig::default(),
                )
                .unwrap();
                let err = truth.sensors[i].delta_from(&fit.sensor);
                for j in 0..5 {
                    total += 1;
                    if err[j].abs() <= 3.0 * fit.sigma[j] {
                        inside += 1;
                    }
                    if err[j].abs() <= fit.sigma[j] {
                        inside1 += 1;
                    }
                }
                // The residual RMS estimates the noise.
                assert!((fit.rms - 0.01).abs() < 0.004, "rms {}", fit.rms);
            }
        }
        let frac = inside as f64 / total as f64;
        assert!(frac >= 0.95, "{inside}/{total} within 3σ");
        // and not trivially: the covariance is not inflated either (a
        // Gaussian puts 68% within 1σ).
        assert_eq!(total, 800);
        let frac1 = inside1 as f64 / total as f64;
        assert!(
            (0.55..=0.80).contains(&frac1),
            "{inside1}/{total} within 1σ"
        );
    }

    #[test]
    fn no_tilt_about_x_is_refused_with_the_right_message() {
        let (nominal, truth) = paper_heads();
        let spread = Spread { rx: 0.0, ..PAPER };
        let poses = run(&truth, spread, 100, 0.01, 5);
        let e = fit_sensor_base(
            &nominal.sensors[0],
            0,
            poses.as_slice(),
            &LsqConfig::default(),
        )
        .unwrap_err();
        assert_eq!(e.error, Error::NotIdentifiable(0));
        assert_eq!(e.diagnostic.status, Status::NotIdentifiable);
        assert!(e.diagnostic.missing.has(Missing::TILT_X));
        assert!(!e.diagnostic.missing.has(Missing::TILT_Y));
        let msg = e.to_string();
        assert!(
            msg.contains("tilt range 0.0° about x: need ≥ 5°"),
            "message: {msg}"
        );
        assert!(!msg.contains("about y"), "message: {msg}");
        // the verdict without fitting agrees
        let d = assess(
            &nominal.sensors[0],
            0,
            poses.as_slice(),
            &Thresholds::default(),
        )
        .unwrap();
        assert_eq!(d.status, Status::NotIdentifiable);
    }

    #[test]
    fn narrow_pose_set_is_weak_not_refused() {
        let (nominal, truth) = paper_heads();
        let spread = Spread {
            rx: 3.0,
            ry: 3.0,
            rs: 5.0,
            ..PAPER
        };
        let poses = run(&truth, spread, 100, 0.01, 9);
        let fit = fit_sensor_base(
            &nominal.sensors[2],
            2,
            poses.as_slice(),
            &LsqConfig::default(),
        )
        .unwrap();
        assert_eq!(fit.diagnostic.status, Status::Weak);
        let msg = fit.diagnostic.to_string();
        assert!(msg.contains("about x: need ≥ 5°"), "{msg}");
        assert!(msg.contains("about y: need ≥ 5°"), "{msg}");
    }

    #[test]
    fn too_few_readings_are_refused() {
        let (nominal, truth) = paper_heads();
        let poses = run(&truth, PAPER, 5, 0.01, 1);
        let e = fit_sensor_base(
            &nominal.sensors[0],
            0,
            poses.as_slice(),
            &LsqConfig::default(),
        )
        .unwrap_err();
        assert_eq!(e.error, Error::NotIdentifiable(0));
        assert!(e.to_string().contains("5 valid readings: need ≥ 6"), "{e}");
    }

    #[test]
    fn missing_readings_are_skipped() {
        let (nominal, truth) = paper_heads();
        let mut poses = run(&truth, PAPER, 100, 0.0, 11);
        for (k, p) in poses.iter_mut().enumerate() {
            if k % 3 == 0 {
                p.readings[1] = None;
            }
        }
        let fit = fit_sensor_base(
            &nominal.sensors[1],
            1,
            poses.as_slice(),
            &LsqConfig::default(),
        )
        .unwrap();
        assert_eq!(fit.used, 66);
        assert_relative_eq!(fit.sensor.zero, truth.sensors[1].zero, epsilon = 1e-8);
    }

    #[test]
    fn never_nan_on_bad_input() {
        let (nominal, truth) = paper_heads();
        let mut poses = run(&truth, PAPER, 50, 0.01, 13);
        poses[7].readings[0] = Some(f64::NAN);
        let e = fit_sensor_base(
            &nominal.sensors[0],
            0,
            poses.as_slice(),
            &LsqConfig::default(),
        )
        .unwrap_err();
        assert_eq!(e.error, Error::NonFinite("reading"));
        poses[7].readings[0] = Some(-1.0);
        let e = fit_sensor_base(
            &nominal.sensors[0],
            0,
            poses.as_slice(),
            &LsqConfig::default(),
        )
        .unwrap_err();
        assert_eq!(e.error, Error::NegativeDistance(0));
        // All identical poses: singular, refused (not NaN).
        let same: Vec<CalPose<f64, 4>> = core::iter::repeat_n(poses[0], 50).collect();
        let e = fit_sensor_base(
            &nominal.sensors[0],
            0,
            same.as_slice(),
            &LsqConfig::default(),
        )
        .unwrap_err();
        assert_eq!(e.error, Error::NotIdentifiable(0));
        // Garbage readings: a result, finite, or an error.
        let mut rng = StdRng::seed_from_u64(1);
        for p in poses.iter_mut() {
            p.readings[3] = Some(rand::Rng::gen_range(&mut rng, 0.0..200.0));
        }
        if let Ok(f) = fit_sensor_base(
            &nominal.sensors[3],
            3,
            poses.as_slice(),
            &LsqConfig::default(),
        ) {
            assert!(f.params.iter().chain(f.sigma.iter()).all(|x| x.is_finite()));
            assert!(f.rms.is_finite());
        }
    }

    #[test]
    fn gain_extension_is_recovered() {
        // Readings with a 0.3 % gain error about 32 mm.
        let (nominal, truth) = paper_heads();
        let mut poses = run(&truth, PAPER, 100, 0.0, 17);
        let ext = ExtTerms::new(&[Term::Gain], 32.0, 20.0);
        let g = 3e-3;
        for p in poses.iter_mut() {
            let d = p.readings[0].unwrap();
            // the reading model of `ext`: r = d + g (d − 32)
            p.readings[0] = Some(d + g * (d - 32.0));
        }
        let fit: LsqFit<f64, 6> = fit_sensor(
            &nominal.sensors[0],
            0,
            poses.as_slice(),
            &ext,
            &LsqConfig::default(),
        )
        .unwrap();
        assert_relative_eq!(fit.coefficients()[0], g, epsilon = 1e-9);
        assert_relative_eq!(fit.sensor.zero, truth.sensors[0].zero, epsilon = 1e-6);
        let e = ext.extension(fit.coefficients());
        assert_relative_eq!(e.gain, g, epsilon = 1e-9);
        // wrong P is an error, not a panic
        let bad: Result<LsqFit<f64, 7>, _> = fit_sensor(
            &nominal.sensors[0],
            0,
            poses.as_slice(),
            &ext,
            &LsqConfig::default(),
        );
        assert_eq!(bad.unwrap_err().error, Error::OutOfRange("parameter count"));
    }

    /// The ridge of [`Regressors::ridge`]: 0 is plain least squares; a
    /// larger one shrinks the table and the gain beside it (and their 1σ),
    /// costs residual, and the fit is a stationary point of the penalised
    /// cost of the module docs, `Σ_k r_k x_kj = w_j c_j` with `w_j` from
    /// the nominal start (to the solver's tolerance: its Jacobian holds the
    /// regressors constant, so it stops by damping a few 10⁻⁴ of the noise
    /// short of the exact optimum).
    #[test]
    fn ridge_shrinks_the_table_to_the_penalised_optimum() {
        let (nominal, truth) = paper_heads();
        let mut poses = run(&truth, PAPER, 80, 0.01, 23);
        let d: Vec<f64> = poses.iter().filter_map(|p| p.readings[0]).collect();
        let (lo, hi) = d
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), x| (a.min(*x), b.max(*x)));
        let mid = 0.5 * (lo + hi);
        for p in poses.iter_mut() {
            let r = p.readings[0].unwrap();
            // a full-period S-curve of 30 µm over the range
            let x = (r - mid) / (0.5 * (hi - lo));
            p.readings[0] = Some(r + 0.03 * (core::f64::consts::PI * x).sin());
        }
        let step = (hi - lo) / 4.0;
        let knots = core::array::from_fn(|j| lo - mid + step * j as f64);
        let terms = |rho: f64| {
            ExtTerms::new(
                &[Term::Gain, Term::Table0, Term::Table1, Term::Table2],
                mid,
                20.0,
            )
            .with_knots(knots)
            .with_ridge(rho)
        };
        let cfg = LsqConfig::default();
        let fit = |rho: f64| -> LsqFit<f64, 9> {
            fit_sensor(&nominal.sensors[0], 0, poses.as_slice(), &terms(rho), &cfg).unwrap()
        };
        let plain: LsqFit<f64, 9> = fit_sensor(
            &nominal.sensors[0],
            0,
            poses.as_slice(),
            &ExtTerms::new(
                &[Term::Gain, Term::Table0, Term::Table1, Term::Table2],
                mid,
                20.0,
            )
            .with_knots(knots),
            &cfg,
        )
        .unwrap();
        assert_eq!(fit(0.0).params, plain.params);
        assert_eq!(fit(-1.0).params, plain.params);
        let norm = |f: &LsqFit<f64, 9>| f.coefficients().iter().map(|c| c * c).sum::<f64>();
        let fits = [0.0, 0.1, 1.0].map(fit);
        for w in fits.windows(2) {
            assert!(
                norm(&w[1]) < norm(&w[0]),
                "{} !< {}",
                norm(&w[1]),
                norm(&w[0])
            );
            assert!(w[1].rms > w[0].rms);
            for j in DOF..9 {
                assert!(w[1].sigma[j] < w[0].sigma[j]);
            }
        }
        // Stationarity of the penalised cost in the coefficients.
        let rho = 0.3;
        let f = fit(rho);
        let t = terms(rho);
        let (mut a0, mut grad) = ([0.0; 4], [0.0; 4]);
        for (k, p) in poses.iter().enumerate() {
            let mut x0 = [0.0; 4];
            let mut x = [0.0; 4];
            t.fill(poses.as_slice(), k, 0, &nominal.sensors[0], &mut x0);
            t.fill(poses.as_slice(), k, 0, &f.sensor, &mut x);
            let pred = crate::model::distance(&f.sensor, &p.plane, 0).unwrap()
                + x.iter()
                    .zip(f.coefficients())
                    .map(|(x, c)| x * c)
                    .sum::<f64>();
            let r = p.readings[0].unwrap() - pred;
            for j in 0..4 {
                a0[j] += x0[j] * x0[j];
                grad[j] += r * x[j];
            }
        }
        for j in 0..4 {
            let w = rho * a0[j];
            let c = f.coefficients()[j];
            // within 1 % of what noise alone puts in `Σ r x` (the solver
            // stops at a statistically negligible step)
            let noise = a0[j].sqrt() * f.rms;
            assert!(
                (grad[j] - w * c).abs() < 0.01 * noise,
                "{j}: {} vs {}",
                grad[j],
                w * c
            );
            assert!(
                (w * c).abs() > 0.05 * noise,
                "{j}: the ridge must matter here"
            );
        }
    }

    #[test]
    fn fit_head_fits_every_sensor() {
        let (nominal, truth) = paper_heads();
        let poses = run(&truth, PAPER, 100, 0.0, 19);
        let fits = fit_head(&nominal, poses.as_slice(), &LsqConfig::default());
        for (i, f) in fits.iter().enumerate() {
            let f = f.as_ref().unwrap();
            assert_relative_eq!(f.sensor.dir, truth.sensors[i].dir, epsilon = 1e-9);
        }
    }

    #[test]
    fn sigma_dir_is_consistent_with_the_tangent_covariance() {
        let (nominal, truth) = paper_heads();
        let poses = run(&truth, PAPER, 100, 0.01, 23);
        let f = fit_sensor_base(
            &nominal.sensors[0],
            0,
            poses.as_slice(),
            &LsqConfig::default(),
        )
        .unwrap();
        let sd = f.sigma_dir();
        // |σ_u|² = σ_α² + σ_β² (the direction moves in its tangent plane)
        assert_relative_eq!(
            sd.norm_squared(),
            f.sigma[3] * f.sigma[3] + f.sigma[4] * f.sigma[4],
            max_relative = 1e-9
        );
        assert_relative_eq!(f.sigma_zero()[2], f.sigma[2]);
    }
}
