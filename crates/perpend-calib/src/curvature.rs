//! `perpend bench curvature`: the micro-plane (Chen eq. 18-19, Tian §3)
//! against the curved model of [`perpend_core::surface`] on spheres and
//! cylinders (issue 14), and a simulated alignment loop.
//!
//! **Accuracy** — per seed, a Tian-style head ([`tian_style_head`]: cone
//! 25°, zero points on a 45 mm circle, standoff 60 mm, true head with
//! zero-point errors ±`zero_err_mm` and beam tilts ±`dir_err_rad`) is
//! calibrated with the 5-DOF least squares ([`fit_sensor_base`]) on a
//! plane run (100 poses, ±10° about x and y, standoff 60 ± 5 mm, tracker
//! ξ = 0.02 mm on 20 points, reading noise ζ = 0.01 mm). Then, for every
//! shape, radius and tilt, test surfaces: the surface passes through the
//! spindle axis at z = 60 ± 2.5 mm with its normal tilted by `tilt` from
//! the axis towards a uniform azimuth; a cylinder's axis lies in the
//! tangent plane at a uniform azimuth. The true head reads it with the
//! same ζ. On the same readings: `plane` — the calibrated head's
//! micro-plane (least squares, the board's default); `curved` — the
//! calibrated head with [`perpend_core::surface::measure`] and the nominal
//! shape; `floor` — the same with the true head (what perfect calibration
//! achieves). Each is the angle to the true normal where the spindle axis
//! meets the surface; the rows give the means over seeds × surfaces.
//!
//! **Alignment loop** — Tian's auto-normalisation (§2 (1), pitch and yaw
//! about the drilling point, which stays put): from a start tilted by
//! `align_tilt` at a uniform azimuth, measure, turn the head by Chen's
//! pitch/yaw (eq. 22) about the measured axis point, measure again; count
//! the moves until the true deviation θ is below [`ALIGNED_DEG`], at most
//! [`MAX_MOVES`]. The cylinder's axis direction is handed to the model in
//! the current TCS (the robot knows its own rotation).
//!
//! Limits: the surfaces are exact spheres and cylinders of the given
//! radius (the model's error for a wrong radius or axis is studied with
//! `--radius-err` and `--axis-err-deg`); no reading effects beyond ζ.

use anyhow::{anyhow, bail, Result};
use nalgebra::{Matrix3, Vector3};
use perpend_core::calib::{fit_sensor_base, LsqConfig};
use perpend_core::ext::Context;
use perpend_core::geometry::tangent_basis;
use perpend_core::head::Head4;
use perpend_core::normal::Method;
use perpend_core::surface::{measure, CurvedSurface, Shape};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::Serialize;

use crate::sim::{
    curved_readings, simulate, tian_style_head, PoseSpread, SimConfig, SimHead, Tracker,
    TIAN_STANDOFF_MM,
};

/// Deviation [deg] below which the alignment loop counts as done.
pub const ALIGNED_DEG: f64 = 0.05;
/// Moves after which the alignment loop gives up.
pub const MAX_MOVES: usize = 10;

/// Arguments of `perpend bench curvature`.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Number of seeds (head, calibration, test surfaces).
    #[arg(long, default_value_t = 10)]
    pub seeds: u64,
    /// First seed.
    #[arg(long, default_value_t = 1)]
    pub first_seed: u64,
    /// Test surfaces per seed, shape, radius and tilt.
    #[arg(long, default_value_t = 50)]
    pub surfaces: usize,
    /// Radii [mm], comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = [300.0, 500.0, 1000.0, 2000.0, 5000.0])]
    pub radii: Vec<f64>,
    /// Tilts [deg] of the head from the normal, comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = [0.0, 2.0, 5.0, 10.0])]
    pub tilts: Vec<f64>,
    /// Concave surfaces (the inside of a sphere or barrel) instead of convex.
    #[arg(long)]
    pub concave: bool,
    /// Zero-point errors of the true head, uniform in ± this [mm].
    #[arg(long, default_value_t = 1.0)]
    pub zero_err_mm: f64,
    /// Beam tilt errors of the true head, uniform in ± this [rad].
    #[arg(long, default_value_t = 0.02)]
    pub dir_err_rad: f64,
    /// Relative error of the radius handed to the curved model (0.1: 10 % too large).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub radius_err: f64,
    /// Error of the cylinder axis azimuth handed to the curved model [deg].
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub axis_err_deg: f64,
    /// Alignment-loop starts per seed, shape and radius.
    #[arg(long, default_value_t = 10)]
    pub align_trials: usize,
    /// Tilt [deg] the alignment loop starts from.
    #[arg(long, default_value_t = 10.0)]
    pub align_tilt: f64,
    /// Print one JSON object {config, rows, alignment}.
    #[arg(long)]
    pub json: bool,
}

/// The two nominal shapes of the benchmark.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    /// A sphere.
    Sphere,
    /// A circular cylinder.
    Cylinder,
}

/// One row of the accuracy table: mean normal errors [deg].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Row {
    /// Shape.
    pub shape: Kind,
    /// Signed radius [mm] (negative: concave).
    pub radius_mm: f64,
    /// Tilt of the head from the normal [deg].
    pub tilt_deg: f64,
    /// Micro-plane, calibrated head.
    pub plane_deg: f64,
    /// Curved model, calibrated head.
    pub curved_deg: f64,
    /// Curved model, true head.
    pub floor_deg: f64,
    /// `curved_deg / floor_deg`.
    pub ratio: f64,
    /// Largest error of the curved model, calibrated head.
    pub curved_max_deg: f64,
    /// Surfaces measured.
    pub n: usize,
}

/// Alignment-loop figures of one model on one shape and radius.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct AlignRow {
    /// Shape.
    pub shape: Kind,
    /// Signed radius [mm].
    pub radius_mm: f64,
    /// `plane` or `curved`.
    pub model: &'static str,
    /// Tilt the loop starts from [deg].
    pub start_deg: f64,
    /// Mean moves to θ < [`ALIGNED_DEG`], over the starts that got there
    /// (`None` when none did).
    pub moves_mean: Option<f64>,
    /// Most moves needed by a start that got there.
    pub moves_max: usize,
    /// Starts that did not get there within [`MAX_MOVES`].
    pub not_reached: usize,
    /// Starts.
    pub trials: usize,
    /// Mean true θ after the last move [deg].
    pub final_deg: f64,
}

/// The calibrated and the true head of one seed.
struct Heads {
    sim: SimHead,
    calibrated: Head4<f64>,
    truth: Head4<f64>,
}

fn head4(s: &[perpend_core::head::Sensor<f64>]) -> Result<Head4<f64>> {
    let arr: [_; 4] = s
        .to_vec()
        .try_into()
        .map_err(|_| anyhow!("the benchmark needs a four-sensor head"))?;
    Ok(Head4::new(arr))
}

/// The noise of every reading (calibration and test): Chen §5's ζ.
fn sim_config() -> SimConfig {
    SimConfig {
        poses: 100,
        spread: PoseSpread::cell(TIAN_STANDOFF_MM),
        tracker: Some(Tracker::paper()),
        ..SimConfig::paper()
    }
}

/// Draws the head of `seed` and calibrates it on a plane run (LSQ).
fn calibrated_heads(a: &Args, rng: &mut StdRng) -> Result<Heads> {
    let sim = tian_style_head(rng, a.zero_err_mm, a.dir_err_rad)?;
    let data = simulate(&sim, &sim_config(), &[], rng)?;
    let lsq = LsqConfig::default();
    let mut fitted = Vec::new();
    for (i, s) in sim.nominal.iter().enumerate() {
        let f = fit_sensor_base(s, i, &data.poses, &lsq)
            .map_err(|e| anyhow!("calibration of sensor {}: {e}", i + 1))?;
        fitted.push(f.sensor);
    }
    Ok(Heads {
        calibrated: head4(&fitted)?,
        truth: head4(&sim.truth)?,
        sim,
    })
}

/// Unit normal towards the head, tilted `tilt` [rad] from −z towards the
/// azimuth `az` [rad].
fn tilted(tilt: f64, az: f64) -> Vector3<f64> {
    Vector3::new(tilt.sin() * az.cos(), tilt.sin() * az.sin(), -tilt.cos())
}

/// A random test surface of `kind` and signed radius `r` through the
/// spindle axis with its normal tilted by `tilt_deg`.
fn draw_surface(kind: Kind, r: f64, tilt_deg: f64, rng: &mut StdRng) -> Result<CurvedSurface<f64>> {
    let az = rng.gen_range(0.0..std::f64::consts::TAU);
    let z = TIAN_STANDOFF_MM + rng.gen_range(-2.5..=2.5);
    let n = tilted(tilt_deg.to_radians(), az);
    let shape = match kind {
        Kind::Sphere => Shape::Sphere { radius: r },
        Kind::Cylinder => {
            let (t1, t2) = tangent_basis(&n);
            let psi = rng.gen_range(0.0..std::f64::consts::PI);
            Shape::Cylinder {
                radius: r,
                axis: t1 * psi.cos() + t2 * psi.sin(),
            }
        }
    };
    CurvedSurface::through(Vector3::new(0.0, 0.0, z), n, &shape).map_err(|e| anyhow!("{e}"))
}

/// The shape the curved model is told: the true one with the radius and
/// axis azimuth errors of the arguments.
fn told_shape(a: &Args, s: &CurvedSurface<f64>) -> Shape<f64> {
    let radius = s.radius * (1.0 + a.radius_err);
    match s.axis {
        None => Shape::Sphere { radius },
        Some(ax) => {
            // Turn the axis about the normal at the axis point.
            let n = s.axis_point().map_or(-Vector3::z(), |(_, n)| n);
            let rot = nalgebra::Rotation3::from_axis_angle(
                &nalgebra::Unit::new_normalize(n),
                a.axis_err_deg.to_radians(),
            );
            Shape::Cylinder {
                radius,
                axis: rot * ax,
            }
        }
    }
}

fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b)).to_degrees()
}

/// Normal [TCS] and axis point of `head` on `r` with `shape`.
fn normal_of(
    head: &Head4<f64>,
    r: &[Option<f64>],
    shape: &Shape<f64>,
) -> Result<(Vector3<f64>, Vector3<f64>)> {
    let r4 = [r[0], r[1], r[2], r[3]];
    let m = measure(head, &r4, &Context::default(), Method::LeastSquares, shape)
        .map_err(|e| anyhow!("{e}"))?;
    Ok((m.fit.normal, m.fit.point))
}

/// Errors [deg] of plane, curved and floor on one test surface.
fn errors_on(a: &Args, h: &Heads, s: &CurvedSurface<f64>, rng: &mut StdRng) -> Result<[f64; 3]> {
    let r = curved_readings(&h.sim, &sim_config(), s, rng);
    if r.iter().any(Option::is_none) {
        bail!("a test surface is out of the sensors' reach");
    }
    let (_, n_true) = s.axis_point().map_err(|e| anyhow!("{e}"))?;
    let told = told_shape(a, s);
    let (plane, _) = normal_of(&h.calibrated, &r, &Shape::Plane)?;
    let (curved, _) = normal_of(&h.calibrated, &r, &told)?;
    let (floor, _) = normal_of(&h.truth, &r, &told)?;
    Ok([
        angle_deg(&plane, &n_true),
        angle_deg(&curved, &n_true),
        angle_deg(&floor, &n_true),
    ])
}

fn mean(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |a, b| a + b) / v.len().max(1) as f64
}

/// The accuracy table over all seeds.
///
/// # Errors
/// Simulation, calibration or measurement failures.
pub fn accuracy(a: &Args) -> Result<Vec<Row>> {
    let sign = if a.concave { -1.0 } else { 1.0 };
    let cells: Vec<(Kind, f64, f64)> = [Kind::Sphere, Kind::Cylinder]
        .iter()
        .flat_map(|&k| {
            a.radii
                .iter()
                .flat_map(move |&r| a.tilts.iter().map(move |&t| (k, sign * r, t)))
        })
        .collect();
    let mut errs: Vec<[Vec<f64>; 3]> = vec![Default::default(); cells.len()];
    let bar = perpend_formats::progress::Progress::new(a.seeds, "curvature: seeds");
    for seed in a.first_seed..a.first_seed + a.seeds {
        bar.inc();
        let mut rng = StdRng::seed_from_u64(seed);
        let h = calibrated_heads(a, &mut rng)?;
        for (cell, e) in cells.iter().zip(errs.iter_mut()) {
            for _ in 0..a.surfaces {
                let s = draw_surface(cell.0, cell.1, cell.2, &mut rng)?;
                let v = errors_on(a, &h, &s, &mut rng)
                    .map_err(|err| anyhow!("seed {seed}, {cell:?}: {err}"))?;
                for k in 0..3 {
                    e[k].push(v[k]);
                }
            }
        }
    }
    Ok(cells
        .iter()
        .zip(errs)
        .map(|(&(shape, radius_mm, tilt_deg), [p, c, f])| Row {
            shape,
            radius_mm,
            tilt_deg,
            plane_deg: mean(&p),
            curved_deg: mean(&c),
            floor_deg: mean(&f),
            ratio: mean(&c) / mean(&f),
            curved_max_deg: c.iter().copied().fold(0.0, f64::max),
            n: c.len(),
        })
        .collect())
}

/// One run of the alignment loop; returns the moves made (`None`: not
/// aligned within [`MAX_MOVES`]) and the final true θ [deg].
fn align_once(
    a: &Args,
    h: &Heads,
    world: &CurvedSurface<f64>,
    curved: bool,
    rng: &mut StdRng,
) -> Result<(Option<usize>, f64)> {
    let (mut rot, mut trans) = (Matrix3::<f64>::identity(), Vector3::<f64>::zeros());
    for k in 0..=MAX_MOVES {
        // The surface in the current TCS: x_tcs = rotᵀ·(x_w − trans).
        let rt = rot.transpose();
        let s = world.transformed(&rt, &(-(rt * trans)));
        let (_, n_true) = s.axis_point().map_err(|e| anyhow!("{e}"))?;
        let theta = angle_deg(&n_true, &-Vector3::z());
        if theta < ALIGNED_DEG {
            return Ok((Some(k), theta));
        }
        let r = curved_readings(&h.sim, &sim_config(), &s, rng);
        let shape = if curved {
            told_shape(a, &s)
        } else {
            Shape::Plane
        };
        let measured = if r.iter().any(Option::is_none) {
            None
        } else {
            normal_of(&h.calibrated, &r, &shape).ok()
        };
        let (Some((n, point)), true) = (measured, k < MAX_MOVES) else {
            return Ok((None, theta));
        };
        let dev = perpend_core::angles::Deviation::from_normal(&n).map_err(|e| anyhow!("{e}"))?;
        let turn = perpend_core::angles::Attitude::from_deviation(&dev).rotation();
        // Pivot about the measured axis point (Tian's VTCP): it keeps its
        // place in the world and on the new spindle axis.
        let pivot_w = rot * point + trans;
        rot *= turn;
        trans = pivot_w - rot * point;
    }
    Ok((None, 180.0))
}

/// Moves and final θ of one alignment row.
#[derive(Default)]
struct AlignAcc {
    moves: Vec<f64>,
    finals: Vec<f64>,
    missed: usize,
}

/// The alignment-loop rows over all seeds: the same starts for both models.
///
/// # Errors
/// Simulation or calibration failures.
pub fn alignment(a: &Args) -> Result<Vec<AlignRow>> {
    let sign = if a.concave { -1.0 } else { 1.0 };
    let keys: Vec<(Kind, f64)> = [Kind::Sphere, Kind::Cylinder]
        .iter()
        .flat_map(|&k| a.radii.iter().map(move |&r| (k, sign * r)))
        .collect();
    let mut acc: Vec<[AlignAcc; 2]> = keys.iter().map(|_| Default::default()).collect();
    for seed in a.first_seed..a.first_seed + a.seeds {
        let mut rng = StdRng::seed_from_u64(seed ^ 0x000a_116e);
        let h = calibrated_heads(a, &mut rng)?;
        for (&(kind, r), acc) in keys.iter().zip(acc.iter_mut()) {
            for _ in 0..a.align_trials {
                let s = draw_surface(kind, r, a.align_tilt, &mut rng)?;
                let noise = rng.clone();
                for (m, curved) in [false, true].into_iter().enumerate() {
                    let (moves, fin) = align_once(a, &h, &s, curved, &mut noise.clone())?;
                    let x = &mut acc[m];
                    x.finals.push(fin);
                    match moves {
                        Some(k) => x.moves.push(k as f64),
                        None => x.missed += 1,
                    }
                }
                rng.gen::<u64>();
            }
        }
    }
    let mut rows = Vec::new();
    for (&(shape, radius_mm), pair) in keys.iter().zip(&acc) {
        for (x, model) in pair.iter().zip(["plane", "curved"]) {
            rows.push(AlignRow {
                shape,
                radius_mm,
                model,
                start_deg: a.align_tilt,
                moves_mean: (!x.moves.is_empty()).then(|| mean(&x.moves)),
                moves_max: x.moves.iter().fold(0.0f64, |p, q| p.max(*q)) as usize,
                not_reached: x.missed,
                trials: x.finals.len(),
                final_deg: mean(&x.finals),
            });
        }
    }
    Ok(rows)
}

fn check(a: &Args) -> Result<()> {
    if a.seeds == 0 || a.surfaces == 0 {
        bail!("--seeds and --surfaces must be at least 1");
    }
    if a.radii.iter().any(|r| !(r.is_finite() && *r > 0.0)) {
        bail!("--radii must be positive numbers (use --concave for concave surfaces)");
    }
    if a.tilts
        .iter()
        .chain([&a.align_tilt])
        .any(|t| !(t.is_finite() && (0.0..60.0).contains(t)))
    {
        bail!("tilts must be in [0°, 60°)");
    }
    for (v, name) in [
        (a.zero_err_mm, "--zero-err-mm"),
        (a.dir_err_rad, "--dir-err-rad"),
        (a.radius_err, "--radius-err"),
        (a.axis_err_deg, "--axis-err-deg"),
    ] {
        if !v.is_finite() {
            bail!("{name} must be a number, got {v}");
        }
    }
    if a.radius_err <= -1.0 {
        bail!("--radius-err must be above -1");
    }
    Ok(())
}

/// Runs `perpend bench curvature`.
///
/// # Errors
/// Invalid arguments, simulation or calibration failures.
pub fn run(a: &Args) -> Result<()> {
    check(a)?;
    let rows = accuracy(a)?;
    let align = alignment(a)?;
    if a.json {
        let config = serde_json::json!({
            "head": "tian-style: cone 25°, 45 mm circle, standoff 60 mm",
            "zero_err_mm": a.zero_err_mm, "dir_err_rad": a.dir_err_rad,
            "seeds": a.seeds, "first_seed": a.first_seed, "surfaces": a.surfaces,
            "zeta_mm": sim_config().zeta_mm, "radius_err": a.radius_err,
            "axis_err_deg": a.axis_err_deg, "aligned_deg": ALIGNED_DEG, "max_moves": MAX_MOVES,
        });
        let v = serde_json::json!({ "config": config, "rows": rows, "alignment": align });
        println!(
            "{}",
            perpend_formats::schema::to_json(perpend_formats::schema::BENCH_CURVATURE, &v)?
        );
        return Ok(());
    }
    print_tables(a, &rows, &align);
    Ok(())
}

fn print_tables(a: &Args, rows: &[Row], align: &[AlignRow]) {
    println!(
        "curved skins (issue 14): Tian-style head (cone 25°, 45 mm, standoff 60 mm), errors ±{} mm / ±{} rad, LSQ-calibrated on a plane run",
        a.zero_err_mm, a.dir_err_rad
    );
    println!(
        "{} seeds × {} surfaces per row, ζ = {} mm; mean angle [°] to the normal where the spindle axis meets the surface",
        a.seeds,
        a.surfaces,
        sim_config().zeta_mm
    );
    println!();
    println!("shape      R [mm]  tilt [°]   plane [°]  curved [°]   floor [°]  curved/floor  curved max [°]");
    for r in rows {
        println!(
            "{:<9} {:>7.0}  {:>8.1}  {:>10.4}  {:>10.4}  {:>10.4}  {:>12.3}  {:>14.4}",
            format!("{:?}", r.shape).to_lowercase(),
            r.radius_mm,
            r.tilt_deg,
            r.plane_deg,
            r.curved_deg,
            r.floor_deg,
            r.ratio,
            r.curved_max_deg
        );
    }
    println!();
    println!(
        "alignment loop: from {}°, pitch/yaw about the measured axis point until θ < {ALIGNED_DEG}° (at most {MAX_MOVES} moves)",
        a.align_tilt
    );
    println!("shape      R [mm]  model    moves mean  moves max  not reached  final θ mean [°]");
    for r in align {
        println!(
            "{:<9} {:>7.0}  {:<7}  {:>10}  {:>9}  {:>6} / {:<4}  {:>16.4}",
            format!("{:?}", r.shape).to_lowercase(),
            r.radius_mm,
            r.model,
            r.moves_mean.map_or("–".into(), |m| format!("{m:.2}")),
            r.moves_max,
            r.not_reached,
            r.trials,
            r.final_deg
        );
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        a: Args,
    }

    fn args(extra: &[&str]) -> Args {
        let mut v = vec![
            "x",
            "--seeds",
            "2",
            "--surfaces",
            "15",
            "--align-trials",
            "4",
        ];
        v.extend_from_slice(extra);
        Cli::parse_from(v).a
    }

    #[test]
    fn curved_model_is_at_the_floor_and_the_plane_is_not() {
        let a = args(&["--radii", "300,2000", "--tilts", "0,10"]);
        let rows = accuracy(&a).unwrap();
        assert_eq!(rows.len(), 8);
        for r in &rows {
            assert!(r.ratio < 1.2, "{r:?}");
            assert!(r.floor_deg < 0.05, "{r:?}");
        }
        let worst = rows
            .iter()
            .find(|r| r.shape == Kind::Sphere && r.radius_mm == 300.0 && r.tilt_deg == 10.0)
            .unwrap();
        assert!(worst.plane_deg > 4.0 * worst.curved_deg, "{worst:?}");
    }

    #[test]
    fn concave_surfaces_and_the_alignment_loop() {
        let a = args(&["--radii", "500", "--tilts", "5", "--concave"]);
        let rows = accuracy(&a).unwrap();
        assert!(
            rows.iter().all(|r| r.radius_mm == -500.0 && r.ratio < 1.2),
            "{rows:?}"
        );
        let al = alignment(&a).unwrap();
        assert_eq!(al.len(), 4);
        for r in al.iter().filter(|r| r.model == "curved") {
            assert_eq!(r.not_reached, 0, "{r:?}");
            assert!(r.moves_mean.unwrap() <= 3.0, "{r:?}");
        }
    }

    #[test]
    fn bad_arguments_are_refused() {
        for bad in [
            &["--radii=-300"][..],
            &["--tilts", "70"][..],
            &["--radius-err", "-1"][..],
        ] {
            assert!(check(&args(bad)).is_err(), "{bad:?}");
        }
        assert!(check(&args(&[])).is_ok());
        let mut a = args(&[]);
        a.seeds = 0;
        assert!(check(&a).is_err());
    }
}
