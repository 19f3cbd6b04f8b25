//! `perpend bench frames`: what the cell's frame errors do to a calibrated
//! head with and without reversal about the spindle axis, against the
//! same-draw floor, and how many turned poses the separation needs.
//!
//! Every row is [`Scenario::issue`] (90 poses, ±10°, 35 ± 5 mm, 4 µm
//! noise, a random head) over `--seeds` seeds; "with reversal" cycles the
//! last joint through 0/90/180/270°, "without" keeps it at 0°. The normal
//! error is the mean over 40 test planes of the angle between the normal
//! the calibrated head reports and the true one (in the true TCS).

use std::fmt::Write as _;

use anyhow::Result;
use serde::Serialize;

use super::{frames_deg, run_scenario, Frames, Outcome, Scenario};

/// Arguments of `perpend bench frames`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Seeds per row.
    #[arg(long, default_value_t = 10)]
    pub seeds: u64,
    /// First seed.
    #[arg(long, default_value_t = 1)]
    pub first_seed: u64,
    /// Print one JSON object (schema `perpend.bench-frames/1`).
    #[arg(long)]
    pub json: bool,
}

/// Mean figures of one case over the seeds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Side {
    /// Mean normal error [deg] of the calibrated head.
    pub normal_deg: f64,
    /// Its ratio to the mean floor.
    pub over_floor: f64,
    /// Mean estimated tracker tilt about x [deg] (estimated whatever its
    /// precision; 0 where not identifiable).
    pub tracker_x_deg: f64,
    /// Mean 1σ of that estimate [µrad] (`None` when never identifiable).
    pub tracker_sigma_urad: Option<f64>,
    /// Seeds in which the tracker tilt was resolved (1σ ≤ [`super::RESOLVE_RAD`]).
    pub resolved: usize,
    /// Seeds in which it was significant (beyond 2σ).
    pub significant: usize,
    /// Mean residual RMS [µm].
    pub rms_um: f64,
}

/// One case: the frame errors and both calibrations.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Row {
    /// True tracker tilt about the datum's x [deg].
    pub tracker_tilt_deg: f64,
    /// True TCP tilt about x [deg].
    pub tcp_tilt_deg: f64,
    /// True TCP offset along x [mm].
    pub tcp_offset_mm: f64,
    /// Mean floor [deg]: head alone, same draw, no frame error.
    pub floor_deg: f64,
    /// With reversal (joint estimate).
    pub reversal: Side,
    /// Without reversal (joint estimate; the head is corrected only for a
    /// significant tilt).
    pub no_reversal: Side,
}

/// How many of the 90 poses must be turned.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Needed {
    /// Turned poses (the rest at 0°).
    pub turned: usize,
    /// Seeds in which the tracker tilt was resolved.
    pub resolved: usize,
    /// Seeds in which it was significant.
    pub significant: usize,
    /// Mean normal error over the mean floor.
    pub over_floor: f64,
    /// Mean |estimate − truth| of the tilt [deg].
    pub tilt_error_deg: f64,
}

/// The report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// `perpend.bench-frames/1`.
    pub schema: &'static str,
    /// Seeds per case.
    pub seeds: u64,
    /// Calibration poses per seed.
    pub poses: usize,
    /// Reading noise [µm].
    pub noise_um: f64,
    /// The frame-error cases.
    pub rows: Vec<Row>,
    /// Tracker tilt of the turned-pose sweep [deg].
    pub sweep_tilt_deg: f64,
    /// The sweep over the number of turned poses.
    pub sweep: Vec<Needed>,
    /// Fewest turned poses with the tilt resolved in every seed and the
    /// normal error within 1.2× the floor.
    pub turned_needed: Option<usize>,
}

/// The cases: tracker tilts 0-0.1°, TCP tilts and offsets, and all at once.
const CASES: [[f64; 3]; 8] = [
    [0.0, 0.0, 0.0],
    [0.025, 0.0, 0.0],
    [0.05, 0.0, 0.0],
    [0.1, 0.0, 0.0],
    [0.0, 0.05, 0.0],
    [0.0, 0.1, 0.0],
    [0.0, 0.0, 0.5],
    [0.05, 0.1, 0.5],
];

/// Turned-pose counts of the sweep.
const TURNED: [usize; 9] = [0, 2, 4, 8, 12, 16, 24, 45, 90];

fn seeds(a: &Args, sc: &Scenario) -> Result<Vec<Outcome>> {
    (a.first_seed..a.first_seed + a.seeds)
        .map(|s| run_scenario(sc, s))
        .collect()
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    s / n.max(1) as f64
}

fn side(out: &[Outcome], floor: f64) -> Side {
    let resolved = out.iter().filter(|o| o.joint.resolved[0]).count();
    let significant = out.iter().filter(|o| o.joint.significant[0]).count();
    let normal = mean(out.iter().map(|o| o.joint_deg));
    let sig: Vec<f64> = out.iter().filter_map(|o| o.joint.sigma[0]).collect();
    Side {
        normal_deg: normal,
        over_floor: normal / floor,
        tracker_x_deg: mean(out.iter().map(|o| o.joint.frames[0].to_degrees())),
        tracker_sigma_urad: (!sig.is_empty()).then(|| 1e6 * mean(sig.into_iter())),
        resolved,
        significant,
        rms_um: 1e3 * mean(out.iter().map(|o| o.joint.rms_mm)),
    }
}

fn row(a: &Args, case: [f64; 3]) -> Result<Row> {
    let f: Frames = frames_deg([case[0], 0.0], [case[1], 0.0], [case[2], 0.0]);
    let with = seeds(a, &Scenario::issue(f))?;
    let without = seeds(
        a,
        &Scenario {
            angles: 1,
            ..Scenario::issue(f)
        },
    )?;
    let floor = mean(with.iter().map(|o| o.floor_deg));
    Ok(Row {
        tracker_tilt_deg: case[0],
        tcp_tilt_deg: case[1],
        tcp_offset_mm: case[2],
        floor_deg: floor,
        reversal: side(&with, floor),
        no_reversal: side(&without, floor),
    })
}

fn sweep(a: &Args, tilt_deg: f64) -> Result<Vec<Needed>> {
    let f = frames_deg([tilt_deg, 0.0], [0.0; 2], [0.0; 2]);
    TURNED
        .iter()
        .map(|&turned| {
            let out = seeds(
                a,
                &Scenario {
                    turned,
                    ..Scenario::issue(f)
                },
            )?;
            let floor = mean(out.iter().map(|o| o.floor_deg));
            Ok(Needed {
                turned,
                resolved: out.iter().filter(|o| o.joint.resolved[0]).count(),
                significant: out.iter().filter(|o| o.joint.significant[0]).count(),
                over_floor: mean(out.iter().map(|o| o.joint_deg)) / floor,
                tilt_error_deg: mean(
                    out.iter()
                        .map(|o| (o.joint.frames[0].to_degrees() - tilt_deg).abs()),
                ),
            })
        })
        .collect()
}

/// Runs the benchmark.
///
/// # Errors
/// Those of [`run_scenario`].
pub fn bench(a: &Args) -> Result<Report> {
    let rows = CASES
        .iter()
        .map(|&c| row(a, c))
        .collect::<Result<Vec<_>>>()?;
    let sweep_tilt_deg = 0.05;
    let sweep = sweep(a, sweep_tilt_deg)?;
    let turned_needed = sweep
        .iter()
        .find(|n| n.resolved as u64 == a.seeds && n.over_floor <= 1.2)
        .map(|n| n.turned);
    let sc = Scenario::issue(Frames::zeros());
    Ok(Report {
        schema: "perpend.bench-frames/1",
        seeds: a.seeds,
        poses: sc.poses,
        noise_um: 1e3 * sc.sigma_mm,
        rows,
        sweep_tilt_deg,
        sweep,
        turned_needed,
    })
}

fn sigma_text(s: &Side, seeds: u64) -> String {
    match s.tracker_sigma_urad {
        Some(u) => format!(
            "{:.4}° ± {u:.0} µrad, r{}/s{}",
            s.tracker_x_deg, s.resolved, s.significant
        ),
        None => format!("not identifiable in {seeds}"),
    }
}

/// The report as text.
pub fn text(r: &Report) -> String {
    let mut t = String::new();
    let _ = writeln!(
        t,
        "frame errors: {} poses, {} µm noise, {} seeds; normal error [deg] of the calibrated head against the true planes",
        r.poses, r.noise_um, r.seeds
    );
    let _ = writeln!(
        t,
        "tracker°  TCP°   TCP mm   floor     reversal (×floor, tracker est ± 1σ, resolved/significant of {})      no reversal (×floor, same)",
        r.seeds
    );
    for w in &r.rows {
        let _ = writeln!(
            t,
            "{:7.3} {:6.3} {:7.2}  {:.5}  {:.5} ({:5.2}×, {:<32}) {:.5} ({:5.2}×, {})",
            w.tracker_tilt_deg,
            w.tcp_tilt_deg,
            w.tcp_offset_mm,
            w.floor_deg,
            w.reversal.normal_deg,
            w.reversal.over_floor,
            sigma_text(&w.reversal, r.seeds),
            w.no_reversal.normal_deg,
            w.no_reversal.over_floor,
            sigma_text(&w.no_reversal, r.seeds),
        );
    }
    let _ = writeln!(
        t,
        "turned poses of {} (tracker tilt {}°):",
        r.poses, r.sweep_tilt_deg
    );
    for n in &r.sweep {
        let _ = writeln!(
            t,
            "  {:3} turned: resolved {}/{}, significant {}/{}, {:.2}× floor, |tilt error| {:.4}°",
            n.turned, n.resolved, r.seeds, n.significant, r.seeds, n.over_floor, n.tilt_error_deg
        );
    }
    let _ = match r.turned_needed {
        Some(n) => writeln!(t, "needed: {n} turned poses"),
        None => writeln!(t, "needed: not reached with 90 turned poses"),
    };
    t
}

/// Runs `perpend bench frames`.
///
/// # Errors
/// Those of [`bench`].
pub fn run(a: &Args) -> Result<()> {
    let r = bench(a)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        print!("{}", text(&r));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bench_separates_the_tracker_tilt_only_with_reversal() {
        let a = Args {
            seeds: 2,
            first_seed: 7,
            json: true,
        };
        let w = row(&a, [0.05, 0.0, 0.0]).unwrap();
        assert!(w.reversal.over_floor <= 1.2, "{w:?}");
        assert_eq!(w.reversal.resolved, 2);
        assert_eq!(w.no_reversal.resolved, 0);
        assert!(w.no_reversal.over_floor > 10.0, "{w:?}");
        let j = serde_json::to_string(&Report {
            schema: "perpend.bench-frames/1",
            seeds: 2,
            poses: 90,
            noise_um: 4.0,
            rows: vec![w],
            sweep_tilt_deg: 0.05,
            sweep: vec![],
            turned_needed: None,
        })
        .unwrap();
        assert!(
            j.starts_with("{\"schema\":\"perpend.bench-frames/1\""),
            "{j}"
        );
    }
}
