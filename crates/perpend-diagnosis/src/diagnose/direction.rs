//! Direction-dependent offsets (hysteresis-like): does each sensor's
//! reading depend on the sign of its last move?
//!
//! A reading that lags its sensor's move reads `−hᵢ·sign(dᵢ,k − dᵢ,k−1)`
//! off (issue 35, item 4; the blind generator's `hysteresis`). The test,
//! judged in the decision stage after the nominal fit:
//!
//! 1. **Measurement order**: `t_s` when every kept pose has it, else the
//!    file's order when its pose numbers increase; otherwise (rows shuffled
//!    without `t_s`) the moves are unknown and the test does not run.
//! 2. **Per sensor**: the nominal fit's in-sample residuals regressed on
//!    the sign of that sensor's last move (the change of its predicted
//!    distance since the pose before in measurement order; the first pose
//!    left out), beside an intercept, the predicted distance and its square
//!    as nuisance columns: an effect of the distance alone (gain, a
//!    nonlinearity), whose residual also follows the last move's sign, is
//!    not taken for a direction effect. `hᵢ = −b` with its 1σ and `tᵢ`.
//! 3. **Pooled**: `T = Σ tᵢ²` over the sensors (either sign of each `hᵢ`).
//! 4. **Null**: the same `T` on the diagnosis's effect-free re-simulations
//!    ([`super::expect::null_table`]: the fitted head as the truth, the
//!    same planes, the reading and tracker noise estimated from the run,
//!    the draws' seeds of [`super::expect::expect`]), continued to
//!    [`NULL_DRAWS`] draws since only the nominal fit is needed. A shared
//!    per-pose plane error (tracker noise) moves every sensor's residual
//!    with the pose's plane, not with each sensor's own move sign; its
//!    leak into the move signs is in the null at the run's tracker noise.
//!    `z = (∛T − mean)/predictive sd` of `∛T` over the draws (the cube
//!    root takes the χ²-like skew out, Wilson-Hilferty), `p` its one-sided
//!    Student-t tail with draws − 1 degrees of freedom; named when `p` is
//!    below the decision's family level `α/m` (the candidates and this
//!    test).
//!
//! Limits: the order of the kept poses only (a pose left out as a blunder
//! still moved the head); a move smaller than the noise has an uncertain
//! sign in the geometry; a direction effect on a verdict that already names
//! an effect is reported, not judged (its residuals carry that effect).

use perpend_core::calib::LsqConfig;
use perpend_core::head::Sensor;
use perpend_core::model::distance;

use super::expect::{null_draw, NoiseModel, Spread};
use perpend_calib::candidates::{fit, Effect, Refs};
use perpend_calib::noise::residuals_of;
use perpend_calib::stats::{self, t_tail, P_MIN};
use perpend_formats::exchange::PoseTable;

/// Effect-free re-simulations behind the null of `T` (the diagnosis's own
/// draws first, the same seed sequence continued).
pub const NULL_DRAWS: usize = 48;

/// Fewest moves per sensor for its regression.
const MIN_MOVES: usize = 8;

/// Which order the moves were taken in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Order {
    /// The `t_s` column.
    Time,
    /// The rows of the file (pose numbers increasing).
    File,
}

impl Order {
    /// In words, for the report.
    pub fn name(self) -> &'static str {
        match self {
            Order::Time => "t_s",
            Order::File => "file order",
        }
    }
}

/// One sensor's direction-dependent offset.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorOffset {
    /// `h`: the reading is `−h·sign(last move)` off [mm].
    pub h_mm: f64,
    /// Its 1σ [mm].
    pub sigma_mm: f64,
    /// `h / σ`.
    pub t: f64,
}

/// The test's result when it could run.
#[derive(Debug, Clone, PartialEq)]
pub struct Tested {
    /// The measurement order used.
    pub order: Order,
    /// Per sensor (`None`: too few moves).
    pub sensors: Vec<Option<SensorOffset>>,
    /// Pooled `T = Σ tᵢ²`.
    pub stat: f64,
    /// `T` over the effect-free re-simulations.
    pub null: Spread,
    /// One-sided p of `T` against that null.
    pub p: f64,
    /// The level `p` is compared with (`α/m`).
    pub level: f64,
    /// `p < level`: a direction-dependent offset is found.
    pub found: bool,
}

/// The test: run, or why not.
#[derive(Debug, Clone, PartialEq)]
pub enum DirectionTest {
    /// It ran.
    Tested(Tested),
    /// It could not run, and why.
    Untestable(String),
}

impl DirectionTest {
    /// Whether a direction-dependent offset was found.
    pub fn found(&self) -> bool {
        matches!(self, DirectionTest::Tested(t) if t.found)
    }

    /// One line for the report.
    pub fn line(&self) -> String {
        let t = match self {
            DirectionTest::Untestable(why) => {
                return format!("direction-dependent offset: cannot test: {why}")
            }
            DirectionTest::Tested(t) => t,
        };
        let per: Vec<String> = t
            .sensors
            .iter()
            .enumerate()
            .map(|(i, s)| match s {
                Some(s) => format!(
                    "s{} {:.1} ± {:.1}",
                    i + 1,
                    1000.0 * s.h_mm,
                    1000.0 * s.sigma_mm
                ),
                None => format!("s{} –", i + 1),
            })
            .collect();
        let what = if t.found {
            "found: the readings depend on the sign of each sensor's last move"
        } else {
            "not found"
        };
        format!(
            "direction-dependent offset {what} (h per sensor [µm]: {}; p {} against {} effect-free re-simulations, level {:.1e}; order: {})",
            per.join(", "),
            if t.p <= P_MIN {
                format!("< {P_MIN:.0e}")
            } else {
                format!("= {:.2e}", t.p)
            },
            t.null.n,
            t.level,
            t.order.name()
        )
    }
}

/// The rows of `poses` in measurement order, and which order that is.
///
/// # Errors
/// Neither `t_s` on every pose nor increasing pose numbers: the order of
/// the moves is unknown.
pub fn measurement_order(poses: &PoseTable) -> Result<(Order, Vec<usize>), String> {
    let times: Option<Vec<f64>> = poses
        .rows
        .iter()
        .map(|r| r.t_s.filter(|t| t.is_finite()))
        .collect();
    let mut idx: Vec<usize> = (0..poses.rows.len()).collect();
    if let Some(t) = times {
        idx.sort_by(|&a, &b| t[a].total_cmp(&t[b]));
        return Ok((Order::Time, idx));
    }
    if poses.rows.windows(2).all(|w| w[0].pose < w[1].pose) {
        return Ok((Order::File, idx));
    }
    Err("the rows carry no t_s and their pose numbers do not increase, so the order of the moves is unknown; write t_s (or the rows in the order measured)".into())
}

/// Per row: a sensor's predicted distance and the sign of its last move
/// (`None` for the first pose in measurement order).
type Moves = Vec<Option<(f64, f64)>>;

/// Per row, sensor `i`'s predicted distance under `geom` and the sign of
/// its last move ([`Moves`]).
fn moves(geom: &Sensor<f64>, i: usize, poses: &PoseTable, order: &[usize]) -> Moves {
    let d: Vec<Option<f64>> = poses
        .rows
        .iter()
        .map(|r| distance(geom, &r.plane, i).ok())
        .collect();
    let mut out = vec![None; poses.rows.len()];
    for w in order.windows(2) {
        if let (Some(a), Some(b)) = (d[w[0]], d[w[1]]) {
            out[w[1]] = Some((b, if b >= a { 1.0 } else { -1.0 }));
        }
    }
    out
}

/// Least squares of `y` on the columns `x` (rows of equal length): the
/// coefficient of the last column, its 1σ. `None` when singular.
fn last_coefficient(x: &[Vec<f64>], y: &[f64]) -> Option<(f64, f64)> {
    let (n, m) = (y.len(), x.first()?.len());
    if n <= m {
        return None;
    }
    // Normal equations [XᵀX | I | Xᵀy], Gauss-Jordan with partial pivoting.
    let w = 2 * m + 1;
    let mut a = vec![vec![0.0; w]; m];
    for (row, &yk) in x.iter().zip(y) {
        for j in 0..m {
            for l in 0..m {
                a[j][l] += row[j] * row[l];
            }
            a[j][2 * m] += row[j] * yk;
        }
    }
    for (j, r) in a.iter_mut().enumerate() {
        r[m + j] = 1.0;
    }
    for c in 0..m {
        let p = (c..m).max_by(|&u, &v| a[u][c].abs().total_cmp(&a[v][c].abs()))?;
        a.swap(c, p);
        let piv = a[c][c];
        if piv.abs() < 1e-12 {
            return None;
        }
        let pr: Vec<f64> = a[c].iter().map(|v| v / piv).collect();
        for (r, row) in a.iter_mut().enumerate() {
            let f = if r == c { 0.0 } else { row[c] };
            for (v, q) in row.iter_mut().zip(&pr) {
                *v = if r == c { *q } else { *v - f * q };
            }
        }
    }
    let beta: Vec<f64> = (0..m).map(|j| a[j][2 * m]).collect();
    let rss: f64 = x
        .iter()
        .zip(y)
        .map(|(row, yk)| yk - row.iter().zip(&beta).map(|(u, b)| u * b).sum::<f64>())
        .map(|e| e * e)
        .sum();
    let var = rss / (n - m) as f64 * a[m - 1][2 * m - 1];
    Some((beta[m - 1], var.max(0.0).sqrt()))
}

/// Sensor `i`'s offset from its residuals `resid` and `moves` ([`moves`]).
fn sensor_offset(resid: &[Option<f64>], moves: &[Option<(f64, f64)>]) -> Option<SensorOffset> {
    let pairs: Vec<(f64, f64, f64)> = resid
        .iter()
        .zip(moves)
        .filter_map(|(r, m)| Some((r.as_ref()?, m.as_ref()?)))
        .map(|(r, &(d, s))| (*r, d, s))
        .collect();
    if pairs.len() < MIN_MOVES {
        return None;
    }
    let ds: Vec<f64> = pairs.iter().map(|p| p.1).collect();
    let (dm, dsd) = (stats::mean(&ds), stats::sd(&ds).max(1e-9));
    let x: Vec<Vec<f64>> = pairs
        .iter()
        .map(|&(_, d, s)| {
            let u = (d - dm) / dsd;
            vec![1.0, u, u * u, s]
        })
        .collect();
    let y: Vec<f64> = pairs.iter().map(|p| p.0).collect();
    let (b, se) = last_coefficient(&x, &y)?;
    (se > 0.0).then(|| SensorOffset {
        h_mm: -b,
        sigma_mm: se,
        t: -b / se,
    })
}

/// Per sensor offsets and the pooled `T` of the residuals `resid`
/// `[pose][sensor]` of the nominal fit `geom` on `poses`.
fn pooled(
    geom: &[Sensor<f64>],
    poses: &PoseTable,
    order: &[usize],
    resid: &[Vec<Option<f64>>],
) -> (f64, Vec<Option<SensorOffset>>) {
    let per: Vec<Option<SensorOffset>> = geom
        .iter()
        .enumerate()
        .map(|(i, g)| {
            let r: Vec<Option<f64>> = resid
                .iter()
                .map(|row| row.get(i).copied().flatten())
                .collect();
            sensor_offset(&r, &moves(g, i, poses, order))
        })
        .collect();
    let t = per.iter().flatten().map(|s| s.t * s.t).sum();
    (t, per)
}

/// What the null re-simulations need.
pub struct NullPlan<'a> {
    /// The fitted head taken as the truth.
    pub truth: &'a [Sensor<f64>],
    /// The nominal head the fits start from.
    pub nominal: &'a [Sensor<f64>],
    /// Term references of the run.
    pub refs: &'a Refs,
    /// The noise estimated from the run.
    pub noise: &'a NoiseModel,
    /// Solver settings.
    pub lsq: &'a LsqConfig<f64>,
    /// The diagnosis's seed.
    pub seed: u64,
}

/// `T` on effect-free re-simulations (seeds as [`super::expect::expect`]).
fn null_stats(plan: &NullPlan<'_>, poses: &PoseTable, order: &[usize]) -> Vec<f64> {
    (0..NULL_DRAWS)
        .filter_map(|j| {
            let table = null_draw(plan.truth, poses, plan.noise, plan.seed, j);
            let fits: Vec<_> = plan
                .nominal
                .iter()
                .enumerate()
                .map(|(i, s)| fit(s, i, &table, plan.refs.terms(Effect::None, i), plan.lsq).ok())
                .collect::<Option<_>>()?;
            let resid = residuals_of(&fits, &table);
            let geom: Vec<Sensor<f64>> = fits.iter().map(|f| f.sensor).collect();
            Some(pooled(&geom, &table, order, &resid).0)
        })
        .collect()
}

/// The test on the nominal fit `geom` with in-sample residuals `resid`
/// (module docs); `level` is the family level `α/m`.
pub fn judge(
    poses: &PoseTable,
    geom: &[Sensor<f64>],
    resid: &[Vec<Option<f64>>],
    plan: &NullPlan<'_>,
    level: f64,
) -> DirectionTest {
    let (order_kind, order) = match measurement_order(poses) {
        Ok(o) => o,
        Err(why) => return DirectionTest::Untestable(why),
    };
    let (stat, sensors) = pooled(geom, poses, &order, resid);
    if sensors.iter().all(Option::is_none) {
        return DirectionTest::Untestable(format!(
            "fewer than {MIN_MOVES} moves with a reading on every sensor"
        ));
    }
    let nulls = null_stats(plan, poses, &order);
    let null = Spread::of(&nulls);
    if null.n < 2 {
        return DirectionTest::Untestable("the effect-free re-simulations failed".into());
    }
    // T is skewed like a χ²: its cube root is nearly normal (Wilson and
    // Hilferty 1931), so the Student tail fits the null's far end.
    let root = Spread::of(&nulls.iter().map(|t| t.cbrt()).collect::<Vec<_>>());
    let z = (stat.cbrt() - root.mean) / root.predictive_sd(1e-12);
    let p = t_tail(z, (null.n - 1) as f64);
    DirectionTest::Tested(Tested {
        order: order_kind,
        sensors,
        stat,
        null,
        p,
        level,
        found: p < level,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// Residuals `noise + f(d) − h·s` on a random walk of distances.
    fn synthetic(h: f64, f: impl Fn(f64) -> f64, seed: u64) -> (Vec<Option<f64>>, Moves) {
        let mut rng = StdRng::seed_from_u64(seed);
        let d: Vec<f64> = (0..200).map(|_| rng.gen_range(20.0..30.0)).collect();
        let mut resid = vec![None];
        let mut mv = vec![None];
        for k in 1..d.len() {
            let s = if d[k] >= d[k - 1] { 1.0 } else { -1.0 };
            resid.push(Some(
                0.01 * perpend_calib::sim::gauss(&mut rng) + f(d[k]) - h * s,
            ));
            mv.push(Some((d[k], s)));
        }
        (resid, mv)
    }

    #[test]
    fn offset_is_recovered_within_its_sigma() {
        let (r, m) = synthetic(0.02, |_| 0.0, 1);
        let s = sensor_offset(&r, &m).unwrap();
        assert!((s.h_mm - 0.02).abs() < 3.0 * s.sigma_mm, "{s:?}");
        // 200 moves at 10 µm: σ about 10/√200 µm
        assert!(s.sigma_mm > 0.0005 && s.sigma_mm < 0.001, "{s:?}");
        assert!(s.t > 10.0, "{s:?}");
    }

    #[test]
    fn an_effect_of_the_distance_alone_is_not_a_direction_effect() {
        // A gain-like and curved error follows the last move's sign too
        // (a high distance is mostly reached by a move outwards).
        let mut big = 0;
        for seed in 0..20 {
            let (r, m) = synthetic(
                0.0,
                |d| 0.01 * (d - 25.0) + 0.002 * (d - 25.0).powi(2),
                seed,
            );
            let s = sensor_offset(&r, &m).unwrap();
            big += usize::from(s.t.abs() > 3.0);
        }
        assert!(big <= 1, "{big} of 20 runs with |t| > 3");
    }

    #[test]
    fn order_is_time_then_increasing_pose_numbers_else_unknown() {
        use perpend_formats::exchange::PoseRow;
        let row = |pose: i64, t: Option<f64>| PoseRow {
            line: 0,
            pose,
            abcd: [0.0, 0.0, 1.0, 0.0],
            plane: perpend_core::geometry::Plane::from_abcd(0.0, 0.0, 1.0, 0.0).unwrap(),
            readings: vec![],
            t_s: t,
            temp_c: None,
            noise: Default::default(),
        };
        let table = |rows| PoseTable { n_sensors: 0, rows };
        let timed = table(vec![
            row(3, Some(20.0)),
            row(1, Some(5.0)),
            row(2, Some(10.0)),
        ]);
        assert_eq!(
            measurement_order(&timed).unwrap(),
            (Order::Time, vec![1, 2, 0])
        );
        let file = table(vec![row(1, None), row(2, None), row(5, None)]);
        assert_eq!(
            measurement_order(&file).unwrap(),
            (Order::File, vec![0, 1, 2])
        );
        let shuffled = table(vec![row(2, None), row(1, None), row(3, None)]);
        assert!(measurement_order(&shuffled).is_err());
    }
}
