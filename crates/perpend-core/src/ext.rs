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
//!      + Σ_k c_k·N_k(f − d_ref)                 linearity table (natural spline)
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
//! The linearity table is the natural cubic spline through the points
//! `(ξ_0, 0), (ξ_1, v_0), (ξ_2, v_1), (ξ_3, v_2), (ξ_4, 0)` (knots about
//! `d_ref`, [`TABLE_KNOTS`] of them): `v_j` is the linearity error at an
//! interior knot relative to the chord through the end knots. The spline is
//! the textbook one (second derivatives `M_i` from the tridiagonal system,
//! `M_0 = M_4 = 0`; e.g. de Boor, *A Practical Guide to Splines*, ch. IV),
//! linear beyond the end knots (a natural spline does not extrapolate a
//! curvature). Its offset and slope are the zero point's and the gain's
//! job: pinning the ends to 0 keeps the table independent of both.
//!
//! The values, not the coefficients of a truncated-power basis, are stored
//! and fitted: the cardinal functions (the table with one `v_j = 1`) are
//! bounded and nearly local, so the fit is well conditioned where the
//! truncated powers of the same space are nearly collinear (condition
//! above 10⁵ on a 60-pose run). The table follows linearity errors a
//! polynomial cannot (an S-curve with a period of the measuring range);
//! the cubic `nonlinearity` and the table are alternatives (both span
//! nearly the same curvature), the host fits one or the other.
//!
//! Limits: the inversion needs `|∂δ/∂f| < 1` (a gain, slope or carry-over
//! above 100 % is no sensor); the coefficients are checked for
//! plausibility where they are fitted, not here.

use crate::Real;

/// Knots of the linearity table.
pub const TABLE_KNOTS: usize = 5;
/// Coefficients of the linearity table (the spline's non-linear part).
pub const TABLE_COEFFS: usize = TABLE_KNOTS - 2;

/// Linearity table: a natural cubic spline in `f − d_ref` through zero at
/// the end knots and `coeffs` at the interior ones (module docs). All values
/// zero = no table (the knots are then ignored).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinTable<T: Real> {
    /// Knots `ξ_0 < … < ξ_4` [mm] about `d_ref`.
    pub knots: [T; TABLE_KNOTS],
    /// Values `v_j` [mm] of the spline at the interior knots `ξ_1..ξ_3`
    /// (the coefficients of the cardinal basis).
    pub coeffs: [T; TABLE_COEFFS],
}

impl<T: Real> LinTable<T> {
    /// No table.
    pub fn none() -> Self {
        Self {
            knots: [T::zero(); TABLE_KNOTS],
            coeffs: [T::zero(); TABLE_COEFFS],
        }
    }

    /// Whether any value is non-zero.
    #[inline]
    pub fn is_active(&self) -> bool {
        self.coeffs.iter().any(|c| *c != T::zero())
    }

    /// Whether the knots are finite and strictly ascending (a table with
    /// coinciding knots has no spline).
    pub fn knots_valid(&self) -> bool {
        self.knots.iter().all(|k| k.is_finite_real()) && self.knots.windows(2).all(|w| w[1] > w[0])
    }

    /// The spline ready to evaluate (its second derivatives solved once);
    /// `None` for invalid knots (then nothing is applied).
    pub fn spline(&self) -> Option<Spline<T>> {
        if !self.knots_valid() {
            return None;
        }
        let mut y = [T::zero(); TABLE_KNOTS];
        y[1..TABLE_KNOTS - 1].copy_from_slice(&self.coeffs);
        let m = second_derivatives(&self.knots, &y);
        Some(Spline {
            k: self.knots,
            y,
            m,
        })
    }

    /// The spline and its slope at `x`; zeros for invalid knots.
    pub fn eval(&self, x: T) -> (T, T) {
        self.spline().map_or((T::zero(), T::zero()), |s| s.eval(x))
    }

    /// `Σ_j v_j·C_j(x)`: the table's value.
    pub fn value(&self, x: T) -> T {
        self.eval(x).0
    }

    /// Its derivative in `x`.
    pub fn slope(&self, x: T) -> T {
        self.eval(x).1
    }

    /// The cardinal functions `C_j(x)` (the table with `v_j = 1`, the
    /// others 0): the regressors of a fit, `value = Σ_j v_j·C_j`.
    pub fn basis(&self, x: T) -> [T; TABLE_COEFFS] {
        let mut out = [T::zero(); TABLE_COEFFS];
        for (j, o) in out.iter_mut().enumerate() {
            let mut unit = Self {
                knots: self.knots,
                coeffs: [T::zero(); TABLE_COEFFS],
            };
            unit.coeffs[j] = T::one();
            *o = unit.value(x);
        }
        out
    }
}

/// A [`LinTable`] with its second derivatives solved: what
/// [`Extension::correct`] evaluates in every Newton step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spline<T: Real> {
    k: [T; TABLE_KNOTS],
    y: [T; TABLE_KNOTS],
    m: [T; TABLE_KNOTS],
}

impl<T: Real> Spline<T> {
    /// Value and slope at `x` (module docs; linear beyond the end knots).
    pub fn eval(&self, x: T) -> (T, T) {
        let (k, y, m) = (&self.k, &self.y, &self.m);
        let last = TABLE_KNOTS - 1;
        // The interval [ξ_i, ξ_i+1] holding x (the outer ones extended).
        let i = (1..last).take_while(|&j| x >= k[j]).count();
        let h = k[i + 1] - k[i];
        let sixth = T::lit(1.0 / 6.0);
        let half = T::lit(0.5);
        let b = (y[i + 1] - y[i]) / h - h * (T::lit(2.0) * m[i] + m[i + 1]) * sixth;
        if x < k[0] {
            return (b * (x - k[0]), b);
        }
        if x > k[last] {
            let s = b + h * (m[i] + m[i + 1]) * half;
            return (s * (x - k[last]), s);
        }
        let t = x - k[i];
        let c3 = (m[i + 1] - m[i]) * sixth / h;
        let v = y[i] + t * (b + t * (m[i] * half + t * c3));
        let s = b + t * (m[i] + T::lit(3.0) * c3 * t);
        (v, s)
    }
}

/// Second derivatives `M_i` of the natural cubic spline through
/// `(k_i, y_i)`: `M_0 = M_4 = 0` and, for the interior knots,
/// `h_{i−1}·M_{i−1} + 2(h_{i−1} + h_i)·M_i + h_i·M_{i+1} = 6·(Δ_i − Δ_{i−1})`
/// with `Δ_i = (y_{i+1} − y_i)/h_i`, solved by the Thomas algorithm
/// (diagonally dominant: stable without pivoting). Knots must ascend.
fn second_derivatives<T: Real>(k: &[T; TABLE_KNOTS], y: &[T; TABLE_KNOTS]) -> [T; TABLE_KNOTS] {
    let h = |i: usize| k[i + 1] - k[i];
    let slope = |i: usize| (y[i + 1] - y[i]) / h(i);
    let mut m = [T::zero(); TABLE_KNOTS];
    // forward sweep: diag' and rhs' per interior row
    let mut diag = [T::zero(); TABLE_KNOTS];
    let mut rhs = [T::zero(); TABLE_KNOTS];
    for i in 1..TABLE_KNOTS - 1 {
        diag[i] = T::lit(2.0) * (h(i - 1) + h(i));
        rhs[i] = T::lit(6.0) * (slope(i) - slope(i - 1));
        if i > 1 {
            let w = h(i - 1) / diag[i - 1];
            diag[i] -= w * h(i - 1);
            let r = w * rhs[i - 1];
            rhs[i] -= r;
        }
    }
    for i in (1..TABLE_KNOTS - 1).rev() {
        m[i] = (rhs[i] - h(i) * m[i + 1]) / diag[i];
    }
    m
}

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
    /// Linearity table (natural spline); an alternative to `nonlinearity`.
    pub table: LinTable<T>,
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
            table: LinTable::none(),
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
        let spline = self.table_spline();
        let (g, _) = self.moving(f, d_prev.is_some(), spline.as_ref());
        self.fixed(d_prev, cos_gamma, ctx) + g
    }

    /// The table's spline when it is active and valid.
    #[inline]
    fn table_spline(&self) -> Option<Spline<T>> {
        if self.table.is_active() {
            self.table.spline()
        } else {
            None
        }
    }

    /// The terms of the excess that do not depend on `f`: incidence,
    /// thermal, drift and the previous channel's share of the carry-over.
    #[inline]
    fn fixed(&self, d_prev: Option<T>, cos_gamma: T, ctx: &Context<T>) -> T {
        let mut c = T::zero();
        if self.incidence != T::zero() && cos_gamma > T::zero() {
            c += self.incidence * (T::one() / cos_gamma - T::one());
        }
        if let Some(p) = d_prev {
            c += self.crosstalk * p;
        }
        if let Some(t) = ctx.temp_c {
            c += self.thermal * (t - self.temp_ref);
        }
        if let Some(t) = ctx.t_s {
            c += self.drift * t;
        }
        c
    }

    /// The terms that do depend on `f` (gain, polynomial, table, the
    /// carry-over's `−crosstalk·f` when there is a previous channel) and
    /// their slope `∂δ/∂f`, the table's spline prepared by the caller.
    #[inline]
    fn moving(&self, f: T, has_prev: bool, spline: Option<&Spline<T>>) -> (T, T) {
        let x = f - self.d_ref;
        let [q, c] = self.nonlinearity;
        let mut delta = x * (self.gain + x * (q + x * c));
        let mut slope = self.gain + x * (T::lit(2.0) * q + T::lit(3.0) * c * x);
        if let Some(sp) = spline {
            let (v, s) = sp.eval(x);
            delta += v;
            slope += s;
        }
        if has_prev {
            delta -= self.crosstalk * f;
            slope -= self.crosstalk;
        }
        (delta, slope)
    }

    /// Whether the excess depends on the distance itself through gain,
    /// polynomial or crosstalk (the table is checked by the caller): then
    /// [`Extension::correct`] iterates.
    #[inline]
    fn depends_on_distance(&self) -> bool {
        self.gain != T::zero()
            || self.nonlinearity[0] != T::zero()
            || self.nonlinearity[1] != T::zero()
            || self.crosstalk != T::zero()
    }

    /// The true distance `f` that makes reading `d`: the solution of
    /// `f + δ(f) = d` (module docs): exactly `d − δ` when the excess does
    /// not depend on `f`, else Newton steps from `f = d` (at most four),
    /// stopping after a step below 10⁻⁶ of the reading: quadratic
    /// convergence makes the next one far below an f32 reading's
    /// resolution, so two steps are the rule. The table's spline is solved
    /// once per call and the terms that do not depend on `f` are summed
    /// once.
    #[inline]
    pub fn correct(&self, d: T, d_prev: Option<T>, cos_gamma: T, ctx: &Context<T>) -> T {
        let c0 = self.fixed(d_prev, cos_gamma, ctx);
        let spline = self.table_spline();
        let sp = spline.as_ref();
        if sp.is_none() && !self.depends_on_distance() {
            return d - c0;
        }
        let has_prev = d_prev.is_some();
        let tol = T::lit(1e-6) * (T::one() + d.abs());
        let mut f = d;
        for _ in 0..4 {
            let (g, s) = self.moving(f, has_prev, sp);
            let j = T::one() + s;
            if !(j.abs() > T::lit(1e-3)) {
                break;
            }
            let step = (f + c0 + g - d) / j;
            f -= step;
            if step.abs() <= tol {
                break;
            }
        }
        f
    }

    /// Whether every coefficient is finite.
    pub fn is_finite(&self) -> bool {
        let t = &self.table;
        t.knots
            .iter()
            .chain(t.coeffs.iter())
            .all(|x| x.is_finite_real())
            && [
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
            table: LinTable {
                knots: self.table.knots.map(c),
                coeffs: self.table.coeffs.map(c),
            },
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
            table: LinTable {
                knots: [-6.0, -3.0, 0.0, 2.0, 6.0],
                coeffs: [1e-3, -2e-3, 1.5e-3],
            },
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
            table: LinTable::none(),
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
            table: LinTable::none(),
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

    fn table() -> LinTable<f64> {
        LinTable {
            knots: [-6.0, -3.0, 0.0, 2.0, 6.0],
            coeffs: [1e-3, -2e-3, 1.5e-3],
        }
    }

    /// By hand: knots 0..4, values (0, 0, 1, 0, 0). The system gives
    /// `M_1 = M_3 = 18/7`, `M_2 = −30/7`, so on `[0, 1]` the spline is
    /// `−3/7·t + 3/7·t³`: `−9/56` at 0.5 with slope `−3/28`, and `∓3/7`
    /// per mm beyond the ends.
    #[test]
    fn table_hand_computed() {
        let t = LinTable {
            knots: [0.0, 1.0, 2.0, 3.0, 4.0],
            coeffs: [0.0, 1.0, 0.0],
        };
        assert_relative_eq!(t.value(0.5), -9.0 / 56.0, epsilon = 1e-12);
        assert_relative_eq!(t.slope(0.5), -3.0 / 28.0, epsilon = 1e-12);
        assert_relative_eq!(t.value(3.5), -9.0 / 56.0, epsilon = 1e-12);
        assert_relative_eq!(t.value(-1.0), 3.0 / 7.0, epsilon = 1e-12);
        assert_relative_eq!(t.value(5.0), 3.0 / 7.0, epsilon = 1e-12);
        assert_relative_eq!(t.value(2.0), 1.0, epsilon = 1e-12);
        assert_eq!(t.basis(2.0), [0.0, 1.0, 0.0]);
    }

    /// The table passes through its values (0 at the end knots), and its
    /// basis reproduces it.
    #[test]
    fn table_interpolates_its_values() {
        let t = table();
        for (j, v) in t.coeffs.iter().enumerate() {
            assert_relative_eq!(t.value(t.knots[j + 1]), *v, epsilon = 1e-15);
        }
        assert_relative_eq!(t.value(t.knots[0]), 0.0, epsilon = 1e-15);
        assert_relative_eq!(t.value(t.knots[4]), 0.0, epsilon = 1e-15);
        for x in [-7.0, -2.0, 0.7, 5.5, 9.0] {
            let b = t.basis(x);
            let sum: f64 = b.iter().zip(t.coeffs.iter()).map(|(b, c)| b * c).sum();
            assert_relative_eq!(sum, t.value(x), epsilon = 1e-15);
        }
    }

    /// A natural spline: linear beyond the end knots (no curvature to
    /// extrapolate), twice continuously differentiable at every knot, and
    /// `slope` is the derivative of `value`.
    #[test]
    fn table_is_a_natural_spline() {
        let t = table();
        let h = 1e-4;
        let curv = |x: f64| (t.value(x + h) - 2.0 * t.value(x) + t.value(x - h)) / (h * h);
        for x in [-40.0, -6.5, 6.5, 9.0, 40.0] {
            assert_relative_eq!(curv(x), 0.0, epsilon = 1e-6);
        }
        for k in t.knots {
            let (a, b) = (k - 1e-3, k + 1e-3);
            assert_relative_eq!(t.value(a), t.value(b), epsilon = 1e-4);
            assert_relative_eq!(t.slope(a), t.slope(b), epsilon = 1e-4);
            assert_relative_eq!(curv(a), curv(b), epsilon = 1e-3);
        }
        for x in [-7.0, -4.2, -0.3, 1.7, 5.0, 8.0] {
            let fd = (t.value(x + h) - t.value(x - h)) / (2.0 * h);
            assert_relative_eq!(t.slope(x), fd, epsilon = 1e-7);
        }
    }

    /// Knots that coincide or go backwards give no basis (no division by
    /// zero, nothing applied); the inversion still holds with a table alone.
    #[test]
    fn table_with_bad_knots_applies_nothing() {
        let mut t = table();
        t.knots[2] = t.knots[1];
        assert!(!t.knots_valid());
        assert_eq!(t.value(1.0), 0.0);
        let e = Extension {
            d_ref: 40.0,
            table: table(),
            ..Extension::identity()
        };
        let ctx = Context::default();
        for f in [30.0, 37.0, 40.5, 44.0, 49.0] {
            let d = f + e.excess(f, None, 1.0, &ctx);
            assert_relative_eq!(e.correct(d, None, 1.0, &ctx), f, epsilon = 1e-9);
        }
    }
}
