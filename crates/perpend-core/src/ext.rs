//! Model extensions: corrections of a reading for effects the paper's
//! zero-point + beam-direction model (Chen §3.1) does not contain.
//!
//! Each coefficient belongs to the stored calibration of one sensor and is
//! zero (no correction) by default. The reading model is explicit: the
//! sensor outputs the true distance `f` plus an excess `δ(f)`, linear in
//! the coefficients:
//!
//! ```text
//! d = f + δ(f)
//! δ(f) = gain·(f − d_ref)                      analog-chain scale error
//!      + nl2·(f − d_ref)² + nl3·(f − d_ref)³   polynomial linearity error
//!      + incidence·(1/cos γ − 1)               γ: angle beam ↔ surface normal
//!      + crosstalk·(d_prev − f)                S&H carry-over from the channel
//!                                              converted just before
//!      + thermal·(T − T_ref)                   head temperature [°C]
//!      + drift·t                               time since start of run [s]
//! ```
//!
//! The host fits it with the terms evaluated on the distance the geometry
//! predicts (never on the reading being predicted: no target leakage, see
//! [`crate::calib::regress`]). The board has only the reading, so
//! [`Extension::correct`] inverts the model: `f + δ(f) = d` by Newton steps
//! from `f = d − δ(d)` (the slope `1 + ∂δ/∂f` is analytic); terms that do
//! not depend on `f` need none.
//!
//! Drift is for estimation only: the host passes the time since the start
//! of the calibration run so that a drifting head does not bias the zero
//! point and beam; the parameters handed to the board are referred to the
//! run's end with drift 0 (`perpend_lab::paramfile::SensorParams::fold_drift`)
//! and the board and `perpend measure` pass no time, so a drift is never
//! extrapolated past the run.
//!
//! `d_prev` is the reading of the previous channel in the ADC scan; for the
//! first channel it is the last channel of the same scan (the scan repeats
//! every period, so at steady state that is the conversion just before). A
//! missing `d_prev`, temperature or time contributes no correction.
//!
//! Limits: the inversion needs `|∂δ/∂f| < 1` (a gain, slope or carry-over
//! above 100 % is no sensor); the coefficients are checked for
//! plausibility where they are fitted, not here.

use crate::Real;

/// Per-sensor correction coefficients (all zero = the paper's model).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Extension<T: Real> {
    /// Reference distance [mm] about which gain and non-linearity act
    /// (mid-range of the sensor; an offset at `d_ref` is the zero point's job).
    pub d_ref: T,
    /// Relative scale error of the analog chain [-].
    pub gain: T,
    /// Quadratic and cubic linearity error [mm⁻¹, mm⁻²].
    pub nonlinearity: [T; 2],
    /// Incidence bias [mm] per unit of `(1/cos γ − 1)`.
    pub incidence: T,
    /// Fraction [-] of the previous channel's reading that leaks into this one.
    pub crosstalk: T,
    /// Thermal drift [mm/°C] about `temp_ref`.
    pub thermal: T,
    /// Reference temperature [°C] of `thermal`.
    pub temp_ref: T,
    /// Drift with time [mm/s].
    pub drift: T,
}

/// What the corrections need besides the reading itself.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Context<T: Real> {
    /// Head temperature [°C], if measured.
    pub temp_c: Option<T>,
    /// Time since the start of the run [s], if known.
    pub t_s: Option<T>,
}

impl<T: Real> Default for Context<T> {
    /// Neither temperature nor time known.
    fn default() -> Self {
        Self {
            temp_c: None,
            t_s: None,
        }
    }
}

impl<T: Real> Default for Extension<T> {
    fn default() -> Self {
        Self::identity()
    }
}

impl<T: Real> Extension<T> {
    /// No correction.
    pub fn identity() -> Self {
        Self {
            d_ref: T::zero(),
            gain: T::zero(),
            nonlinearity: [T::zero(); 2],
            incidence: T::zero(),
            crosstalk: T::zero(),
            thermal: T::zero(),
            temp_ref: T::lit(20.0),
            drift: T::zero(),
        }
    }

    /// Whether the incidence term is active (then the normal is computed in
    /// two passes: the angle γ needs a first plane).
    #[inline]
    pub fn needs_incidence(&self) -> bool {
        self.incidence != T::zero()
    }

    /// The excess `δ(f)` of the reading over the true distance `f`
    /// (module docs).
    ///
    /// `d_prev` is the previous channel's reading, `cos_gamma` `|n·u|`.
    pub fn excess(&self, f: T, d_prev: Option<T>, cos_gamma: T, ctx: &Context<T>) -> T {
        let x = f - self.d_ref;
        let mut delta =
            self.gain * x + self.nonlinearity[0] * x * x + self.nonlinearity[1] * x * x * x;
        if self.incidence != T::zero() && cos_gamma > T::zero() {
            delta += self.incidence * (T::one() / cos_gamma - T::one());
        }
        if let Some(p) = d_prev {
            delta += self.crosstalk * (p - f);
        }
        if let Some(t) = ctx.temp_c {
            delta += self.thermal * (t - self.temp_ref);
        }
        if let Some(t) = ctx.t_s {
            delta += self.drift * t;
        }
        delta
    }

    /// Whether the excess depends on the distance itself (gain, linearity,
    /// crosstalk): then [`Extension::correct`] iterates.
    #[inline]
    fn depends_on_distance(&self) -> bool {
        self.gain != T::zero()
            || self.nonlinearity[0] != T::zero()
            || self.nonlinearity[1] != T::zero()
            || self.crosstalk != T::zero()
    }

    /// `∂δ/∂f`: the slope of the excess in the distance.
    #[inline]
    fn slope(&self, f: T, d_prev: Option<T>) -> T {
        let x = f - self.d_ref;
        let mut s = self.gain
            + T::lit(2.0) * self.nonlinearity[0] * x
            + T::lit(3.0) * self.nonlinearity[1] * x * x;
        if d_prev.is_some() {
            s -= self.crosstalk;
        }
        s
    }

    /// The true distance `f` that makes reading `d`: the solution of
    /// `f + δ(f) = d` (module docs): exactly `d − δ` when the excess does
    /// not depend on `f`, else three Newton steps from `f = d` (quadratic
    /// convergence: below 10⁻⁹ mm for a 5 % gain and 20 % carry-over).
    #[inline]
    pub fn correct(&self, d: T, d_prev: Option<T>, cos_gamma: T, ctx: &Context<T>) -> T {
        let mut f = d - self.excess(d, d_prev, cos_gamma, ctx);
        if self.depends_on_distance() {
            for _ in 0..3 {
                let r = f + self.excess(f, d_prev, cos_gamma, ctx) - d;
                let j = T::one() + self.slope(f, d_prev);
                if !(j.abs() > T::lit(1e-3)) {
                    break;
                }
                f -= r / j;
            }
        }
        f
    }

    /// Whether every coefficient is finite.
    pub fn is_finite(&self) -> bool {
        [
            self.d_ref,
            self.gain,
            self.nonlinearity[0],
            self.nonlinearity[1],
            self.incidence,
            self.crosstalk,
            self.thermal,
            self.temp_ref,
            self.drift,
        ]
        .iter()
        .all(|x| x.is_finite_real())
    }

    /// Converts to another float type.
    pub fn cast<U: Real>(&self) -> Extension<U> {
        let c = |x: T| U::lit(x.to_f64());
        Extension {
            d_ref: c(self.d_ref),
            gain: c(self.gain),
            nonlinearity: [c(self.nonlinearity[0]), c(self.nonlinearity[1])],
            incidence: c(self.incidence),
            crosstalk: c(self.crosstalk),
            thermal: c(self.thermal),
            temp_ref: c(self.temp_ref),
            drift: c(self.drift),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    /// `correct` inverts the reading model `d = f + δ(f)` for coefficients
    /// far beyond any plausible sensor (5 % gain, 20 % carry-over).
    #[test]
    fn correct_inverts_the_reading_model() {
        let ctx = Context {
            temp_c: Some(31.0),
            t_s: Some(600.0),
        };
        let e = Extension {
            d_ref: 40.0,
            gain: 0.05,
            nonlinearity: [2e-3, -4e-4],
            incidence: 0.02,
            crosstalk: 0.2,
            thermal: 0.003,
            temp_ref: 22.0,
            drift: -2e-5,
        };
        for f in [33.0, 38.5, 40.0, 44.0, 47.5] {
            let d = f + e.excess(f, Some(41.0), 0.9, &ctx);
            assert_relative_eq!(e.correct(d, Some(41.0), 0.9, &ctx), f, epsilon = 1e-7);
        }
        // Terms independent of f are removed exactly in one step.
        let flat = Extension {
            gain: 0.0,
            nonlinearity: [0.0; 2],
            crosstalk: 0.0,
            ..e
        };
        let d = 40.0 + flat.excess(40.0, None, 0.9, &ctx);
        assert_eq!(flat.correct(d, None, 0.9, &ctx), 40.0);
    }

    #[test]
    fn identity_changes_nothing() {
        let e = Extension::<f64>::identity();
        let ctx = Context {
            temp_c: Some(35.0),
            t_s: Some(100.0),
        };
        assert_eq!(e.correct(42.5, Some(40.0), 0.8, &ctx), 42.5);
    }

    #[test]
    fn each_term_hand_computed() {
        let ctx = Context {
            temp_c: Some(30.0),
            t_s: Some(10.0),
        };
        let e = Extension {
            d_ref: 40.0,
            gain: 1e-3,
            nonlinearity: [1e-4, 1e-5],
            incidence: 0.01,
            crosstalk: 0.002,
            thermal: 0.001,
            temp_ref: 20.0,
            drift: 1e-4,
        };
        // x = 2: gain 0.002, nl 0.0004 + 0.00008, inc 0.01*(1/0.8-1) = 0.0025,
        // xt 0.002*(40-42) = -0.004, th 0.01, drift 0.001
        let want = 0.002 + 0.0004 + 0.00008 + 0.0025 - 0.004 + 0.01 + 0.001;
        assert_relative_eq!(e.excess(42.0, Some(40.0), 0.8, &ctx), want, epsilon = 1e-12);
    }
}
