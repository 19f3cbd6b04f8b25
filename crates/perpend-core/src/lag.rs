//! First-order lag of a sampled signal: the temperature of the sensor
//! bodies behind the head thermometer.
//!
//! A sensor body exchanges heat with the head through a thermal resistance:
//! its temperature `y` follows the measured head temperature `u` as
//! `τ·dy/dt = u − y` (Newton's law of cooling, one lumped capacity). Where
//! a warm-up is still under way the sensors are colder than the thermometer
//! says, and a thermal coefficient applied to the thermometer's reading
//! over-corrects early and under-corrects late; applied to `y` it does not.
//! `τ = 0` is no lag (`y = u`).
//!
//! [`step`] advances `y` over one interval `dt` in which the input moves
//! linearly from `u0` to `u1` (first-order hold): exactly
//!
//! ```text
//! y(dt) = u1 + (y0 − u0)·a − (u1 − u0)·φ,   a = exp(−dt/τ),
//!                                           φ = (1 − a)·τ/dt
//! ```
//!
//! (`φ → 1` as `dt/τ → 0`; `1 − a` is computed as `−expm1(−dt/τ)`, so a
//! short step loses no digits to cancellation). The result is exact for
//! any `dt`, so the board may step at its own pace and the host at the
//! poses' times and both get the same `y` for the same input.
//!
//! Precision on the board (`f32`): a step changes `y` by about
//! `(u − y)·dt/τ`; stepped every millisecond at `τ = 600 s` that is a few
//! units in the last place of a temperature of 30 °C, and the rounding of
//! each step accumulates. The caller steps at the temperature's own rate
//! (about once per second), where the change is a thousand ulps. The step
//! is evaluated as the increment `y0 + (u0 − y0)·(1 − a) + (u1 − u0)·(1 −
//! φ)` (the same closed form): `a` itself, rounded near 1, would carry an
//! error of half an ulp of 1 into every step's decay, a systematic error
//! of τ of up to 0.3 % at `dt/τ = 1e-5` (1 s steps at τ = 1 day: 4.5e-3 °C
//! after a day towards a 10 °C step, 5.6e-4 °C as an increment; tests).
//!
//! Limits: the input between steps is taken as linear. A negative, zero or
//! non-finite `τ`, or a non-finite `dt`, is no lag (`u1` is returned); a
//! `dt ≤ 0`, or one so short against `τ` that `dt/τ` rounds to 0, leaves
//! `y0`.

use crate::Real;

/// `y` after an interval `dt` [s] in which the input went linearly from
/// `u0` to `u1`, for a first-order lag of time constant `tau` [s] that
/// was at `y0` (module docs). `tau ≤ 0` (or not finite) returns `u1`;
/// `dt ≤ 0`, or `dt/tau` rounding to 0, returns `y0`.
pub fn step<T: Real>(y0: T, u0: T, u1: T, dt: T, tau: T) -> T {
    if !(tau > T::zero()) || !tau.is_finite_real() || !dt.is_finite_real() {
        return u1;
    }
    match coefficients(dt, tau) {
        Some((one_minus_a, phi)) => increment(y0, u0, u1, one_minus_a, phi),
        None => y0,
    }
}

/// `(1 − a, φ)` of a step of `dt` [s] at time constant `tau` [s] (positive
/// and finite): `1 − a = −expm1(−dt/τ)`, `φ = (1 − a)·τ/dt`; `None` for
/// `dt ≤ 0` or `dt/τ` rounding to 0 (the step leaves `y0`). With
/// [`increment`] they are [`step`], bit for bit: a caller stepping many
/// times over the same `dt` computes them once.
pub fn coefficients<T: Real>(dt: T, tau: T) -> Option<(T, T)> {
    if !(dt > T::zero()) {
        return None;
    }
    let x = dt / tau;
    if !(x > T::zero()) {
        return None;
    }
    let b = -(-x).exp_m1();
    Some((b, b / x))
}

/// `y0` moved by the step of [`step`] written as an increment,
/// `y0 + (u0 − y0)·(1 − a) + (u1 − u0)·(1 − φ)` (module docs,
/// "Precision"), from `one_minus_a` = `1 − a` and `phi` = `φ`
/// ([`coefficients`]): in `f32` the only rounding at the temperature's
/// magnitude is the final sum.
#[inline]
pub fn increment<T: Real>(y0: T, u0: T, u1: T, one_minus_a: T, phi: T) -> T {
    let du = u1 - u0;
    y0 + ((u0 - y0) * one_minus_a + (du - du * phi))
}

/// The lagged input at each of the times `t` (ascending, [s]) of the
/// samples `u`, starting at rest (`y = u[0]`): [`step`] between
/// consecutive samples. `out` receives one value per sample; extra
/// entries of the longer of `t`/`u`/`out` are ignored.
pub fn filter<T: Real>(t: &[T], u: &[T], tau: T, out: &mut [T]) {
    let n = t.len().min(u.len()).min(out.len());
    if n == 0 {
        return;
    }
    let mut y = u[0];
    out[0] = y;
    for k in 1..n {
        y = step(y, u[k - 1], u[k], t[k] - t[k - 1], tau);
        out[k] = y;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    /// A step input: the lag reaches `1 − e^{-t/τ}` of it.
    #[test]
    fn a_step_input_rises_exponentially() {
        let y = step(0.0_f64, 1.0, 1.0, 300.0, 600.0);
        assert_relative_eq!(y, 1.0 - (-0.5_f64).exp(), epsilon = 1e-15);
        assert_eq!(step(0.3_f64, 1.0, 1.0, 0.0, 600.0), 0.3);
        assert_eq!(step(0.3_f64, 1.0, 2.0, 5.0, 0.0), 2.0);
    }

    /// A ramp `u = r·t` from rest: `y = r·(t − τ(1 − e^{-t/τ}))`, in one
    /// step or in many uneven ones.
    #[test]
    fn a_ramp_is_followed_exactly_at_any_step() {
        let (r, tau) = (0.01_f64, 400.0);
        let exact = |t: f64| r * (t - tau * (1.0 - (-t / tau).exp()));
        assert_relative_eq!(
            step(0.0, 0.0, r * 900.0, 900.0, tau),
            exact(900.0),
            epsilon = 1e-12
        );
        let t: Vec<f64> = (0..40).map(|k| (k * k) as f64 * 0.7).collect();
        let u: Vec<f64> = t.iter().map(|x| r * x).collect();
        let mut y = vec![0.0; t.len()];
        filter(&t, &u, tau, &mut y);
        for (ti, yi) in t.iter().zip(&y) {
            assert_relative_eq!(*yi, exact(*ti), epsilon = 1e-12);
        }
    }

    /// `dt/τ` that rounds to 0 (an `f32` `dt` of 1e-45 s) leaves `y0`
    /// instead of `0/0` = NaN.
    #[test]
    fn a_step_too_short_to_count_leaves_the_state() {
        assert_eq!(step(21.0f32, 22.0, 23.0, 1e-45, 10.0), 21.0);
        assert_eq!(step(21.0f64, 22.0, 23.0, 1e-320, 1e6), 21.0);
    }

    /// `f32` steps of 1 s towards a 10 °C step, against the closed form in
    /// `f64`: at τ = 1 h (3600 steps) and τ = 1 day (86 400 steps) the
    /// error stays below 1e-4 °C and 1.5e-3 °C (with `a` rounded near 1:
    /// 5.1e-4 and 4.5e-3 °C).
    #[test]
    fn f32_steps_keep_the_time_constant() {
        for (tau, n, tol) in [(3600.0f32, 3600u32, 1e-4), (86_400.0, 86_400, 1.5e-3)] {
            let (mut y, mut worst) = (20.0f32, 0.0f64);
            for k in 1..=n {
                y = step(y, 30.0, 30.0, 1.0, tau);
                let exact = 30.0 - 10.0 * (-f64::from(k) / f64::from(tau)).exp();
                worst = worst.max((f64::from(y) - exact).abs());
            }
            assert!(worst < tol, "τ = {tau}: {worst}");
        }
    }

    /// Steps of a millisecond at a long τ agree with one step of the whole
    /// interval (no cancellation in `1 − a`).
    #[test]
    fn short_steps_lose_no_digits() {
        let tau = 600.0_f64;
        let mut y = 20.0;
        for _ in 0..1000 {
            y = step(y, 30.0, 30.0, 1e-3, tau);
        }
        assert_relative_eq!(y, step(20.0, 30.0, 30.0, 1.0, tau), epsilon = 1e-11);
        assert_relative_eq!(y - 20.0, 10.0 * (1.0 - (-1.0 / tau).exp()), epsilon = 1e-11);
    }
}
