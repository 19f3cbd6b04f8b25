//! Extra linear columns of the least-squares problem: the model extensions
//! of [`crate::ext`] as regressors.
//!
//! The batch solver fits, per sensor, `P = 5 + E` parameters: the 5-DOF
//! geometry of [`crate::head::Sensor`] and `E` coefficients `c_j` of
//! corrections that are linear in the coefficients. A reading is predicted as
//!
//! ```text
//! d_meas = f(E, u; plane) + Σ_j c_j · x_j(observation)
//! ```
//!
//! where `f` is Chen eq. 1-3 and `x_j` are the regressors supplied by a
//! [`Regressors`] implementation. [`ExtTerms`] supplies the terms of
//! [`crate::ext::Extension::excess`] (gain, linearity, incidence and its
//! spot terms, crosstalk, thermal, drift), so that a fitted coefficient vector becomes an
//! [`Extension`] that the board applies with
//! [`crate::ext::Extension::correct`]; [`NoExtra`] is the paper's model.
//!
//! **No target leakage.** A regressor never contains the reading it helps
//! predict: gain, linearity and crosstalk use the distance `f` the current
//! geometric estimate predicts for the pose (crosstalk: the *previous*
//! channel's measured reading minus `f`), incidence the estimate's beam
//! direction, thermal and drift the pose's temperature and time. With the
//! measured reading in its own regressor, a fit could lower the residuals
//! by shrinking that reading's noise (a negative "crosstalk" of `d_prev −
//! d` does exactly that) and a held-out prediction would see the value it
//! predicts.
//!
//! On the board the plane is what is being measured, so
//! [`Extension::correct`] evaluates the same terms on the measured reading:
//! the two differ by `c·(d − f)`, second order in the (small) coefficient
//! and the noise.
//!
//! Limits: a missing input (previous channel, temperature, time)
//! contributes 0, as in [`crate::ext`]; the solver's Jacobian treats the
//! regressors as constants within one step (their dependence on the
//! geometry is first order in the coefficients).

use super::Poses;
use crate::ext::{Cardinal, Extension, Incidence, LinTable, TABLE_COEFFS, TABLE_KNOTS};
use crate::head::Sensor;
use crate::model::distance;
use crate::Real;

/// Supplier of the extra columns of one sensor's least-squares problem.
pub trait Regressors<T: Real> {
    /// Number of extra columns `E` (the solver's `P` must be `5 + E`).
    fn count(&self) -> usize;

    /// Writes the `count()` regressors of the observation (pose `k`, sensor
    /// `sensor`) into `out[..count()]`; `geom` is the current geometric
    /// estimate of the sensor.
    fn fill<P: Poses<T> + ?Sized>(
        &self,
        poses: &P,
        k: usize,
        sensor: usize,
        geom: &Sensor<T>,
        out: &mut [T],
    );

    /// Short name of column `j` for diagnostics (e.g. `"gain"`).
    fn name(&self, j: usize) -> &'static str;

    /// Relative ridge `ρ_j ≥ 0` of column `j` (0 by default: plain least
    /// squares). The solver adds `w_j·c_j²` to its cost, `w_j = ρ_j·(JᵀJ)_jj`
    /// at the start (see [`super::lsq`]'s module docs).
    fn ridge(&self, _j: usize) -> T {
        T::zero()
    }
}

/// No extra columns: the paper's zero-point + beam-direction model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct NoExtra;

impl<T: Real> Regressors<T> for NoExtra {
    fn count(&self) -> usize {
        0
    }
    fn fill<P: Poses<T> + ?Sized>(&self, _: &P, _: usize, _: usize, _: &Sensor<T>, _: &mut [T]) {}
    fn name(&self, _j: usize) -> &'static str {
        "none"
    }
}

/// One term of [`Extension::excess`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Term {
    /// `gain · (d − d_ref)`.
    Gain,
    /// `nl2 · (d − d_ref)²`.
    Quadratic,
    /// `nl3 · (d − d_ref)³`.
    Cubic,
    /// `incidence · (1/cos γ − 1)`, `cos γ = |n·u|`.
    Incidence,
    /// `crosstalk · (d_prev − d)`.
    Crosstalk,
    /// `thermal · (T − T_ref)`.
    Thermal,
    /// `drift · t`.
    Drift,
    /// `v_0 · C_0(d − d_ref)`: the linearity table's ([`crate::ext::LinTable`])
    /// value at its first interior knot times its cardinal function.
    Table0,
    /// `v_1 · C_1(d − d_ref)`.
    Table1,
    /// `v_2 · C_2(d − d_ref)`.
    Table2,
    /// `spot[0] · tan²γ·cos φ` ([`crate::ext`], "Incidence").
    SpotCos,
    /// `spot[1] · tan²γ·sin φ`.
    SpotSin,
}

impl Term {
    /// All terms, in the column order [`ExtTerms`] uses.
    pub const ALL: [Term; 12] = [
        Term::Gain,
        Term::Quadratic,
        Term::Cubic,
        Term::Incidence,
        Term::Crosstalk,
        Term::Thermal,
        Term::Drift,
        Term::Table0,
        Term::Table1,
        Term::Table2,
        Term::SpotCos,
        Term::SpotSin,
    ];

    /// The spot terms of the incidence correction.
    pub const SPOT: [Term; 2] = [Term::SpotCos, Term::SpotSin];

    /// The linearity table's terms.
    pub const TABLE: [Term; 3] = [Term::Table0, Term::Table1, Term::Table2];

    /// Their bits in [`ExtTerms::mask`].
    pub const TABLE_BITS: u16 = Term::Table0.bit() | Term::Table1.bit() | Term::Table2.bit();

    /// Bit of this term in [`ExtTerms::mask`].
    pub const fn bit(self) -> u16 {
        match self {
            Term::Gain => 1,
            Term::Quadratic => 2,
            Term::Cubic => 4,
            Term::Incidence => 8,
            Term::Crosstalk => 16,
            Term::Thermal => 32,
            Term::Drift => 64,
            Term::Table0 => 128,
            Term::Table1 => 256,
            Term::Table2 => 512,
            Term::SpotCos => 1024,
            Term::SpotSin => 2048,
        }
    }

    /// Name of the term.
    pub const fn name(self) -> &'static str {
        match self {
            Term::Gain => "gain",
            Term::Quadratic => "nonlinearity2",
            Term::Cubic => "nonlinearity3",
            Term::Incidence => "incidence",
            Term::Crosstalk => "crosstalk",
            Term::Thermal => "thermal",
            Term::Drift => "drift",
            Term::Table0 => "table0",
            Term::Table1 => "table1",
            Term::Table2 => "table2",
            Term::SpotCos => "spot_cos",
            Term::SpotSin => "spot_sin",
        }
    }
}

/// A selection of [`Term`]s as regressors, columns in the order of
/// [`Term::ALL`], with the reference distance and temperature of the
/// sensor's [`Extension`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExtTerms<T: Real> {
    /// Bit set of [`Term::bit`]s.
    pub mask: u16,
    /// Reference distance [mm] of gain and linearity (mid-range).
    pub d_ref: T,
    /// Reference temperature [°C] of the thermal term.
    pub temp_ref: T,
    /// Knots [mm] of the linearity table about `d_ref` (used by the
    /// `Table*` terms only; strictly ascending for those). Set by
    /// [`ExtTerms::with_knots`], which solves their cardinal splines once.
    knots: [T; TABLE_KNOTS],
    /// The cardinal splines of `knots` (`None` for invalid knots: the
    /// table's columns are then zero).
    cardinal: Option<Cardinal<T>>,
    /// The affine part `(a_j, b_j)` taken off each table column:
    /// `C_j(x) − a_j − b_j·x` (e.g. `C_j`'s least-squares line over the
    /// run's readings; zeros by default). The slope `b_j` is taken off only
    /// when the gain term is fitted beside the table (it is then the gain's
    /// job), as the diagnosis always fits a table.
    ///
    /// Why: the cardinal functions are pinned to 0 at the end knots, so on
    /// a run whose readings crowd the middle of their range, `Σ_j C_j` is
    /// nearly a constant there and trades with the zero point along the
    /// beam, and a tilted combination with the gain (column-scaled
    /// condition above 10⁵: "the readings do not determine the zero point /
    /// the gain"). Offset and slope are in the model anyway (zero point and
    /// gain), so the centred columns span the same predictions, well
    /// conditioned; [`ExtTerms::stored`] gives offset and slope back to
    /// the zero point and the gain for the board.
    pub table_affine: [(T, T); TABLE_COEFFS],
    /// Relative ridge `ρ` of the table's columns and of the gain beside
    /// them ([`Regressors::ridge`]; 0: plain least squares). It shrinks the
    /// table toward a straight line and the line toward the paper's model.
    ///
    /// Why: on a wide pose spread (±15°) the readings vary mostly with the
    /// tilt, and a smooth function of the reading is nearly a combination
    /// of the beam direction's columns (`∂d/∂α ∝ (d − d̄)(n·e₁)`, quadratic
    /// in the tilt like the table). The table's coefficients then trade
    /// with the direction and carry the noise: on two effect-free ±15°,
    /// 60-pose blind runs with tracker noise the unpenalised table's
    /// held-out RMS was 1.15× and 1.30× the same-draw floor, on the first
    /// 1.02× with `ρ = 0.1`.
    /// The other terms are never penalised.
    pub ridge: T,
}

impl<T: Real> ExtTerms<T> {
    /// The terms in `terms` about `d_ref` / `temp_ref`.
    pub fn new(terms: &[Term], d_ref: T, temp_ref: T) -> Self {
        Self {
            mask: terms.iter().fold(0, |m, t| m | t.bit()),
            d_ref,
            temp_ref,
            knots: [T::zero(); TABLE_KNOTS],
            cardinal: None,
            table_affine: [(T::zero(), T::zero()); TABLE_COEFFS],
            ridge: T::zero(),
        }
    }

    /// Knots [mm] of the linearity table about `d_ref`.
    pub fn knots(&self) -> [T; TABLE_KNOTS] {
        self.knots
    }

    /// The same terms with the relative ridge `ridge` on the table and the
    /// gain beside it ([`ExtTerms::ridge`]; negative or non-finite: 0).
    pub fn with_ridge(self, ridge: T) -> Self {
        let ridge = if ridge.is_finite_real() && ridge > T::zero() {
            ridge
        } else {
            T::zero()
        };
        Self { ridge, ..self }
    }

    /// The same terms with the linearity table's knots `knots`.
    pub fn with_knots(self, knots: [T; TABLE_KNOTS]) -> Self {
        Self {
            knots,
            cardinal: Cardinal::of(&knots),
            ..self
        }
    }

    /// The same terms with the affine part `(a_j, b_j)` taken off the
    /// table's columns ([`ExtTerms::table_affine`]).
    pub fn with_table_affine(self, table_affine: [(T, T); TABLE_COEFFS]) -> Self {
        Self {
            table_affine,
            ..self
        }
    }

    /// The slope taken off table column `j` (0 unless the gain is fitted).
    fn table_slope(&self, j: usize) -> T {
        if self.mask & Term::Gain.bit() != 0 {
            self.table_affine[j].1
        } else {
            T::zero()
        }
    }

    /// The column of term `t` among these terms (`None` when not selected).
    pub fn column(&self, t: Term) -> Option<usize> {
        self.terms().position(|x| x == t)
    }

    /// Offset `s = Σ_j v_j·a_j` and slope `Σ_j v_j·b_j` that centred table
    /// columns take off the fitted table (`coeffs` in column order).
    pub fn table_offset_slope(&self, coeffs: &[T]) -> (T, T) {
        Term::TABLE
            .iter()
            .enumerate()
            .filter_map(|(j, t)| Some((j, *coeffs.get(self.column(*t)?)?)))
            .fold((T::zero(), T::zero()), |(s, b), (j, c)| {
                (s + c * self.table_affine[j].0, b + c * self.table_slope(j))
            })
    }

    /// The sensor as the board stores it, from a fit of these terms (the
    /// geometry `geom`, the coefficients `coeffs` in column order), and
    /// the terms that predict the same readings for it; `coeffs` is updated
    /// to those terms (the gain's column).
    ///
    /// A fit with centred table columns ([`ExtTerms::table_affine`])
    /// predicts `f + g·x + Σ_j v_j·(C_j(x) − a_j − b_j·x) + …`, `x = f −
    /// d_ref`. The board's table has neither offset nor slope, so the gain
    /// becomes `g − Σ_j v_j·b_j` and `s = Σ_j v_j·a_j` moves into the zero
    /// point: `E' = E + k·u` gives `f' = f − k` (Chen eq. 1-3: the distance
    /// is measured from `E` along `u`), and `d_ref' = d_ref − k` keeps every
    /// distance term at the same `x`. A carry-over `c·(d_prev − f)` gains
    /// `c·k` by the shift, hence `k = s/(1 − c)`. Exact: the returned
    /// terms, filled with the returned sensor, predict what these terms and
    /// `geom` predict.
    pub fn stored(&self, geom: &Sensor<T>, coeffs: &mut [T]) -> (Sensor<T>, Self) {
        let (s, slope) = self.table_offset_slope(coeffs);
        let c = self
            .column(Term::Crosstalk)
            .and_then(|j| coeffs.get(j).copied())
            .unwrap_or_else(T::zero);
        let k = Self::zero_shift(s, c);
        if let Some(x) = self.column(Term::Gain).and_then(|g| coeffs.get_mut(g)) {
            *x -= slope;
        }
        let terms = Self {
            d_ref: self.d_ref - k,
            table_affine: [(T::zero(), T::zero()); TABLE_COEFFS],
            ..*self
        };
        let mut sensor = *geom;
        sensor.zero += sensor.dir * k;
        sensor.ext = terms.extension(coeffs);
        (sensor, terms)
    }

    /// `k = s/(1 − c)`: the zero point's shift along the beam that carries
    /// a table offset `s` beside a carry-over `c` ([`ExtTerms::stored`]).
    pub fn zero_shift(s: T, c: T) -> T {
        // A carry-over of 1 is no sensor (plausibility bounds it below 0.5).
        if (T::one() - c).abs() > T::lit(1e-9) {
            s / (T::one() - c)
        } else {
            s
        }
    }

    /// The table with these knots and values `c`.
    fn table(&self, c: [T; 3]) -> LinTable<T> {
        LinTable {
            knots: self.knots,
            coeffs: c,
        }
    }

    fn terms(&self) -> impl Iterator<Item = Term> + '_ {
        Term::ALL.into_iter().filter(|t| self.mask & t.bit() != 0)
    }

    /// The extension with the fitted coefficients `coeffs` (in column order,
    /// at least `count()` of them; missing ones count as 0).
    pub fn extension(&self, coeffs: &[T]) -> Extension<T> {
        let mut e = Extension::identity();
        e.d_ref = self.d_ref;
        e.temp_ref = self.temp_ref;
        let mut table = [T::zero(); 3];
        for (j, t) in self.terms().enumerate() {
            let c = coeffs.get(j).copied().unwrap_or_else(T::zero);
            match t {
                Term::Gain => e.gain = c,
                Term::Quadratic => e.nonlinearity[0] = c,
                Term::Cubic => e.nonlinearity[1] = c,
                Term::Incidence => e.incidence = c,
                Term::Crosstalk => e.crosstalk = c,
                Term::Thermal => e.thermal = c,
                Term::Drift => e.drift = c,
                Term::Table0 => table[0] = c,
                Term::Table1 => table[1] = c,
                Term::Table2 => table[2] = c,
                Term::SpotCos => e.spot[0] = c,
                Term::SpotSin => e.spot[1] = c,
            }
        }
        if table.iter().any(|c| *c != T::zero()) {
            e.table = self.table(table);
        }
        e
    }
}

impl<T: Real> Regressors<T> for ExtTerms<T> {
    fn count(&self) -> usize {
        self.mask.count_ones() as usize
    }

    fn fill<P: Poses<T> + ?Sized>(
        &self,
        poses: &P,
        k: usize,
        sensor: usize,
        geom: &Sensor<T>,
        out: &mut [T],
    ) {
        // The distance the current geometry predicts, never the reading
        // being predicted: a regressor built from that reading lets the fit
        // shrink the reading's own noise instead of explaining anything
        // (target leakage). Where the beam misses the plane at the estimate
        // the reading stands in (the solver skips that observation anyway).
        let plane = poses.plane(k);
        let d = distance(geom, &plane, sensor)
            .ok()
            .or_else(|| poses.reading(k, sensor))
            .unwrap_or_else(T::zero);
        let x = d - self.d_ref;
        let basis = match &self.cardinal {
            Some(c) if self.mask & Term::TABLE_BITS != 0 => c.basis(x),
            _ => [T::zero(); 3],
        };
        let n = poses.sensors().max(1);
        let ctx = poses.context(k);
        let inc = if self.mask & (Term::SpotCos.bit() | Term::SpotSin.bit()) != 0 {
            Incidence::of(&plane.n, &geom.dir)
        } else {
            Incidence::from(plane.n.dot(&geom.dir).abs())
        };
        for (slot, t) in out.iter_mut().zip(self.terms()) {
            *slot = match t {
                Term::Gain => x,
                Term::Quadratic => x * x,
                Term::Cubic => x * x * x,
                Term::Incidence => {
                    let c = inc.cos_gamma;
                    if c > T::zero() {
                        T::one() / c - T::one()
                    } else {
                        T::zero()
                    }
                }
                Term::Crosstalk => poses
                    .reading(k, (sensor + n - 1) % n)
                    .map_or_else(T::zero, |p| p - d),
                Term::Thermal => ctx.temp_c.map_or_else(T::zero, |t| t - self.temp_ref),
                Term::Drift => ctx.t_s.unwrap_or_else(T::zero),
                Term::Table0 => basis[0] - self.table_affine[0].0 - self.table_slope(0) * x,
                Term::Table1 => basis[1] - self.table_affine[1].0 - self.table_slope(1) * x,
                Term::Table2 => basis[2] - self.table_affine[2].0 - self.table_slope(2) * x,
                Term::SpotCos => inc.spot[0],
                Term::SpotSin => inc.spot[1],
            };
        }
    }

    fn name(&self, j: usize) -> &'static str {
        self.terms().nth(j).map_or("extension", Term::name)
    }

    fn ridge(&self, j: usize) -> T {
        match self.terms().nth(j) {
            Some(Term::Gain | Term::Table0 | Term::Table1 | Term::Table2)
                if self.mask & Term::TABLE_BITS != 0 =>
            {
                self.ridge
            }
            _ => T::zero(),
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::calib::testutil::{paper_heads, plane};
    use crate::calib::CalPose;
    use crate::ext::Context;
    use approx::assert_relative_eq;

    #[test]
    fn regressors_reproduce_extension_excess() {
        let (_, truth) = paper_heads();
        let p = plane(15.0, 2.0, 29.0);
        let pose = CalPose {
            plane: p,
            readings: [Some(33.0), Some(30.5), None, Some(35.25)],
            ctx: Context {
                temp_c: Some(31.0),
                t_s: Some(12.5),
            },
        };
        let poses = [pose];
        let terms = ExtTerms::new(&Term::ALL, 32.0, 21.0).with_knots([-4.0, -1.5, 0.5, 2.0, 5.0]);
        assert_eq!(Regressors::<f64>::count(&terms), 12);
        let c = [
            1e-3, 2e-4, -3e-5, 0.02, 4e-3, 1e-3, -2e-4, 3e-3, -1e-3, 2e-3, 0.03, -0.045,
        ];
        let ext = terms.extension(&c);
        for i in [0usize, 1, 3] {
            let mut x = [0.0; 12];
            terms.fill(poses.as_slice(), 0, i, &truth.sensors[i], &mut x);
            let lin: f64 = x.iter().zip(c.iter()).map(|(a, b)| a * b).sum();
            let prev = pose.readings[(i + 3) % 4];
            let inc = Incidence::of(&p.n, &truth.sensors[i].dir);
            assert!(
                inc.spot[0].abs() + inc.spot[1].abs() > 1e-3,
                "a tilted beam"
            );
            // The excess evaluated at the predicted distance, not the reading.
            let f = distance(&truth.sensors[i], &p, i).unwrap();
            let want = ext.excess(f, prev, inc, &pose.ctx);
            assert_relative_eq!(lin, want, epsilon = 1e-12);
            // ... so the pose's own reading does not enter its regressors.
            let mut moved = poses;
            moved[0].readings[i] = Some(pose.readings[i].unwrap() + 0.7);
            let mut y = [0.0; 12];
            terms.fill(moved.as_slice(), 0, i, &truth.sensors[i], &mut y);
            assert_eq!(x, y);
        }
        assert_eq!(Regressors::<f64>::name(&terms, 4), "crosstalk");
        let only = ExtTerms::new(&[Term::Thermal, Term::Gain], 30.0, 20.0);
        assert_eq!(Regressors::<f64>::name(&only, 0), "gain");
        assert_eq!(Regressors::<f64>::name(&only, 1), "thermal");
        let e = only.extension(&[0.5, 0.25]);
        assert_eq!(
            (e.gain, e.thermal, e.d_ref, e.temp_ref),
            (0.5, 0.25, 30.0, 20.0)
        );
    }

    /// A fit with centred table columns, stored for the board, predicts
    /// every reading it predicted (offset into the zero point, slope into
    /// the gain, beside a carry-over), through the board's own
    /// [`Extension::excess`] and through the returned terms.
    #[test]
    fn stored_table_predicts_what_the_centred_fit_did() {
        let (_, truth) = paper_heads();
        let terms = ExtTerms::new(
            &[
                Term::Gain,
                Term::Crosstalk,
                Term::Table0,
                Term::Table1,
                Term::Table2,
            ],
            31.0,
            20.0,
        )
        .with_knots([-4.0, -1.5, 0.5, 2.0, 5.0])
        .with_table_affine([(0.31, -0.02), (0.45, 0.01), (0.22, 0.05)]);
        let fitted = [2e-3, 0.04, 0.03, -0.02, 0.025];
        for i in [0usize, 1, 3] {
            let geom = truth.sensors[i];
            let mut coeffs = fitted;
            let (stored, back) = terms.stored(&geom, &mut coeffs);
            assert!(back
                .table_affine
                .iter()
                .all(|(a, b)| *a == 0.0 && *b == 0.0));
            for (tilt, off) in [(0.0, 28.0), (6.0, 30.5), (-9.0, 33.0), (12.0, 35.5)] {
                let p = plane(tilt, tilt / 2.0, off);
                let pose = CalPose {
                    plane: p,
                    readings: [Some(30.0), Some(31.0), Some(32.0), Some(33.0)],
                    ctx: Context::default(),
                };
                let poses = [pose];
                let predict = |t: &ExtTerms<f64>, s: &Sensor<f64>, c: &[f64]| {
                    let mut x = [0.0; 5];
                    t.fill(poses.as_slice(), 0, i, s, &mut x);
                    distance(s, &p, i).unwrap() + x.iter().zip(c).map(|(a, b)| a * b).sum::<f64>()
                };
                let want = predict(&terms, &geom, &fitted);
                assert_relative_eq!(predict(&back, &stored, &coeffs), want, epsilon = 1e-9);
                let f = distance(&stored, &p, i).unwrap();
                let prev = pose.readings[(i + 3) % 4];
                let cg = p.n.dot(&stored.dir).abs();
                let board = f + stored.ext.excess(f, prev, cg, &pose.ctx);
                assert_relative_eq!(board, want, epsilon = 1e-9);
            }
            assert_relative_eq!(stored.dir, geom.dir);
            assert!(
                (stored.zero - geom.zero).norm() > 1e-3,
                "the offset moved the zero point"
            );
        }
    }
}
