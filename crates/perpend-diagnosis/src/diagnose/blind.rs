//! `perpend bench diagnose`: the diagnosis scored on runs that perpend did
//! not write.
//!
//! The runs come from the independent generator `host-tests/blind/gen.py`
//! (Python standard library, no code shared with perpend: its own head
//! geometries, plane sampling, tracker, noise and effect shapes, which are
//! not the candidates' terms) and are graded by `host-tests/blind/score.py`
//! against the hidden truth that only the generator knows. This command
//! runs that scorer with **this very binary** as the tool under test: each
//! run is diagnosed by `perpend diagnose --json` from its two exchange
//! files alone, exactly as a user would, and only then compared with the
//! truth. Neither the generator nor the grader is in this crate, so neither
//! can share an assumption with the candidates by construction.
//!
//! The grid (score.py's docstring, docs/diagnosis.md): reading noise 0.002
//! to 0.05 mm, declared σ right, ×0.5, ×2 or missing, per-pose sample
//! columns, tracker ×1 or ×3, pose spread ±2° to ±15°, 30, 60 or 120 poses,
//! two head geometries; per regime effect-free runs, every single effect,
//! pairs, tracker blunders and an out-of-catalogue ripple; a detection-limit
//! block over the effect's visible size. Per cell: false-positive rate,
//! singles named, pairs both named, blunders found, extended held-out RMS
//! over the same-draw floor (and over the least cost of estimating the
//! named model's coefficients, which the goal reads). `--combined` and
//! `--offcat` run the blocks off the grid (two factors at once; other
//! noise, spatter, other shapes).
//!
//! Limits: needs Python ≥ 3.9 and the `host-tests/blind` folder of the
//! source tree (`--blind DIR` where the binary runs elsewhere); the full
//! grid takes about an hour on two cores, the reduced grid (the default,
//! what CI runs) about ten minutes. Seeds from 1000 (the default) were
//! used for tuning; report figures from another `--seed-base`.
//! `perpend bench diagnose-self` is the older self-consistency check on
//! perpend's own simulator ([`super::bench`]).

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{anyhow, bail, Result};

/// Where the independent generator lives in the source tree this binary
/// was built from.
const SOURCE_BLIND: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../host-tests/blind");

/// Arguments of `perpend bench diagnose`.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// The whole grid with the detection-limit block (about an hour on two
    /// cores); without it the reduced grid CI runs, with its pooled goals.
    #[arg(long)]
    pub full: bool,
    /// Two factors at once (tracker ×3 with 30 poses, ±2°, σ 0.03 mm, …)
    /// instead of the grid.
    #[arg(long, conflicts_with = "offcat")]
    pub combined: bool,
    /// Off both catalogues: t3 and heteroscedastic noise, missing readings,
    /// spatter, a knee linearity, a second-order thermal lag, a quadratic
    /// carry-over.
    #[arg(long)]
    pub offcat: bool,
    /// First seed (default: the tuning range, 1000; report with another).
    #[arg(long)]
    pub seed_base: Option<u64>,
    /// Effect-free runs per regime.
    #[arg(long)]
    pub nulls: Option<u32>,
    /// Runs per effect class and regime.
    #[arg(long)]
    pub effects: Option<u32>,
    /// Comma-separated truths to run (e.g. `none`, `gain+thermal_lag`).
    #[arg(long)]
    pub only: Option<String>,
    /// Comma-separated regimes to run (e.g. `base,30 poses`).
    #[arg(long)]
    pub regime: Option<String>,
    /// Exit with an error when a goal is missed (per regime with `--full`,
    /// pooled on the reduced grid).
    #[arg(long)]
    pub check: bool,
    /// Print the grid as one JSON object (regime → class → counts and
    /// rates) instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Also write the table as Markdown here.
    #[arg(long)]
    pub md: Option<PathBuf>,
    /// Also write the detection-limit curve (full grid) as SVG here.
    #[arg(long)]
    pub svg: Option<PathBuf>,
    /// Also write one JSON line per run (case, truth, answer, grade) here.
    #[arg(long)]
    pub runs: Option<PathBuf>,
    /// Worker processes (default: one per core).
    #[arg(long)]
    pub jobs: Option<u32>,
    /// The folder of `gen.py` and `score.py` (default: the source tree's
    /// `host-tests/blind`).
    #[arg(long)]
    pub blind: Option<PathBuf>,
    /// The Python interpreter (default: `$PYTHON`, else `python3`).
    #[arg(long)]
    pub python: Option<String>,
}

/// The scorer's command line for `a`, the tool under test being `perpend`.
fn score_args(a: &Args, perpend: &Path) -> Vec<String> {
    let mut v = vec!["--perpend".to_string(), perpend.display().to_string()];
    if !a.full {
        v.push("--quick".into());
    }
    for (flag, on) in [
        ("--combined", a.combined),
        ("--offcat", a.offcat),
        ("--check", a.check),
    ] {
        if on {
            v.push(flag.into());
        }
    }
    let num = [
        ("--seed-base", a.seed_base),
        ("--nulls", a.nulls.map(u64::from)),
        ("--effects", a.effects.map(u64::from)),
        ("--jobs", a.jobs.map(|j| u64::from(j.max(1)))),
    ];
    for (flag, x) in num {
        if let Some(x) = x {
            v.extend([flag.to_string(), x.to_string()]);
        }
    }
    let text = [
        ("--only", a.only.as_deref()),
        ("--regime", a.regime.as_deref()),
    ];
    for (flag, x) in text {
        if let Some(x) = x {
            v.extend([flag.to_string(), x.to_string()]);
        }
    }
    let files = [("--md", &a.md), ("--svg", &a.svg), ("--runs", &a.runs)];
    for (flag, p) in files {
        if let Some(p) = p {
            v.extend([flag.to_string(), p.display().to_string()]);
        }
    }
    if a.json {
        // score.py then prints the JSON alone on standard output and its
        // table on standard error.
        v.extend(["--json".to_string(), "-".to_string()]);
    }
    v
}

/// The scorer, checked to be there.
///
/// # Errors
/// No `score.py` and `gen.py` in the folder.
fn scorer(a: &Args) -> Result<PathBuf> {
    let dir = a
        .blind
        .clone()
        .unwrap_or_else(|| PathBuf::from(SOURCE_BLIND));
    let score = dir.join("score.py");
    if !(score.is_file() && dir.join("gen.py").is_file()) {
        bail!(
            "the independent generator is not in {}: pass --blind DIR, the folder host-tests/blind of perpend's source tree (gen.py and score.py)",
            dir.display()
        );
    }
    Ok(score)
}

/// Runs `perpend bench diagnose`.
///
/// # Errors
/// No generator, no Python, a goal missed with `--check`, a scorer that
/// fails.
pub fn run(a: &Args) -> Result<()> {
    // (`--full` keeps its detection-limit block whatever the counts.)
    let limit_block = a.full && !(a.combined || a.offcat);
    if a.nulls == Some(0) && a.effects == Some(0) && !limit_block {
        bail!("--nulls 0 and --effects 0 leave nothing to run");
    }
    let score = scorer(a)?;
    let me = std::env::current_exe().map_err(|e| anyhow!("cannot find this binary: {e}"))?;
    let python = a
        .python
        .clone()
        .or_else(|| std::env::var("PYTHON").ok())
        .unwrap_or_else(|| "python3".into());
    let status = Command::new(&python)
        .arg(&score)
        .args(score_args(a, &me))
        .status()
        .map_err(|e| {
            anyhow!(
                "cannot run {python} (Python ≥ 3.9, standard library only; --python or $PYTHON): {e}"
            )
        })?;
    match status.code() {
        Some(0) => Ok(()),
        // score.py exits 1 on a missed goal, as Python does on an error.
        Some(1) if a.check => bail!(
            "the blind diagnosis missed a goal, or the scorer failed: its lines above say which"
        ),
        _ => bail!("{python} {} failed: {status}", score.display()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        a: Args,
    }

    fn args(line: &[&str]) -> Args {
        let mut v = vec!["bench"];
        v.extend_from_slice(line);
        Cli::try_parse_from(v)
            .map(|c| c.a)
            .unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn options_reach_the_scorer_as_it_names_them() {
        let a = args(&[
            "--full",
            "--seed-base",
            "500000",
            "--nulls",
            "100",
            "--regime",
            "30 poses,base",
            "--json",
            "--check",
        ]);
        let v = score_args(&a, Path::new("/x/perpend"));
        let joined = v.join("|");
        assert!(joined.starts_with("--perpend|/x/perpend|--check|"));
        assert!(!v.contains(&"--quick".to_string()));
        assert!(joined.contains("--seed-base|500000"));
        assert!(joined.contains("--nulls|100"));
        assert!(joined.contains("--regime|30 poses,base"));
        assert!(joined.ends_with("--json|-"));
        let q = score_args(&args(&[]), Path::new("p"));
        assert_eq!(q, ["--perpend", "p", "--quick"]);
    }

    #[test]
    fn a_missing_generator_is_named() {
        let e = run(&args(&["--blind", "/nonexistent/blind"])).expect_err("no generator");
        assert!(e.to_string().contains("/nonexistent/blind"), "{e}");
        assert!(run(&args(&["--nulls", "0", "--effects", "0"])).is_err());
    }

    #[test]
    fn the_source_tree_holds_the_generator() {
        assert!(scorer(&args(&[])).is_ok());
    }
}
