//! `perpend bench diagnose-self`: how well the diagnosis names effects
//! injected by perpend's own simulator (a self-consistency check).
//!
//! For every hidden effect of [`Hidden::ALL`] (clean data, the six
//! catalogue effects and the out-of-catalogue ripple), every magnitude and
//! every seed, a run is simulated ([`super::scenario`]), written in the
//! exchange format, read back through the file readers and diagnosed with
//! the default settings, exactly as `perpend diagnose` would. The effect
//! size is measured, not assumed: the **noise floor** of a run is the base
//! model's held-out RMS on its clean twin (same head, planes and noise, no
//! effect), and the **raise** is the base model's held-out RMS on the run
//! over that floor, minus one.
//!
//! Reported: the confusion matrix of named vs hidden effect (all runs and
//! runs with raise ≥ 50%), the false-positive rate on clean data, the
//! detection rate per effect against the raise, the extended model's
//! held-out RMS over the floor, and the acceptance criteria.
//!
//! **Not the benchmark of record.** The runs come from perpend's own
//! simulator and effects injected through the same extension terms the
//! candidates fit, so this bench checks the pipeline's consistency with
//! itself (and its speed), not that it recognises effects it was not built
//! around. The figures of the README and `docs/diagnosis.md` come from the
//! independent generator `host-tests/blind/gen.py` (Python standard
//! library, no shared code, other functional forms), which `perpend bench
//! diagnose` runs ([`super::blind`]):
//! `perpend bench diagnose --full --seed-base 500000 --nulls 100`.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use anyhow::{anyhow, bail, Result};
use serde::Serialize;

use super::scenario::{generate, write, Hidden, Scenario};
use super::{diagnose, Settings};
use perpend_calib::candidates::{Effect, Refs};
use perpend_calib::cv::{cross_validate, Folds};
use perpend_calib::stats;
use perpend_formats::exchange::{read_poses, read_sensors};

/// Arguments of `perpend bench diagnose-self`.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Seeds per (effect, magnitude).
    #[arg(long, default_value_t = 20)]
    pub seeds: u64,
    /// First seed.
    #[arg(long, default_value_t = 1)]
    pub first_seed: u64,
    /// Magnitudes: RMS of the part of the effect the paper's model cannot
    /// absorb, in units of the reading noise σ (see `diagnose::scenario`).
    #[arg(long, value_delimiter = ',', default_values_t = [0.25, 0.5, 1.0, 1.5, 2.0, 3.0])]
    pub magnitudes: Vec<f64>,
    /// Poses per run.
    #[arg(long, default_value_t = 100)]
    pub poses: usize,
    /// Monte-Carlo draws of each diagnosis' expectation.
    #[arg(long, default_value_t = 8)]
    pub draws: usize,
    /// Worker threads.
    #[arg(long, default_value_t = 2)]
    pub jobs: usize,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
    /// Also write every run as one JSON line to this file.
    #[arg(long)]
    pub records: Option<std::path::PathBuf>,
}

/// One diagnosed run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Record {
    /// Hidden effect.
    pub hidden: String,
    /// Magnitude [σ].
    pub magnitude: f64,
    /// Seed.
    pub seed: u64,
    /// Reading noise [mm].
    pub sigma_mm: f64,
    /// What the diagnosis named.
    pub named: String,
    /// Base held-out RMS on the clean twin [mm].
    pub floor_mm: f64,
    /// Base held-out RMS [mm].
    pub base_mm: f64,
    /// Extended held-out RMS [mm].
    pub ext_mm: f64,
    /// The diagnosis' simulated expectation [mm].
    pub expected_mm: f64,
    /// `base / floor − 1`.
    pub raise: f64,
    /// Mean held-out normal error, base / extended [deg].
    pub normal_deg: (f64, f64),
}

/// Diagnoses one scenario through the files.
///
/// # Errors
/// Simulation, I/O or diagnosis failures.
pub fn run_one(sc: &Scenario, settings: &Settings, tag: &str) -> Result<Record> {
    let g = generate(sc)?;
    let dir = std::env::temp_dir().join(format!(
        "perpend-bench-diagnose-{}-{tag}",
        std::process::id()
    ));
    write(&g.data, &dir)?;
    let res = (|| {
        let table = read_sensors(&dir.join("sensors.csv"))?;
        let poses = read_poses(&dir.join("poses.csv"), Some(table.len()))?;
        diagnose(&table, &poses, settings)
    })();
    let _ = std::fs::remove_dir_all(&dir);
    let d = res?;
    let nominal = g
        .clean
        .sensors
        .sensors()
        .map_err(|e| anyhow!("nominal head: {e}"))?;
    let n = g.clean.poses.rows.len();
    let folds = Folds::new(n, super::folds_for(n, settings.folds), settings.seed);
    let floor = cross_validate(
        Effect::None,
        &nominal,
        &g.clean.poses,
        &Refs::of(&g.clean.poses),
        &folds,
        &settings.lsq,
    )
    .map_err(|e| anyhow!("clean twin: {e}"))?
    .rms;
    let j = d.json();
    Ok(Record {
        hidden: sc.hidden.name().into(),
        magnitude: sc.magnitude,
        seed: sc.seed,
        sigma_mm: sc.sigma_mm,
        named: j.effect,
        floor_mm: floor,
        base_mm: j.base.heldout_rms_mm,
        ext_mm: j.extended.heldout_rms_mm,
        expected_mm: j.expected_rms_mm,
        raise: j.base.heldout_rms_mm / floor - 1.0,
        normal_deg: (
            j.base.heldout_normal_err_deg.unwrap_or(f64::NAN),
            j.extended.heldout_normal_err_deg.unwrap_or(f64::NAN),
        ),
    })
}

/// The scenarios of a bench run: every effect at every magnitude for every
/// seed, and as many clean runs (each with its own seed, so that the
/// false-positive rate rests on as many runs as any effect). The reading
/// noise of a seed is log-uniform in 0.004-0.02 mm.
pub fn scenarios(a: &Args) -> Vec<Scenario> {
    let mut out = Vec::new();
    for s in a.first_seed..a.first_seed + a.seeds {
        let sigma = Scenario::draw(s, &[Hidden::None], a.poses).sigma_mm;
        for h in Hidden::ALL {
            for (j, &m) in a.magnitudes.iter().enumerate() {
                let (seed, sigma, m) = if h == Hidden::None {
                    let cs = s.wrapping_mul(1000).wrapping_add(j as u64);
                    (
                        cs,
                        Scenario::draw(cs, &[Hidden::None], a.poses).sigma_mm,
                        0.0,
                    )
                } else {
                    (s, sigma, m)
                };
                out.push(Scenario {
                    seed,
                    hidden: h,
                    magnitude: m,
                    poses: a.poses,
                    sigma_mm: sigma,
                    with_time: true,
                    with_temp: true,
                });
            }
        }
    }
    out
}

/// Runs every scenario on `jobs` threads; records in scenario order.
///
/// # Errors
/// The first failing scenario.
pub fn run_all(sc: &[Scenario], settings: &Settings, jobs: usize) -> Result<Vec<Record>> {
    let next = AtomicUsize::new(0);
    let out: Mutex<Vec<(usize, Result<Record>)>> = Mutex::new(Vec::with_capacity(sc.len()));
    let bar =
        perpend_formats::progress::Progress::new(sc.len() as u64, "bench diagnose-self: runs");
    std::thread::scope(|scope| {
        for _ in 0..jobs.max(1) {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(s) = sc.get(i) else { break };
                let r = run_one(s, settings, &i.to_string());
                bar.inc();
                if let Ok(mut v) = out.lock() {
                    v.push((i, r));
                }
            });
        }
    });
    let mut v = out
        .into_inner()
        .map_err(|_| anyhow!("a worker thread panicked"))?;
    v.sort_by_key(|(i, _)| *i);
    v.into_iter()
        .map(|(i, r)| {
            r.map_err(|e| {
                let s = &sc[i];
                anyhow!(
                    "{} magnitude {} seed {}: {e:#}",
                    s.hidden.name(),
                    s.magnitude,
                    s.seed
                )
            })
        })
        .collect()
}

/// Detection in one bin of effect size.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Bin {
    /// Lower edge of the raise (base held-out RMS over floor, minus 1).
    pub raise_lo: f64,
    /// Upper edge.
    pub raise_hi: f64,
    /// Runs in the bin.
    pub n: usize,
    /// Fraction named correctly.
    pub correct_rate: f64,
}

/// Extended held-out RMS over the floor for one effect.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ExtRatio {
    /// Runs (catalogue effect named correctly, raise ≥ 50%).
    pub n: usize,
    /// Mean of `ext / floor`.
    pub mean: f64,
    /// 95th percentile.
    pub p95: f64,
    /// Largest.
    pub max: f64,
}

/// One acceptance criterion of issue 5.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Criterion {
    /// Measured value.
    pub value: f64,
    /// Target.
    pub target: f64,
    /// Runs it is measured on.
    pub n: usize,
    /// Whether it is met.
    pub pass: bool,
}

/// The bench's summary.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// Runs diagnosed.
    pub runs: usize,
    /// Seeds per (effect, magnitude).
    pub seeds: u64,
    /// Magnitudes [σ].
    pub magnitudes: Vec<f64>,
    /// hidden → named → count, all runs.
    pub confusion: BTreeMap<String, BTreeMap<String, usize>>,
    /// Same for runs whose raise is ≥ 50% (clean runs included as is).
    pub confusion_raise_ge_50pct: BTreeMap<String, BTreeMap<String, usize>>,
    /// Fraction of clean runs named anything but `none`.
    pub false_positive_rate: f64,
    /// Fraction of ripple runs of any size called `unexplained` (small
    /// ripples are rightly called `none`; for information).
    pub ripple_unexplained_all_sizes: f64,
    /// Correct-naming rate per effect against the raise.
    pub detection: BTreeMap<String, Vec<Bin>>,
    /// Extended held-out RMS over the floor per catalogue effect.
    pub ext_over_floor: BTreeMap<String, ExtRatio>,
    /// The criteria.
    pub criteria: BTreeMap<String, Criterion>,
}

const EDGES: [f64; 8] = [0.0, 0.1, 0.25, 0.5, 1.0, 2.0, 4.0, f64::INFINITY];

impl Criterion {
    /// A rate that must reach `target`.
    fn at_least(value: f64, target: f64, n: usize) -> Self {
        Self {
            value,
            target,
            n,
            pass: value >= target,
        }
    }

    /// A ratio that must stay at or below `target`.
    fn at_most(value: f64, target: f64, n: usize) -> Self {
        Self {
            value,
            target,
            n,
            pass: value <= target,
        }
    }
}

/// Whether the run was named as its hidden effect should be.
fn correct(r: &Record) -> bool {
    Hidden::ALL
        .iter()
        .find(|h| h.name() == r.hidden)
        .is_some_and(|h| h.correct_verdict() == r.named)
}

/// The share of the runs selected by `f` for which `ok` holds, and their
/// number.
fn rate(
    recs: &[Record],
    f: &dyn Fn(&Record) -> bool,
    ok: &dyn Fn(&Record) -> bool,
) -> (f64, usize) {
    let sel: Vec<&Record> = recs.iter().filter(|r| f(r)).collect();
    (
        sel.iter().filter(|r| ok(r)).count() as f64 / sel.len().max(1) as f64,
        sel.len(),
    )
}

/// hidden → named → count, over all runs and over the runs whose raise is
/// ≥ 50 % (clean runs included as they are).
type Confusion = BTreeMap<String, BTreeMap<String, usize>>;

fn confusions(recs: &[Record]) -> (Confusion, Confusion) {
    let mut confusion = Confusion::new();
    let mut conf50 = Confusion::new();
    for r in recs {
        *confusion
            .entry(r.hidden.clone())
            .or_default()
            .entry(r.named.clone())
            .or_default() += 1;
        if r.hidden == "none" || r.raise >= 0.5 {
            *conf50
                .entry(r.hidden.clone())
                .or_default()
                .entry(r.named.clone())
                .or_default() += 1;
        }
    }
    (confusion, conf50)
}

/// The detection rate of hidden effect `h` per raise bin.
fn detection_bins(recs: &[Record], h: Hidden) -> Vec<Bin> {
    EDGES
        .windows(2)
        .map(|w| {
            let inb: Vec<&Record> = recs
                .iter()
                .filter(|r| r.hidden == h.name() && r.raise >= w[0] && r.raise < w[1])
                .collect();
            Bin {
                raise_lo: w[0],
                raise_hi: w[1],
                n: inb.len(),
                correct_rate: inb.iter().filter(|r| correct(r)).count() as f64
                    / inb.len().max(1) as f64,
            }
        })
        .collect()
}

/// The extended model's held-out RMS over the floor for catalogue effect
/// `h`, on its runs named correctly with a raise ≥ 50 %.
fn ext_ratio(recs: &[Record], h: Hidden) -> ExtRatio {
    let v: Vec<f64> = recs
        .iter()
        .filter(|r| r.hidden == h.name() && r.raise >= 0.5 && correct(r))
        .map(|r| r.ext_mm / r.floor_mm)
        .collect();
    ExtRatio {
        n: v.len(),
        mean: stats::mean(&v),
        p95: stats::quantile(&v, 0.95),
        max: stats::quantile(&v, 1.0),
    }
}

/// The acceptance criteria over the records.
fn criteria(
    recs: &[Record],
    fp: (f64, usize),
    ext: &BTreeMap<String, ExtRatio>,
) -> BTreeMap<String, Criterion> {
    let is_cat = |r: &Record| {
        Hidden::ALL
            .iter()
            .any(|h| h.in_catalog() && h.name() == r.hidden)
    };
    let mut c = BTreeMap::new();
    let (v, n) = rate(recs, &|r| is_cat(r) && r.raise >= 0.5, &correct);
    c.insert(
        "catalog_named_correctly_raise_ge_50pct".to_string(),
        Criterion::at_least(v, 0.95, n),
    );
    for h in Hidden::ALL.iter().filter(|h| h.in_catalog()) {
        let (v, n) = rate(recs, &|r| r.hidden == h.name() && r.raise >= 0.5, &correct);
        c.insert(
            format!("{}_named_correctly_raise_ge_50pct", h.name()),
            Criterion::at_least(v, 0.95, n),
        );
    }
    c.insert(
        "clean_called_none".to_string(),
        Criterion::at_least(1.0 - fp.0, 0.95, fp.1),
    );
    let (v, n) = rate(recs, &|r| r.hidden == "ripple" && r.raise >= 0.5, &correct);
    c.insert(
        "ripple_called_unexplained_raise_ge_50pct".to_string(),
        Criterion::at_least(v, 0.90, n),
    );
    let n_ext = ext.values().map(|e| e.n).sum();
    let worst = ext.values().map(|e| e.mean).fold(0.0f64, f64::max);
    c.insert(
        "ext_rms_over_floor_worst_effect_mean".to_string(),
        Criterion::at_most(worst, 1.15, n_ext),
    );
    let worst_max = ext.values().map(|e| e.max).fold(0.0f64, f64::max);
    c.insert(
        "ext_rms_over_floor_worst_run".to_string(),
        Criterion::at_most(worst_max, 1.15, n_ext),
    );
    c
}

/// Summarises the records.
pub fn summarise(recs: &[Record], a: &Args) -> Summary {
    let (confusion, conf50) = confusions(recs);
    let clean: Vec<&Record> = recs.iter().filter(|r| r.hidden == "none").collect();
    let fp = clean.iter().filter(|r| r.named != "none").count() as f64 / clean.len().max(1) as f64;
    let effects = || Hidden::ALL.into_iter().filter(|h| *h != Hidden::None);
    let detection = effects()
        .map(|h| (h.name().to_string(), detection_bins(recs, h)))
        .collect();
    let ext_over_floor: BTreeMap<String, ExtRatio> = effects()
        .filter(|h| h.in_catalog())
        .map(|h| (h.name().to_string(), ext_ratio(recs, h)))
        .collect();
    Summary {
        runs: recs.len(),
        ripple_unexplained_all_sizes: rate(recs, &|r| r.hidden == "ripple", &correct).0,
        seeds: a.seeds,
        magnitudes: a.magnitudes.clone(),
        confusion,
        confusion_raise_ge_50pct: conf50,
        false_positive_rate: fp,
        detection,
        criteria: criteria(recs, (fp, clean.len()), &ext_over_floor),
        ext_over_floor,
    }
}

fn print_confusion(title: &str, c: &BTreeMap<String, BTreeMap<String, usize>>) {
    let cols = [
        "none",
        "gain",
        "nonlinearity",
        "incidence",
        "crosstalk",
        "thermal",
        "drift",
        "unexplained",
    ];
    println!("\n{title}");
    print!("  {:<13}", "hidden \\ named");
    for c in cols {
        print!(" {:>7}", &c[..c.len().min(7)]);
    }
    println!();
    for h in Hidden::ALL {
        let Some(row) = c.get(h.name()) else { continue };
        print!("  {:<13}", h.name());
        for col in cols {
            print!(" {:>7}", row.get(col).copied().unwrap_or(0));
        }
        println!();
    }
}

/// The text report's detection rates, extended-model ratios and criteria.
fn print_rates(s: &Summary) {
    println!("\ndetection rate (named correctly) against the raise");
    print!("  {:<13}", "effect");
    for w in EDGES.windows(2) {
        let hi = if w[1].is_finite() {
            format!("{:.0}%", w[1] * 100.0)
        } else {
            "∞".into()
        };
        print!(" {:>14}", format!("{:.0}-{}", w[0] * 100.0, hi));
    }
    println!();
    for (h, bins) in &s.detection {
        print!("  {h:<13}");
        for b in bins {
            if b.n == 0 {
                print!(" {:>14}", "–");
            } else {
                print!(
                    " {:>14}",
                    format!("{:.0}% ({})", b.correct_rate * 100.0, b.n)
                );
            }
        }
        println!();
    }
    println!("\nextended held-out RMS / floor (catalogue effects named correctly, raise ≥ 50%)");
    for (h, e) in &s.ext_over_floor {
        println!(
            "  {h:<13} n = {:>4}  mean {:.3}  p95 {:.3}  max {:.3}",
            e.n, e.mean, e.p95, e.max
        );
    }
    println!("\ncriteria (issue 5)");
    for (k, c) in &s.criteria {
        println!(
            "  {:<48} {:>7.3}  target {:<5}  n = {:<5} {}",
            k,
            c.value,
            c.target,
            c.n,
            if c.pass { "met" } else { "NOT MET" }
        );
    }
}

/// Runs `perpend bench diagnose-self`.
///
/// # Errors
/// Invalid arguments, simulation or diagnosis failures.
pub fn run(a: &Args) -> Result<()> {
    if a.seeds == 0 {
        bail!("--seeds must be at least 1");
    }
    if a.magnitudes.iter().any(|m| !(m.is_finite() && *m > 0.0)) {
        bail!("--magnitudes must be positive numbers");
    }
    let settings = Settings {
        draws: Some(a.draws.max(3)),
        // The bench grades verdicts; the limits of a `none` are not graded.
        limit_draws: 0,
        ..Settings::default()
    };
    let sc = scenarios(a);
    let recs = run_all(&sc, &settings, a.jobs)?;
    if let Some(p) = &a.records {
        let mut text = String::new();
        for r in &recs {
            text.push_str(&serde_json::to_string(r)?);
            text.push('\n');
        }
        std::fs::write(p, text).map_err(|e| anyhow!("cannot write {}: {e}", p.display()))?;
    }
    let s = summarise(&recs, a);
    if a.json {
        println!(
            "{}",
            perpend_formats::schema::to_json(perpend_formats::schema::BENCH_DIAGNOSE_SELF, &s)?
        );
        return Ok(());
    }
    println!(
        "diagnosis of hidden effects: {} runs ({} seeds × {} magnitudes × 7 effects, and as many clean runs), {} poses each, σ log-uniform 0.004-0.02 mm",
        s.runs,
        a.seeds,
        a.magnitudes.len(),
        a.poses
    );
    println!(
        "magnitude: RMS of the part of the effect the paper's model cannot absorb, in units of σ: {:?}",
        a.magnitudes
    );
    println!("effect size: raise = base held-out RMS / floor − 1 (floor: base held-out RMS of the clean twin)");
    println!("(perpend's own simulator: a self-consistency check; the benchmark of record is the independent generator, perpend bench diagnose --full)");
    print_confusion("confusion, all runs", &s.confusion);
    print_confusion(
        "confusion, runs with raise ≥ 50%",
        &s.confusion_raise_ge_50pct,
    );
    println!(
        "\nfalse-positive rate on clean data: {:.1}%",
        s.false_positive_rate * 100.0
    );
    println!(
        "ripple (out of catalogue) called unexplained at any size: {:.1}% (small ripples are rightly called none)",
        s.ripple_unexplained_all_sizes * 100.0
    );
    print_rates(&s);
    Ok(())
}
