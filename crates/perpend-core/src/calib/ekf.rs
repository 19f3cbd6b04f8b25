//! The paper's extended Kalman filter for the sensor parameters (Chen §3.2,
//! eq. 10-16), implemented as written; per sensor, one reading at a time.
//!
//! State: `X = ΔΦ_i = [Δx, Δy, Δz, Δm, Δn, Δq]ᵀ`, the error of the nominal
//! zero point and of the (unnormalised) beam direction `w = (m, n, q)`.
//!
//! ```text
//! eq. 10  X_k = X_{k-1} + w_{k-1}                 constant parameters + process noise (Q)
//! eq. 11  Z_k = H_k X_k + v_k,  Z_k = d_meas − d_nom,  H_k = J at the estimate (R)
//! eq. 12  X̂_{k|k-1} = X̂_{k-1|k-1}
//! eq. 13  P_{k|k-1} = P_{k-1|k-1} + Q
//! eq. 14  K_k = P_{k|k-1} H_kᵀ (H_k P_{k|k-1} H_kᵀ + R)⁻¹
//! eq. 15  P_{k|k} = (I − K_k H_k) P_{k|k-1}
//! eq. 16  X̂_{k|k} = X̂_{k|k-1} + K_k (Z_k − H_k X̂_{k|k-1})
//! stop:   ‖X̂_{k|k} − X̂_{k-1|k-1}‖ < δ;   X̂_0 = 0, P_0 = I
//! ```
//!
//! `d_nom` is the distance the nominal sensor would read on the pose's plane
//! and `J` is Chen eq. 9 ([`crate::model::chen_jacobian`]). The measurement
//! is scalar, so eq. 14 is a division, not a matrix inverse; one update is
//! a handful of 6-vector and 6×6 operations in fixed memory.
//!
//! Where the paper is loose, and what this implementation does:
//!
//! * **Over-parameterised direction.** The distance of eq. 3 does not change
//!   when `w` is scaled, so `J` is orthogonal to `w` and one of the six
//!   states is unobservable. At `X̂ = 0` with `P_0 = I` the gain `K = P Hᵀ/S`
//!   is orthogonal to the nominal direction, so the filter never moves along
//!   it; later the component of `P Hᵀ` along the nominal direction is
//!   `−H·Δw`, second order in the estimated change, and the variance along
//!   `w` is never reduced. This is harmless (directions are normalised before
//!   use) but makes `P` meaningless along `w`, and the 6 "1σ" values are not
//!   the uncertainty of a unit direction. The batch solver ([`super::lsq`])
//!   uses the 5-DOF form instead.
//! * **Linearised innovation.** Eq. 16 uses `Z_k − H_k X̂`, with `Z_k`
//!   linearised about the nominal sensor but `H_k` evaluated at the current
//!   estimate (eq. 11, `H_k = J|_{d̂_{i,k|k-1}}`): the first-order prediction
//!   of `d_meas − d_nom` is only consistent when `J` is constant. With errors
//!   of 1.5 mm / 0.07 rad the neglected curvature is a few µm per reading.
//!   [`Innovation::Linearised`] is the paper's form (default);
//!   [`Innovation::Nonlinear`] uses the standard EKF innovation
//!   `d_meas − f(Φ_nom + X̂)`.
//! * **Noise values.** §3.2 gives `R = 10⁻⁴` (the square of the simulated
//!   ζ = 0.01 mm), §5 step 7 uses `R = 8·10⁻⁵` and §6 `R = 9·10⁻⁶`; none
//!   includes the tracker's plane-fit error. `Q > 0` for constant parameters
//!   keeps the gain from vanishing. See the named constructors of
//!   [`EkfConfig`].
//! * **Stopping rule.** `‖ΔX̂‖ < δ` mixes millimetres and (unitless)
//!   direction components and tests a single step: one reading whose
//!   innovation happens to be small stops the filter. Implemented as written;
//!   the number of readings used is reported (Chen Table 3).
//! * **Covariance update.** Eq. 15 (default) loses symmetry and, in `f32`,
//!   can lose positive definiteness once `P` has shrunk by ~7 orders of
//!   magnitude from `P_0 = I`; `P` is symmetrised after every update.
//!   [`CovarianceUpdate::Joseph`] is the numerically safer
//!   `(I−KH)P(I−KH)ᵀ + K R Kᵀ`, identical in exact arithmetic.
//!
//! Limits: the beam must meet the plane in front of the sensor at the
//! nominal and at the estimated parameters (errors of [`chen_jacobian`]).

use nalgebra::{SMatrix, SVector, Vector3};

use super::Poses;
use crate::geometry::Plane;
use crate::head::Sensor;
use crate::model::chen_jacobian;
use crate::{finite, Error, Real, Result};

/// Number of states: Chen's `ΔΦ = [Δx, Δy, Δz, Δm, Δn, Δq]`.
pub const STATES: usize = 6;

/// A state vector `ΔΦ` [mm, mm, mm, -, -, -].
pub type State<T> = SVector<T, STATES>;

/// A 6×6 covariance.
pub type Cov<T> = SMatrix<T, STATES, STATES>;

/// Which innovation eq. 16 uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Innovation {
    /// The paper's `Z_k − H_k X̂_{k|k-1}` with `Z_k = d_meas − d_nom`.
    #[default]
    Linearised,
    /// The standard EKF innovation `d_meas − f(Φ_nom + X̂_{k|k-1})`.
    Nonlinear,
}

/// How the covariance is updated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CovarianceUpdate {
    /// Chen eq. 15, `P = (I − K H) P⁻`, then symmetrised.
    #[default]
    Paper,
    /// Joseph form `(I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ`, then symmetrised.
    Joseph,
}

/// Filter settings (Chen §3.2). `Q` and `P_0` are diagonal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EkfConfig<T: Real> {
    /// Diagonal of the process noise covariance `Q` (eq. 13).
    pub q: State<T>,
    /// Measurement noise variance `R` [mm²] (eq. 14).
    pub r: T,
    /// Diagonal of the initial covariance `P_0`.
    pub p0: State<T>,
    /// Initial state `X̂_0`.
    pub x0: State<T>,
    /// Stopping threshold `δ` on `‖X̂_k − X̂_{k-1}‖`.
    pub delta: T,
    /// Innovation form of eq. 16.
    pub innovation: Innovation,
    /// Covariance update form of eq. 15.
    pub covariance: CovarianceUpdate,
}

impl<T: Real> EkfConfig<T> {
    fn chen(q: f64, r: f64) -> Self {
        Self {
            q: State::from_element(T::lit(q)),
            r: T::lit(r),
            p0: State::from_element(T::one()),
            x0: State::zeros(),
            delta: T::lit(1e-4),
            innovation: Innovation::Linearised,
            covariance: CovarianceUpdate::Paper,
        }
    }

    /// The paper's simulation (§5 step 7): `Q = 10⁻¹⁰·I`, `R = 8·10⁻⁵`,
    /// `P_0 = I`, `X̂_0 = 0`, `δ = 10⁻⁴`.
    pub fn chen_simulation() -> Self {
        Self::chen(1e-10, 8e-5)
    }

    /// The paper's experiment (§6): `Q = 10⁻¹²·I`, `R = 9·10⁻⁶`, otherwise
    /// as [`EkfConfig::chen_simulation`].
    pub fn chen_experiment() -> Self {
        Self::chen(1e-12, 9e-6)
    }

    /// The values printed in §3.2: `Q = 10⁻¹⁰·I`, `R = 10⁻⁴`.
    pub fn chen_section3() -> Self {
        Self::chen(1e-10, 1e-4)
    }

    /// Checks the ranges: `R > 0`, `Q ≥ 0`, `P_0 > 0`, `δ ≥ 0`, all finite.
    ///
    /// # Errors
    /// [`Error::OutOfRange`] naming the offending value.
    pub fn validate(&self) -> Result<()> {
        let ok = |x: T| x.is_finite_real();
        if !(ok(self.r) && self.r > T::zero()) {
            return Err(Error::OutOfRange("EKF R"));
        }
        if !self.q.iter().all(|&x| ok(x) && x >= T::zero()) {
            return Err(Error::OutOfRange("EKF Q"));
        }
        if !self.p0.iter().all(|&x| ok(x) && x > T::zero()) {
            return Err(Error::OutOfRange("EKF P0"));
        }
        if !self.x0.iter().all(|&x| ok(x)) {
            return Err(Error::OutOfRange("EKF X0"));
        }
        if !(ok(self.delta) && self.delta >= T::zero()) {
            return Err(Error::OutOfRange("EKF delta"));
        }
        Ok(())
    }
}

/// What one update did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Step<T: Real> {
    /// The innovation of eq. 16 [mm] (0 when the filter had already stopped).
    pub innovation: T,
    /// `‖X̂_{k|k} − X̂_{k-1|k-1}‖` (0 when it had already stopped).
    pub change: T,
    /// Whether the stopping rule holds now (further updates are ignored).
    pub stopped: bool,
}

/// The filter of one sensor: fixed memory (a 6-vector and a 6×6 matrix).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ekf<T: Real> {
    idx: usize,
    zero: Vector3<T>,
    dir: Vector3<T>,
    x: State<T>,
    p: Cov<T>,
    cfg: EkfConfig<T>,
    updates: usize,
    stopped: bool,
}

impl<T: Real> Ekf<T> {
    /// A filter for sensor `idx` (0-based, for error reports) whose nominal
    /// parameters `Φ_nom` are `nominal`'s zero point and (unit) direction.
    ///
    /// # Errors
    /// Those of [`EkfConfig::validate`].
    pub fn new(nominal: &Sensor<T>, idx: usize, cfg: EkfConfig<T>) -> Result<Self> {
        cfg.validate()?;
        Ok(Self {
            idx,
            zero: nominal.zero,
            dir: nominal.dir,
            x: cfg.x0,
            p: Cov::from_diagonal(&cfg.p0),
            cfg,
            updates: 0,
            stopped: false,
        })
    }

    /// Processes one reading `d_meas` of the plane `plane` (eq. 11-16) and
    /// applies the stopping rule. After the rule has held, further calls
    /// change nothing and return `stopped = true`.
    ///
    /// On error the filter is left unchanged.
    ///
    /// # Errors
    /// [`Error::NonFinite`] for a non-finite reading or a non-finite result,
    /// [`Error::NegativeDistance`], and the errors of
    /// [`crate::model::chen_jacobian`] at the nominal or estimated sensor.
    pub fn update(&mut self, plane: &Plane<T>, d_meas: T) -> Result<Step<T>> {
        if self.stopped {
            return Ok(Step {
                innovation: T::zero(),
                change: T::zero(),
                stopped: true,
            });
        }
        finite(d_meas, "reading")?;
        if d_meas < T::zero() {
            return Err(Error::NegativeDistance(self.idx));
        }
        let x = self.x;
        // eq. 12-13: prediction.
        let mut p = self.p;
        for i in 0..STATES {
            p[(i, i)] += self.cfg.q[i];
        }
        // eq. 11: H_k = J at the current estimate Φ_nom + X̂.
        let zero_hat = self.zero + Vector3::new(x[0], x[1], x[2]);
        let w_hat = self.dir + Vector3::new(x[3], x[4], x[5]);
        let (d_hat, h) = chen_jacobian(&zero_hat, &w_hat, plane, self.idx)?;
        let innovation = match self.cfg.innovation {
            Innovation::Linearised => {
                let (d_nom, _) = chen_jacobian(&self.zero, &self.dir, plane, self.idx)?;
                (d_meas - d_nom) - h.dot(&x)
            }
            Innovation::Nonlinear => d_meas - d_hat,
        };
        // eq. 14: scalar innovation variance, no matrix inverse.
        let ph = p * h;
        let s = h.dot(&ph) + self.cfg.r;
        if !(s > T::zero()) || !s.is_finite_real() {
            return Err(Error::NonFinite("EKF innovation variance"));
        }
        let k = ph / s;
        // eq. 16.
        let x_new = x + k * innovation;
        // eq. 15 (P⁻ symmetric: K H P⁻ = K (P⁻ Hᵀ)ᵀ).
        let p_new = match self.cfg.covariance {
            CovarianceUpdate::Paper => p - k * ph.transpose(),
            CovarianceUpdate::Joseph => {
                let ikh = Cov::<T>::identity() - k * h.transpose();
                ikh * p * ikh.transpose() + k * k.transpose() * self.cfg.r
            }
        };
        let p_new = (p_new + p_new.transpose()) * T::lit(0.5);
        if !x_new.iter().chain(p_new.iter()).all(|v| v.is_finite_real()) {
            return Err(Error::NonFinite("EKF state"));
        }
        let change = (x_new - x).norm();
        self.x = x_new;
        self.p = p_new;
        self.updates += 1;
        self.stopped = change < self.cfg.delta;
        Ok(Step {
            innovation,
            change,
            stopped: self.stopped,
        })
    }

    /// The current estimate `X̂ = ΔΦ`.
    pub fn state(&self) -> &State<T> {
        &self.x
    }

    /// The current covariance `P`.
    pub fn covariance(&self) -> &Cov<T> {
        &self.p
    }

    /// `sqrt(diag P)`: the filter's 1σ of each state (see the module docs on
    /// what it means along the beam direction).
    pub fn sigma(&self) -> State<T> {
        State::from_fn(|i, _| self.p[(i, i)].max(T::zero()).sqrt())
    }

    /// Number of readings processed (Chen Table 3 counts these until the
    /// stop).
    pub fn updates(&self) -> usize {
        self.updates
    }

    /// Whether the stopping rule has held.
    pub fn stopped(&self) -> bool {
        self.stopped
    }

    /// The modified sensor `Φ_mod = Φ_nom + ΔΦ` (Chen §3.2), direction
    /// normalised.
    ///
    /// # Errors
    /// [`Error::ZeroLength`] if the estimated direction vanished.
    pub fn sensor(&self) -> Result<Sensor<T>> {
        let x = &self.x;
        Sensor::new(
            self.zero + Vector3::new(x[0], x[1], x[2]),
            self.dir + Vector3::new(x[3], x[4], x[5]),
        )
    }
}

/// Result of running the filter over a calibration run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EkfFit<T: Real> {
    /// The modified sensor `Φ_nom + ΔΦ` (direction normalised).
    pub sensor: Sensor<T>,
    /// The estimate `ΔΦ`.
    pub state: State<T>,
    /// Its covariance `P`.
    pub covariance: Cov<T>,
    /// Readings processed until the stop (Chen Table 3), or all of them.
    pub used: usize,
    /// Valid readings of this sensor in the run.
    pub available: usize,
    /// Whether the stopping rule held before the data ran out.
    pub converged: bool,
}

/// Runs the filter of sensor `idx` over the poses in order, skipping
/// missing readings, until the stopping rule holds or the data ends.
///
/// # Errors
/// Those of [`Ekf::new`] and [`Ekf::update`], and
/// [`Error::TooFewReadings`] when the sensor has no reading at all.
pub fn ekf_sensor<T: Real, P: Poses<T> + ?Sized>(
    nominal: &Sensor<T>,
    idx: usize,
    poses: &P,
    cfg: EkfConfig<T>,
) -> Result<EkfFit<T>> {
    let mut ekf = Ekf::new(nominal, idx, cfg)?;
    let mut available = 0usize;
    for k in 0..poses.len() {
        if let Some(d) = poses.reading(k, idx) {
            available += 1;
            if !ekf.stopped() {
                ekf.update(&poses.plane(k), d)?;
            }
        }
    }
    if available == 0 {
        return Err(Error::TooFewReadings(0));
    }
    Ok(EkfFit {
        sensor: ekf.sensor()?,
        state: ekf.x,
        covariance: ekf.p,
        used: ekf.updates(),
        available,
        converged: ekf.stopped(),
    })
}
