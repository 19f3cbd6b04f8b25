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
//!      + spot₁·tan²γ·cos φ + spot₂·tan²γ·sin φ  φ: azimuth of the normal's
//!                                              tilt about the beam
//!      + crosstalk·(d_prev − f)                S&H carry-over from the channel
//!                                              converted just before
//!      + thermal·(T − T_ref)                   sensor-body temperature [°C]
//!      + drift·t                               time since start of run [s]
//! ```
//!
//! The host fits it with the terms evaluated on the distance the geometry
//! predicts (never on the reading being predicted: no target leakage, see
//! [`crate::calib::regress`]). The board has only the reading, so
//! [`Extension::correct`] inverts the model: `f + δ(f) = d` by Chebyshev
//! steps from `f = d` ("Inversion" below; the slope and curvature of `δ`
//! are analytic); terms that do not depend on `f` need none.
//!
//! Drift is for estimation only: the host passes the time since the start
//! of the calibration run so that a drifting head does not bias the zero
//! point and beam; the parameters handed to the board are referred to the
//! run's end with drift 0 (`perpend_formats::paramfile::SensorParams::fold_drift`)
//! and the board and `perpend measure` pass no time, so a drift is never
//! extrapolated past the run.
//!
//! `T` is the temperature the caller passes in [`Context::temp_c`]: the
//! head thermometer's, or, where the head has a thermal time constant,
//! that reading through the first-order lag of the sensor bodies
//! ([`crate::lag`]; the board's `perpend_board::thermal`, the host's
//! `perpend_calib::lags` and `perpend measure`). The lag is state
//! over time, so it lives with the caller, not in these coefficients.
//!
//! ## Incidence
//!
//! The angles come from the plane normal `n` and the beam `u` as an
//! [`Incidence`] ([`Incidence::of`]; `n` of either orientation, taken
//! along the beam: `c = |n·u| = cos γ`). The symmetric term `1/cos γ − 1`
//! is the bias of a spot whose centroid moves along the beam with the
//! spot's size; a triangulation sensor sees the spot from its receiver's
//! side, at an azimuth `ψ` about the beam, and the centroid of the spot,
//! stretched as `tan²γ` along the tilt's azimuth `φ`, moves as
//! `k·tan²γ·cos(φ − ψ)` (the "spot" form). In a frame fixed to the beam
//! (`e₁` the head's x axis projected ⊥ `u`, or its y axis where the beam
//! is within 26° of x; `e₂ = u × e₁`) `φ = atan2(n·e₂, n·e₁)`, and
//! `k·cos(φ − ψ) = (k·cos ψ)·cos φ + (k·sin ψ)·sin φ`: the two
//! coefficients `spot = [k·cos ψ, k·sin ψ]` are linear, as the others.
//! `tan²γ·cos φ = |s|·s₁/c²` with `s = (n·e₁, n·e₂)`: no trigonometry.
//! Bounded where `c > 0`; a beam along the plane (`c = 0`) adds nothing.
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
//! ## Prepared form
//!
//! [`Extension::prepare`] turns the coefficients into what the inversion
//! evaluates, a [`Prepared`]: gain, polynomial and table (when active and
//! valid) as one piecewise cubic in the distance `f` itself (six pieces:
//! between the knots and beyond each end knot, each `a + t·(b + t·(c +
//! t·e))` about its start; the spline's second derivatives solved and the
//! polynomial re-expanded about each start once), whether the excess
//! depends on `f`, which terms fixed in `f` have a coefficient (none, the
//! thermal term alone, evaluated as `thermal·(T − T_ref)` only, or others:
//! all of them; the same sum bit for bit for finite inputs), and a
//! Lipschitz constant `L = max |6e|` of `δ''` (the spline is C², its `δ''`
//! linear on each piece). Evaluating `δ`, `δ'`, `δ''` is then a bisection
//! among the five knots and a Horner scheme, no division. It is derived
//! data, stored nowhere: prepare again whenever a coefficient changes (the
//! board prepares where its parameters are set,
//! `perpend_board::pipeline::Pipeline::new`; [`Extension::correct`]
//! prepares on every call).
//!
//! ## Inversion
//!
//! `F(f) = f + δ(f) − d = 0` is solved from `f₀ = d` by Chebyshev's method
//! (Newton's step plus its second-order term, cubic convergence; Traub,
//! *Iterative Methods for the Solution of Equations*, 1964, §5.1): with
//! `j = F'(f₀)`, `c = F''(f₀)`, Newton's step `n = F(f₀)/j` and
//! `w = c·n²/(2j)`, `f₁ = f₀ − (n + w)`. At most four evaluations of `δ`;
//! it stops after a step `|n + w| ≤ 10⁻⁶·(1 + |d|)` (the step rule), when
//! the early-stop bound below holds, or at `|j| ≤ 10⁻³` (no inversion).
//!
//! ## Early stop
//!
//! With `u = n + w` the quadratic model `F(f₀) − j·u + c·u²/2` is
//! `c·w·(2n + w)/2` (as `j·w = c·n²/2`), and Taylor's remainder with a
//! Lipschitz `δ''` is at most `L·|u|³/6`, so
//! `|F(f₁)| ≤ r = |c|·|w|·(2|n| + |w|)/2 + L·|u|³/6`. Within `D = |u| + ε`
//! of `f₀` the slope is at least `m = |j| − |c|·D − L·D²/2`. If `r ≤ ε·m`,
//! `F` is monotone on `[f₁ − ε, f₁ + ε]` and changes there by at least
//! `ε·m ≥ |F(f₁)|` either side, so the root lies within `ε` of `f₁` and
//! the confirming evaluation is skipped. `ε` is the step rule's
//! `10⁻⁶·(1 + |d|)` in `f32`, and 16 units of roundoff of `1 + |d|` in
//! `f64` (so the host's results stay those of the converged iteration).
//! The bound holds in exact arithmetic; evaluating in `f32` adds a few
//! units in the last place of `d`. For a table as on the board (knots at
//! ±0.75 and ±1.5 mm about `d_ref`, values 30, −40, 25 µm: `|c| ≤ 0.56
//! mm⁻¹`, `L ≈ 1.3 mm⁻²`) one step leaves `r ≤ 2.4·10⁻⁵ mm` across the
//! knots, below `ε ≈ 5·10⁻⁵ mm` at 47 mm: one evaluation per reading,
//! where Newton's steps with the step rule took two or three (tested).
//!
//! Limits: the inversion needs `|∂δ/∂f| < 1` (a gain, slope or carry-over
//! above 100 % is no sensor); the coefficients are checked for
//! plausibility where they are fitted, not here.

use nalgebra::Vector3;

use crate::Real;

/// The beam's angles to the surface that the incidence terms take (module
/// docs, "Incidence").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Incidence<T: Real> {
    /// `cos γ = |n·u|`.
    pub cos_gamma: T,
    /// `[tan²γ·cos φ, tan²γ·sin φ]` in the beam's fixed frame.
    pub spot: [T; 2],
}

impl<T: Real> From<T> for Incidence<T> {
    /// `cos γ` alone: the azimuth unknown, the spot terms contribute 0
    /// (what a caller without the plane normal, or a head without spot
    /// coefficients, passes).
    fn from(cos_gamma: T) -> Self {
        Self {
            cos_gamma,
            spot: [T::zero(); 2],
        }
    }
}

impl<T: Real> Incidence<T> {
    /// The angles of beam `u` (unit) on a surface of unit normal `n` of
    /// either orientation (module docs, "Incidence").
    pub fn of(n: &Vector3<T>, u: &Vector3<T>) -> Self {
        let c = n.dot(u);
        let (c, n) = if c < T::zero() { (-c, -n) } else { (c, *n) };
        let (e1, e2) = beam_frame(u);
        let (s1, s2) = (n.dot(&e1), n.dot(&e2));
        let spot = if c > T::zero() {
            let k = (s1 * s1 + s2 * s2).fast_sqrt() / (c * c);
            [k * s1, k * s2]
        } else {
            [T::zero(); 2]
        };
        Self { cos_gamma: c, spot }
    }
}

/// The frame `(e₁, e₂)` fixed to beam `u` in which the spot's azimuth is
/// measured (module docs, "Incidence").
pub fn beam_frame<T: Real>(u: &Vector3<T>) -> (Vector3<T>, Vector3<T>) {
    let a = if u.x.abs() < T::lit(0.9) {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let p = a - u * a.dot(u);
    let len = p.norm_squared().fast_sqrt();
    let e1 = if len > T::zero() { p / len } else { a };
    (e1, u.cross(&e1))
}

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

    /// The spline ready to evaluate (its second derivatives solved and
    /// turned into the cubic of each interval once); `None` for invalid
    /// knots (then nothing is applied).
    pub fn spline(&self) -> Option<Spline<T>> {
        if !self.knots_valid() {
            return None;
        }
        let mut y = [T::zero(); TABLE_KNOTS];
        y[1..TABLE_KNOTS - 1].copy_from_slice(&self.coeffs);
        let m = second_derivatives(&self.knots, &y);
        Some(Spline::natural(&self.knots, &y, &m))
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
    /// others 0): the regressors of a fit, `value = Σ_j v_j·C_j`; zeros
    /// for invalid knots. Solves the three splines on every call: a fit
    /// evaluating many readings keeps a [`Cardinal`] instead.
    pub fn basis(&self, x: T) -> [T; TABLE_COEFFS] {
        Cardinal::of(&self.knots).map_or([T::zero(); TABLE_COEFFS], |c| c.basis(x))
    }
}

/// The cardinal functions of a set of knots (the splines of
/// [`LinTable::basis`]) solved once, to evaluate at many readings: one
/// search among the knots and a Horner scheme per function. The same
/// arithmetic as [`LinTable::basis`], so the same values to the last bit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cardinal<T: Real> {
    s: [Spline<T>; TABLE_COEFFS],
}

impl<T: Real> Cardinal<T> {
    /// The cardinal splines of `knots`; `None` for invalid knots
    /// ([`LinTable::knots_valid`]).
    pub fn of(knots: &[T; TABLE_KNOTS]) -> Option<Self> {
        let unit = |j: usize| {
            let mut coeffs = [T::zero(); TABLE_COEFFS];
            coeffs[j] = T::one();
            LinTable {
                knots: *knots,
                coeffs,
            }
            .spline()
        };
        Some(Self {
            s: [unit(0)?, unit(1)?, unit(2)?],
        })
    }

    /// `C_j(x)` for the three interior knots.
    #[inline]
    pub fn basis(&self, x: T) -> [T; TABLE_COEFFS] {
        let i = self.s[0].piece(x);
        core::array::from_fn(|j| self.s[j].value_in(i, x))
    }
}

/// Pieces of a [`Spline`]: one beyond each end knot, one between each
/// pair of neighbouring knots.
const PIECES: usize = TABLE_KNOTS + 1;

/// A piecewise cubic ready to evaluate: a [`LinTable`]'s spline with its
/// second derivatives solved, and (in [`Prepared`]) the gain and the
/// polynomial of an [`Extension`] added, in the distance itself. Piece `p`
/// holds `[base, a, b, c, e]`: `a + t·(b + t·(c + t·e))` with
/// `t = x − base`, for `x` at or beyond `p` of the knots (the pieces
/// before the first and after the last knot extend the neighbouring end,
/// linearly for a natural spline). Evaluation is a search among the five
/// knots and a Horner scheme, no division.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spline<T: Real> {
    k: [T; TABLE_KNOTS],
    p: [[T; 5]; PIECES],
}

impl<T: Real> Spline<T> {
    /// The natural spline through `(k_i, y_i)` with second derivatives
    /// `m_i` (`m_0 = m_4 = 0`), linear beyond the end knots; on
    /// `[k_i, k_i+1]` with `h = k_i+1 − k_i` the cubic is
    /// `y_i + t·(b_i + t·(m_i/2 + t·(m_i+1 − m_i)/(6h)))`,
    /// `b_i = (y_i+1 − y_i)/h − h·(2m_i + m_i+1)/6` (de Boor ch. IV).
    fn natural(k: &[T; TABLE_KNOTS], y: &[T; TABLE_KNOTS], m: &[T; TABLE_KNOTS]) -> Self {
        let last = TABLE_KNOTS - 1;
        let sixth = T::lit(1.0 / 6.0);
        let half = T::lit(0.5);
        let mut p = [[T::zero(); 5]; PIECES];
        let mut end = T::zero();
        for i in 0..last {
            let h = k[i + 1] - k[i];
            let b = (y[i + 1] - y[i]) / h - h * (T::lit(2.0) * m[i] + m[i + 1]) * sixth;
            let c3 = (m[i + 1] - m[i]) * sixth / h;
            p[i + 1] = [k[i], y[i], b, m[i] * half, c3];
            end = b + h * (m[i] + m[i + 1]) * half;
        }
        p[0] = [k[0], y[0], p[1][2], T::zero(), T::zero()];
        p[PIECES - 1] = [k[last], y[last], end, T::zero(), T::zero()];
        Self { k: *k, p }
    }

    /// This piecewise cubic plus `x·(gain + x·(q + x·c))` (each piece's
    /// Taylor coefficients about its base), shifted by `origin`: the
    /// result at `origin + x` is this one's at `x`.
    fn plus_polynomial(&self, gain: T, q: T, c: T, origin: T) -> Self {
        let (two, three) = (T::lit(2.0), T::lit(3.0));
        let mut p = self.p;
        for pc in p.iter_mut() {
            let x0 = pc[0];
            pc[1] += x0 * (gain + x0 * (q + x0 * c));
            pc[2] += gain + x0 * (two * q + three * c * x0);
            pc[3] += q + three * c * x0;
            pc[4] += c;
            pc[0] = x0 + origin;
        }
        Self {
            k: self.k.map(|k| k + origin),
            p,
        }
    }

    /// Value and slope at `x` (module docs; linear beyond the end knots).
    #[inline]
    pub fn eval(&self, x: T) -> (T, T) {
        let (v, s, _) = self.eval2(x);
        (v, s)
    }

    /// The piece of `x`: the number of knots at or below it (0..=5), by
    /// bisection.
    #[inline]
    fn piece(&self, x: T) -> usize {
        let k = &self.k;
        if x >= k[2] {
            if x >= k[3] {
                4 + usize::from(x >= k[4])
            } else {
                3
            }
        } else if x >= k[1] {
            2
        } else {
            usize::from(x >= k[0])
        }
    }

    /// The value at `x` on piece `i` ([`Spline::piece`]): the value of
    /// [`Spline::eval2`].
    #[inline]
    fn value_in(&self, i: usize, x: T) -> T {
        let [base, a, b, c, e] = self.p[i];
        let t = x - base;
        a + t * (b + t * (c + t * e))
    }

    /// Value, slope and second derivative at `x`.
    #[inline]
    fn eval2(&self, x: T) -> (T, T, T) {
        let [base, a, b, c, e] = self.p[self.piece(x)];
        let t = x - base;
        let e3t = T::lit(3.0) * e * t;
        let half_curv = c + c + e3t;
        let v = a + t * (b + t * (c + t * e));
        let s = b + t * half_curv;
        (v, s, half_curv + e3t)
    }

    /// A Lipschitz constant of the second derivative: the largest
    /// `|6e|` of the pieces (the second derivative is continuous and
    /// linear on each piece).
    fn lipschitz2(&self) -> T {
        let six = T::lit(6.0);
        self.p
            .iter()
            .map(|pc| (six * pc[4]).abs())
            .fold(T::zero(), |m, x| if x > m { x } else { m })
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

/// Most evaluations of `δ` in [`Extension::correct`].
const MAX_EVALS: usize = 4;
/// The inversion stops after a step at most this fraction of `1 + |d|` \[-\].
const STEP_REL: f64 = 1e-6;

/// The early stop's tolerance as a fraction of `1 + |d|`: [`STEP_REL`],
/// but at most 16 units of roundoff of the float type (so that in `f64`
/// the result stays that of the converged iteration).
#[inline]
fn early_rel<T: Real>() -> T {
    let ulps = T::lit(16.0) * T::default_epsilon();
    let step = T::lit(STEP_REL);
    if ulps < step {
        ulps
    } else {
        step
    }
}

/// An [`Extension`] prepared for [`Extension::correct_with`]
/// ([`Extension::prepare`]; module docs, "Prepared form"): gain,
/// polynomial and table as one piecewise cubic in the distance, whether
/// the inversion iterates, and the bound on the change of the curvature of
/// `δ` that allows the early stop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prepared<T: Real> {
    moving: Spline<T>,
    iterate: bool,
    /// Which terms that do not depend on `f` have a coefficient.
    fixed: Fixed,
    /// [`Extension::needs_incidence`], decided once (the board asks it for
    /// every sensor on every sample).
    incidence: bool,
    /// `L/2` and `L/6`, `L` a Lipschitz constant of `δ''`.
    lip2: T,
    lip6: T,
}

/// The terms fixed in `f` that have a coefficient ([`Prepared`]): what the
/// inversion evaluates of them once per reading.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fixed {
    /// None: they contribute nothing.
    None,
    /// Only the thermal term: `thermal·(T − T_ref)` when a temperature is
    /// known (the other terms' zero coefficients add exact zeros for
    /// finite inputs, so the result is that of all terms, bit for bit).
    Thermal,
    /// Incidence, carry-over or drift (and perhaps the thermal term): all
    /// of [`Extension::fixed`].
    All,
}

impl<T: Real> Prepared<T> {
    /// Whether the extension it was prepared from has an incidence term
    /// ([`Extension::needs_incidence`]).
    #[inline]
    pub fn needs_incidence(&self) -> bool {
        self.incidence
    }

    /// Whether the step `−(n + w)` from `f0`, taken with slope `j`,
    /// curvature `c` (`F'(f0)`, `F''(f0)`), Newton step `n` and correction
    /// `w = c·n²/(2j)`, left the iterate within `early` of the root
    /// (module docs, "Early stop"): `r ≤ early·m` with
    /// `r = |c|·|w|·(2|n| + |w|)/2 + L·|u|³/6`,
    /// `m = |j| − |c|·D − L·D²/2`, `D = |u| + early`, `u = n + w`.
    #[inline]
    fn settled(&self, n: T, w: T, j: T, c: T, early: T) -> bool {
        let (na, wa, ca) = (n.abs(), w.abs(), c.abs());
        let ua = (n + w).abs();
        let half = T::lit(0.5);
        let r = half * ca * wa * (na + na + wa) + self.lip6 * ua * ua * ua;
        let dd = ua + early;
        let m = j.abs() - dd * (ca + self.lip2 * dd);
        r <= early * m
    }
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
    /// Spot bias [mm] per unit of `tan²γ·cos φ` and of `tan²γ·sin φ`
    /// (module docs, "Incidence"): `k·cos ψ`, `k·sin ψ`.
    pub spot: [T; 2],
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
            spot: [T::zero(); 2],
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
        self.incidence != T::zero() || self.has_spot()
    }

    /// Whether a spot term is active (then the correction needs the beam's
    /// azimuth, [`Incidence::of`], not only `cos γ`).
    #[inline]
    pub fn has_spot(&self) -> bool {
        self.spot[0] != T::zero() || self.spot[1] != T::zero()
    }

    /// The spot bias as its size `k` [mm per unit of tan²γ] and the
    /// receiver's azimuth `ψ` [rad] in the beam's frame.
    pub fn spot_polar(&self) -> (T, T) {
        let [a, b] = self.spot;
        ((a * a + b * b).fast_sqrt(), b.atan2(a))
    }

    /// The excess `δ(f)` of the reading over the true distance `f`
    /// (module docs).
    ///
    /// `d_prev` is the previous channel's reading, `inc` the beam's angles
    /// ([`Incidence::of`]; `cos γ = |n·u|` alone leaves out the spot terms).
    pub fn excess(
        &self,
        f: T,
        d_prev: Option<T>,
        inc: impl Into<Incidence<T>>,
        ctx: &Context<T>,
    ) -> T {
        let prep = self.prepare();
        let (g, _) = self.moving(&prep, f, d_prev.is_some());
        self.fixed(d_prev, &inc.into(), ctx) + g
    }

    /// What [`Extension::correct_with`] needs besides the coefficients,
    /// derived from them (module docs, "Prepared form"): call it again
    /// whenever a coefficient changes.
    pub fn prepare(&self) -> Prepared<T> {
        let table = if self.table.is_active() {
            self.table.spline()
        } else {
            None
        };
        let [q, c] = self.nonlinearity;
        let spline = table.unwrap_or(Spline {
            k: [T::zero(); TABLE_KNOTS],
            p: [[T::zero(); 5]; PIECES],
        });
        let moving = spline.plus_polynomial(self.gain, q, c, self.d_ref);
        Prepared {
            moving,
            iterate: table.is_some() || self.depends_on_distance(),
            incidence: self.needs_incidence(),
            fixed: if self.needs_incidence()
                || self.crosstalk != T::zero()
                || self.drift != T::zero()
            {
                Fixed::All
            } else if self.thermal != T::zero() {
                Fixed::Thermal
            } else {
                Fixed::None
            },
            lip2: T::lit(0.5) * moving.lipschitz2(),
            lip6: moving.lipschitz2() / T::lit(6.0),
        }
    }

    /// The terms of the excess that do not depend on `f`: incidence,
    /// thermal, drift and the previous channel's share of the carry-over.
    #[inline]
    fn fixed(&self, d_prev: Option<T>, inc: &Incidence<T>, ctx: &Context<T>) -> T {
        let mut c = T::zero();
        let cos_gamma = inc.cos_gamma;
        if self.incidence != T::zero() && cos_gamma > T::zero() {
            c += self.incidence * (T::one() / cos_gamma - T::one());
        }
        if self.has_spot() {
            c += self.spot[0] * inc.spot[0] + self.spot[1] * inc.spot[1];
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

    /// The terms that do depend on `f` (gain, polynomial and table from
    /// the prepared piecewise cubic, the carry-over's `−crosstalk·f` when
    /// there is a previous channel) and their slope `∂δ/∂f`.
    #[inline]
    fn moving(&self, prep: &Prepared<T>, f: T, has_prev: bool) -> (T, T) {
        let (mut delta, mut slope) = prep.moving.eval(f);
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
    /// `f + δ(f) = d` (module docs, "Inversion"). Prepares the
    /// coefficients on every call; [`Extension::correct_with`] takes them
    /// prepared once.
    #[inline]
    pub fn correct(
        &self,
        d: T,
        d_prev: Option<T>,
        inc: impl Into<Incidence<T>>,
        ctx: &Context<T>,
    ) -> T {
        self.correct_with(&self.prepare(), d, d_prev, inc, ctx)
    }

    /// [`Extension::correct`] with the coefficients prepared by
    /// [`Extension::prepare`] of this extension (a stale `prep` corrects
    /// with the coefficients it was prepared from).
    #[inline]
    pub fn correct_with(
        &self,
        prep: &Prepared<T>,
        d: T,
        d_prev: Option<T>,
        inc: impl Into<Incidence<T>>,
        ctx: &Context<T>,
    ) -> T {
        let scale = T::one() + d.abs();
        let early = early_rel::<T>() * scale;
        self.invert(prep, d, d_prev, inc, ctx, early).0
    }

    /// The inversion (module docs) with the early stop at `early` (`ε`); also
    /// returns the number of evaluations of `δ`.
    #[inline]
    fn invert(
        &self,
        prep: &Prepared<T>,
        d: T,
        d_prev: Option<T>,
        inc: impl Into<Incidence<T>>,
        ctx: &Context<T>,
        early: T,
    ) -> (T, usize) {
        let c0 = match prep.fixed {
            Fixed::None => T::zero(),
            Fixed::Thermal => match ctx.temp_c {
                Some(t) => self.thermal * (t - self.temp_ref),
                None => T::zero(),
            },
            // converted only here: the board's samples without incidence,
            // carry-over or drift never build the angles
            Fixed::All => self.fixed(d_prev, &inc.into(), ctx),
        };
        if !prep.iterate {
            return (d - c0, 0);
        }
        // f + δ(f) − d = lin·f + P(f) − r: the carry-over's −crosstalk·f
        // folded into the linear term, the terms fixed in f into r.
        let lin = if d_prev.is_some() {
            T::one() - self.crosstalk
        } else {
            T::one()
        };
        let r = d - c0;
        let tol = T::lit(STEP_REL) * (T::one() + d.abs());
        let mut f = d;
        let mut evals = 0;
        while evals < MAX_EVALS {
            let (v, s, c) = prep.moving.eval2(f);
            evals += 1;
            let j = lin + s;
            if !(j.abs() > T::lit(1e-3)) {
                break;
            }
            // Newton's step n and Chebyshev's correction w (module docs).
            let inv = T::one() / j;
            let n = (lin * f + v - r) * inv;
            let w = T::lit(0.5) * c * n * n * inv;
            f -= n + w;
            if (n + w).abs() <= tol || prep.settled(n, w, j, c, early) {
                break;
            }
        }
        (f, evals)
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
                self.spot[0],
                self.spot[1],
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
            spot: self.spot.map(c),
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
            spot: [0.0; 2],
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

    /// The thermal term alone (`Fixed::Thermal`: `thermal·(T − T_ref)`
    /// only) corrects exactly as the sum of all fixed terms
    /// (`Fixed::All`), bit for bit in `f32` and `f64`, with and without a
    /// table, a previous channel, a temperature and a time; a zero thermal
    /// coefficient is `Fixed::None`, another fixed term `Fixed::All`.
    #[test]
    fn thermal_alone_is_the_sum_of_all_fixed_terms() {
        fn check<T: Real + core::fmt::Debug>(e: &Extension<T>) {
            let prep = e.prepare();
            assert_eq!(prep.fixed, Fixed::Thermal);
            let all = Prepared {
                fixed: Fixed::All,
                ..prep
            };
            for k in 0..40 {
                let d = T::lit(43.0 + 0.17 * k as f64);
                let prev = (k % 2 == 0).then(|| T::lit(41.0 + 0.3 * k as f64));
                for (temp, t) in [(Some(31.7), Some(600.0)), (Some(12.5), None), (None, None)] {
                    let ctx = Context {
                        temp_c: temp.map(T::lit),
                        t_s: t.map(T::lit),
                    };
                    let want = e.correct_with(&all, d, prev, T::one(), &ctx);
                    let got = e.correct_with(&prep, d, prev, T::one(), &ctx);
                    assert_eq!(got.to_f64().to_bits(), want.to_f64().to_bits(), "{d:?}");
                }
            }
        }
        let e = Extension {
            d_ref: 46.5,
            table: LinTable {
                knots: [-1.5, -0.75, 0.0, 0.75, 1.5],
                coeffs: [0.03, -0.04, 0.025],
            },
            thermal: 2e-3,
            temp_ref: 22.0,
            ..Extension::identity()
        };
        check(&e);
        check(&e.cast::<f32>());
        let flat = Extension {
            table: LinTable::none(),
            ..e
        };
        check(&flat);
        check(&flat.cast::<f32>());
        assert_eq!(Extension::<f64>::identity().prepare().fixed, Fixed::None);
        for other in [
            Extension { drift: 1e-6, ..e },
            Extension {
                crosstalk: 0.01,
                ..e
            },
            Extension {
                incidence: 0.02,
                ..e
            },
        ] {
            assert_eq!(other.prepare().fixed, Fixed::All);
        }
    }

    /// [`Incidence::of`] is the spot form of the blind generator
    /// (`host-tests/blind/gen.py`, `spot_form`): `spot = [k·cos ψ, k·sin ψ]`
    /// gives `k·tan²γ·cos(φ − ψ)` with `φ` measured by trigonometry in the
    /// beam's frame, for any `ψ`; the normal's orientation does not matter,
    /// and a beam along the normal has no spot bias.
    #[test]
    fn spot_terms_are_the_azimuthal_form() {
        let e0 = Extension::<f64>::identity();
        let ctx = Context::default();
        for (ux, uy) in [(0.5, 0.0), (-0.2, 0.45), (0.95, 0.1)] {
            let u = Vector3::<f64>::new(ux, uy, 1.0).normalize();
            let (e1, e2) = beam_frame(&u);
            assert!(e1.dot(&u).abs() < 1e-12 && (e1.norm() - 1.0).abs() < 1e-12);
            assert!(e2.dot(&u).abs() < 1e-12 && e2.dot(&e1).abs() < 1e-12);
            for (nx, ny) in [(0.1, -0.3), (-0.4, 0.2), (0.0, 0.05)] {
                let n = Vector3::<f64>::new(nx, ny, 1.0).normalize();
                let c = n.dot(&u);
                let tan2 = (1.0 - c * c) / (c * c);
                let phi = n.dot(&e2).atan2(n.dot(&e1));
                for psi in [0.0, 1.1, -2.5, 3.0] {
                    let k: f64 = 0.3;
                    let e = Extension {
                        spot: [k * f64::cos(psi), k * f64::sin(psi)],
                        ..e0
                    };
                    let want = k * tan2 * (phi - psi).cos();
                    let got = e.excess(40.0, None, Incidence::of(&n, &u), &ctx);
                    assert_relative_eq!(got, want, epsilon = 1e-12);
                    let flipped = e.excess(40.0, None, Incidence::of(&-n, &u), &ctx);
                    assert_relative_eq!(flipped, want, epsilon = 1e-12);
                    let d = 40.0 + got;
                    let back = e.correct(d, None, Incidence::of(&n, &u), &ctx);
                    assert_relative_eq!(back, 40.0, epsilon = 1e-12);
                }
            }
            let along = Incidence::of(&u, &u);
            assert!(along.spot[0].abs() + along.spot[1].abs() < 1e-12);
        }
        let e = Extension {
            spot: [0.0, 0.02],
            ..e0
        };
        assert!(e.needs_incidence() && e.has_spot());
        assert_eq!(e.prepare().fixed, Fixed::All);
        assert_relative_eq!(e.spot_polar().0, 0.02);
        assert_relative_eq!(e.spot_polar().1, core::f64::consts::FRAC_PI_2);
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
            spot: [0.0; 2],
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

    /// The cardinal splines solved once give, to the last bit, the value
    /// of the table with that one value 1 (the fit's regressors are the
    /// same whichever way they are computed), on every piece and beyond
    /// the ends; invalid knots give none.
    #[test]
    fn cardinal_is_the_unit_tables_value_bit_for_bit() {
        let knots = table().knots;
        let c = Cardinal::of(&knots).unwrap();
        for x in [-9.0, -6.0, -4.4, -3.0, -0.1, 0.0, 1.3, 2.0, 4.7, 6.0, 8.5] {
            let b = c.basis(x);
            for (j, bj) in b.iter().enumerate() {
                let mut coeffs = [0.0; TABLE_COEFFS];
                coeffs[j] = 1.0;
                let unit = LinTable { knots, coeffs };
                assert_eq!(bj.to_bits(), unit.value(x).to_bits(), "x = {x}, j = {j}");
            }
        }
        assert!(Cardinal::of(&[0.0, 1.0, 1.0, 2.0, 3.0]).is_none());
        assert!(Cardinal::of(&[0.0, 1.0, f64::NAN, 2.0, 3.0]).is_none());
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

/// The prepared form and the early stop against the algorithm they
/// replaced and against an independent root.
#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod prepared_tests {
    use super::*;
    use approx::assert_relative_eq;
    use proptest::prelude::*;

    /// The algorithm before the prepared form, verbatim in substance: the
    /// spline solved per call, evaluated in `f − d_ref`, Newton steps from
    /// the reading. The reference of the host's results.
    mod previous {
        use super::super::*;

        fn spline(t: &LinTable<f64>, x: f64) -> (f64, f64) {
            let k = &t.knots;
            let mut y = [0.0; TABLE_KNOTS];
            y[1..TABLE_KNOTS - 1].copy_from_slice(&t.coeffs);
            let m = second_derivatives(k, &y);
            let last = TABLE_KNOTS - 1;
            let i = (1..last).take_while(|&j| x >= k[j]).count();
            let h = k[i + 1] - k[i];
            let b = (y[i + 1] - y[i]) / h - h * (2.0 * m[i] + m[i + 1]) / 6.0;
            if x < k[0] {
                return (b * (x - k[0]), b);
            }
            if x > k[last] {
                let s = b + h * (m[i] + m[i + 1]) * 0.5;
                return (s * (x - k[last]), s);
            }
            let t = x - k[i];
            let c3 = (m[i + 1] - m[i]) / 6.0 / h;
            let v = y[i] + t * (b + t * (m[i] * 0.5 + t * c3));
            (v, b + t * (m[i] + 3.0 * c3 * t))
        }

        fn moving(e: &Extension<f64>, f: f64, has_prev: bool) -> (f64, f64) {
            let x = f - e.d_ref;
            let [q, c] = e.nonlinearity;
            let mut delta = x * (e.gain + x * (q + x * c));
            let mut slope = e.gain + x * (2.0 * q + 3.0 * c * x);
            if e.table.is_active() && e.table.knots_valid() {
                let (v, s) = spline(&e.table, x);
                delta += v;
                slope += s;
            }
            if has_prev {
                delta -= e.crosstalk * f;
                slope -= e.crosstalk;
            }
            (delta, slope)
        }

        pub fn excess(
            e: &Extension<f64>,
            f: f64,
            p: Option<f64>,
            cg: f64,
            ctx: &Context<f64>,
        ) -> f64 {
            e.fixed(p, &cg.into(), ctx) + moving(e, f, p.is_some()).0
        }

        pub fn correct(
            e: &Extension<f64>,
            d: f64,
            p: Option<f64>,
            cg: f64,
            ctx: &Context<f64>,
        ) -> f64 {
            let c0 = e.fixed(p, &cg.into(), ctx);
            let tol = 1e-6 * (1.0 + d.abs());
            let mut f = d;
            for _ in 0..4 {
                let (g, s) = moving(e, f, p.is_some());
                let j = 1.0 + s;
                if !(j.abs() > 1e-3) {
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
    }

    /// The root of `f + δ(f) = d` by bisection within 50 mm of `d`
    /// (independent of the inversion; `δ' > −1` makes the left side
    /// increasing).
    fn root(e: &Extension<f64>, d: f64, p: Option<f64>, cg: f64, ctx: &Context<f64>) -> f64 {
        let (mut lo, mut hi) = (d - 50.0, d + 50.0);
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if mid + e.excess(mid, p, cg, ctx) < d {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        0.5 * (lo + hi)
    }

    /// A table as the board gets one: knots at ±1.5 mm and halfway about
    /// `d_ref`, values of tens of µm.
    fn board_table(d_ref: f64) -> Extension<f64> {
        Extension {
            d_ref,
            table: LinTable {
                knots: [-1.5, -0.75, 0.0, 0.75, 1.5],
                coeffs: [0.03, -0.04, 0.025],
            },
            ..Extension::identity()
        }
    }

    /// Realistic extensions: the board's table, 10 mm knots, uneven knots
    /// with gain, carry-over and thermal drift, the polynomial alone.
    fn realistic() -> [Extension<f64>; 4] {
        let wide = Extension {
            table: LinTable {
                knots: [-20.0, -10.0, 0.0, 10.0, 20.0],
                coeffs: [0.032, -0.04, 0.025],
            },
            ..board_table(50.0)
        };
        let mixed = Extension {
            d_ref: 40.0,
            gain: 1e-3,
            table: LinTable {
                knots: [-6.0, -3.0, 0.0, 2.0, 6.0],
                coeffs: [0.02, -0.035, 0.015],
            },
            crosstalk: 0.01,
            thermal: 2e-3,
            temp_ref: 22.0,
            ..Extension::identity()
        };
        let poly = Extension {
            d_ref: 45.0,
            gain: 2e-3,
            nonlinearity: [1e-4, -2e-5],
            ..Extension::identity()
        };
        [board_table(46.5), wide, mixed, poly]
    }

    /// The host's (`f64`) corrections and excesses equal those of the
    /// previous algorithm within 10⁻⁹ mm (10⁻¹² mm for the excess) over a
    /// grid of readings ±4 mm about `d_ref`, with and without a previous
    /// channel and a temperature.
    #[test]
    fn host_results_match_the_previous_algorithm() {
        let ctxs = [
            Context::default(),
            Context {
                temp_c: Some(27.5),
                t_s: None,
            },
        ];
        for e in realistic() {
            for ctx in &ctxs {
                for p in [None, Some(e.d_ref + 0.8)] {
                    for k in 0..=800 {
                        let d = e.d_ref - 4.0 + 0.01 * k as f64;
                        let (new, old) = (
                            e.correct(d, p, 1.0, ctx),
                            previous::correct(&e, d, p, 1.0, ctx),
                        );
                        assert!((new - old).abs() <= 1e-9, "{d}: {new} vs {old}");
                        let (xn, xo) = (
                            e.excess(d, p, 1.0, ctx),
                            previous::excess(&e, d, p, 1.0, ctx),
                        );
                        assert!((xn - xo).abs() <= 1e-12, "{d}: {xn} vs {xo}");
                    }
                }
            }
        }
    }

    /// Golden values of the prepared piecewise cubic: the hand-computed
    /// table of `table_hand_computed` about `d_ref` = 40 (`−9/56` at
    /// 40.5 with slope `−3/28`, `3/7` at 45, one knot beyond the end),
    /// the polynomial of `each_term_hand_computed`, and their inversion.
    #[test]
    fn prepared_golden_values() {
        let e = Extension {
            d_ref: 40.0,
            table: LinTable {
                knots: [0.0, 1.0, 2.0, 3.0, 4.0],
                coeffs: [0.0, 1.0, 0.0],
            },
            ..Extension::identity()
        };
        let p = e.prepare();
        let (v, s) = p.moving.eval(40.5);
        assert_relative_eq!(v, -9.0 / 56.0, epsilon = 1e-12);
        assert_relative_eq!(s, -3.0 / 28.0, epsilon = 1e-12);
        assert_relative_eq!(p.moving.eval(45.0).0, 3.0 / 7.0, epsilon = 1e-12);
        let ctx = Context::default();
        assert_relative_eq!(
            e.correct(40.5 - 9.0 / 56.0, None, 1.0, &ctx),
            40.5,
            epsilon = 1e-12
        );
        assert_relative_eq!(
            e.correct(45.0 + 3.0 / 7.0, None, 1.0, &ctx),
            45.0,
            epsilon = 1e-12
        );
        let poly = Extension {
            d_ref: 40.0,
            gain: 1e-3,
            nonlinearity: [1e-4, 1e-5],
            ..Extension::identity()
        };
        let (v, s) = poly.prepare().moving.eval(42.0);
        assert_relative_eq!(v, 0.002 + 0.0004 + 0.00008, epsilon = 1e-15);
        assert_relative_eq!(
            s,
            1e-3 + 2.0 * 1e-4 * 2.0 + 3.0 * 1e-5 * 4.0,
            epsilon = 1e-15
        );
    }

    /// The board's case in `f64` with the board's `ε = 10⁻⁶·(1 + d)`: the
    /// bound stops after one evaluation at every reading of a grid across
    /// the knots, and the result is within `ε` of the bisected root (the
    /// error it accepts is not nil); at the interior knots (true distance
    /// `d_ref + ξ_j`, reading `+ v_j`) the step rule alone takes more.
    #[test]
    fn early_stop_bound_holds_where_it_stops() {
        let e = board_table(46.5);
        let prep = e.prepare();
        let ctx = Context::default();
        let mut largest = 0.0f64;
        for k in 0..=300 {
            let d = 45.0 + 0.01 * k as f64;
            let eps = 1e-6 * (1.0 + d);
            let (f, evals) = e.invert(&prep, d, None, 1.0, &ctx, eps);
            assert_eq!(evals, 1, "{d}");
            let err = (f - root(&e, d, None, 1.0, &ctx)).abs();
            assert!(err <= eps, "{d}: {err} > {eps}");
            largest = largest.max(err);
        }
        assert!(largest > 1e-9, "{largest}");
        for j in 0..TABLE_COEFFS {
            let f = e.d_ref + e.table.knots[j + 1];
            let d = f + e.table.coeffs[j];
            let eps = 1e-6 * (1.0 + d);
            let (got, evals) = e.invert(&prep, d, None, 1.0, &ctx, eps);
            assert_eq!(evals, 1);
            assert!((got - f).abs() <= eps, "{got} vs {f}");
            assert!(e.invert(&prep, d, None, 1.0, &ctx, 0.0).1 >= 2);
        }
    }

    /// A table with a large change of curvature (values of 50-80 µm over
    /// knots 0.5 mm apart, `L ≈ 5 mm⁻²`): at the interior knots the bound
    /// does not hold after one step, the inversion keeps iterating and
    /// ends within `ε` of the true distance.
    #[test]
    fn early_stop_keeps_iterating_on_large_curvature() {
        let e: Extension<f64> = Extension {
            d_ref: 40.0,
            table: LinTable {
                knots: [-1.0, -0.5, 0.0, 0.5, 1.0],
                coeffs: [0.05, -0.08, 0.05],
            },
            ..Extension::identity()
        };
        let prep = e.prepare();
        assert!(prep.lip6 * 6.0 > 4.0, "{}", prep.lip6 * 6.0);
        let ctx = Context::default();
        for j in 0..TABLE_COEFFS {
            let f = e.d_ref + e.table.knots[j + 1];
            let d = f + e.table.coeffs[j];
            let eps = 1e-6 * (1.0 + d);
            let (got, evals) = e.invert(&prep, d, None, 1.0, &ctx, eps);
            assert!(evals >= 2, "{d}");
            assert!((got - f).abs() <= eps, "{got} vs {f}");
        }
    }

    /// The board's `f32` inversion of the board's table is within `ε` and a
    /// few units of `f32` roundoff of the `f64` root.
    #[test]
    fn board_f32_inversion_within_tolerance() {
        let e = board_table(46.5);
        let e32 = e.cast::<f32>();
        let prep = e32.prepare();
        let ctx = Context::default();
        for k in 0..=300 {
            let d = 45.0 + 0.01 * k as f64;
            let got = e32.correct_with(&prep, d as f32, None, 1.0, &Context::default()) as f64;
            let want = root(&e, d as f32 as f64, None, 1.0, &ctx);
            let tol = 1e-6 * (1.0 + d) + 8.0 * f32::EPSILON as f64 * d;
            assert!((got - want).abs() <= tol, "{d}: {got} vs {want}");
        }
    }

    proptest! {
        /// Wherever the early stop says the root is within `ε` of the
        /// step's result, it is (tables with values up to 0.1 mm over
        /// knots 0.2-3 mm apart and `|δ'| < 0.9`, gain and carry-over,
        /// readings across and beyond the knots, `ε` up to 10⁻⁴ mm).
        #[test]
        fn early_stop_is_sound(
            h in 0.2f64..3.0,
            v in prop::array::uniform3(-0.1f64..0.1),
            gain in -0.01f64..0.01,
            xt in 0.0f64..0.05,
            x in -8.0f64..8.0,
            rel in 1e-8f64..2e-6,
        ) {
            let e = Extension {
                d_ref: 40.0,
                gain,
                crosstalk: xt,
                table: LinTable {
                    knots: [-2.0 * h, -h, 0.0, h, 2.0 * h],
                    coeffs: v,
                },
                ..Extension::identity()
            };
            let prep = e.prepare();
            // The inversion's premise (module docs, limits): |δ'| < 1, so
            // that the root is unique (within 10 %).
            let steep = (-400..=400).any(|k| {
                let f = 40.0 + 0.01 * h * k as f64;
                (prep.moving.eval(f).1 - xt).abs() >= 0.9
            });
            prop_assume!(!steep);
            let ctx = Context::default();
            let (d, p) = (40.0 + x * h, Some(41.0));
            let eps = rel * (1.0 + d);
            // every step's result: the first step alone, and the rest
            for cap in 1..=MAX_EVALS {
                let (f, evals, settled) = one_run(&e, &prep, d, p, eps, cap);
                if settled && evals == cap {
                    let err = (f - root(&e, d, p, 1.0, &ctx)).abs();
                    prop_assert!(err <= eps, "{} > {}", err, eps);
                }
            }
        }
    }

    /// The inversion's loop cut after `cap` evaluations: the iterate, the
    /// evaluations done and whether the last one stopped on the bound.
    fn one_run(
        e: &Extension<f64>,
        prep: &Prepared<f64>,
        d: f64,
        p: Option<f64>,
        eps: f64,
        cap: usize,
    ) -> (f64, usize, bool) {
        let lin = if p.is_some() { 1.0 - e.crosstalk } else { 1.0 };
        let r = d - e.fixed(p, &1.0.into(), &Context::default());
        let mut f = d;
        for evals in 1..=cap {
            let (v, s, c) = prep.moving.eval2(f);
            let j = lin + s;
            let n = (lin * f + v - r) / j;
            let w = 0.5 * c * n * n / j;
            f -= n + w;
            if prep.settled(n, w, j, c, eps) {
                return (f, evals, true);
            }
        }
        (f, cap, false)
    }
}
