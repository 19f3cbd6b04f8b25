//! `perpend record history`: the calibrations and interim checks of each
//! head against time, and their trend (issue 45).
//!
//! Reads every calibration record (`*.record.json`, a cell run's
//! `record.json`) and interim check record (`perpend cell check --out`)
//! under the directories given (by their `schema`, whatever their
//! names); a calibration's own `params.record.json` is left out where a
//! cell record of the same parameter file (same output SHA-256)
//! supersedes it. Groups them by head serial (one section
//! per head, `--serial` to pick one; records without a board are the
//! head "no board") and per head lists each entry's kind, outcome, the
//! error before the calibration and the verified p95 after it.
//!
//! Trend: the verified p95 (fresh poses and checks; cross-validated p95
//! only when a head has nothing else) against time by weighted least
//! squares ([`fit_line`]), 1σ of each p95 taken as 2.11·sd/√n of its
//! per-pose errors (the normal-theory standard error of a 95th
//! percentile), scaled by the Birge ratio when the scatter exceeds it. The
//! slope's unit fits the span (per minute, hour, day or week). A slope is
//! a trend when |slope| > [`TREND_SIGMAS`]·σ; only then "recalibrate by
//! DATE" (where the trend reaches the tolerance). Only the geometry
//! (x, y, z, m, n, q) of calibrations is trended, not the extension
//! coefficients.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};
use perpend_calib::interim::CheckRecord;
use perpend_calib::record::{Record, KIND_CROSS_VALIDATED, KIND_EXPECTED_ONLY};

use crate::record_fmt::{epoch_s, esc, geometry, iso, opt_deg};

/// Tolerance of the trend's date when neither `--tolerance-deg` nor any
/// record names one [deg].
pub const DEFAULT_TOLERANCE_DEG: f64 = 0.05;

/// A slope is a trend when it exceeds this many of its 1σ.
pub const TREND_SIGMAS: f64 = 2.0;

/// A weighted least-squares line `y = a + b·t`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Line {
    /// Intercept at `t = 0`.
    pub a: f64,
    /// Slope per unit of `t`.
    pub b: f64,
    /// 1σ of the slope (scaled by the Birge ratio when the scatter exceeds
    /// the weights; by the scatter alone without weights).
    pub sigma_b: f64,
    /// Points fitted.
    pub n: usize,
}

impl Line {
    /// Whether the slope is resolved: |b| > [`TREND_SIGMAS`]·σ_b.
    pub fn resolved(&self) -> bool {
        self.b.abs() > TREND_SIGMAS * self.sigma_b
    }
}

/// Fits `y = a + b·t` by weighted least squares, weights `1/σ²` (`None`:
/// equal weights, σ from the scatter). `None` below three points, with a
/// single time, or with a σ that is not positive and finite.
pub fn fit_line(t: &[f64], y: &[f64], sig: Option<&[f64]>) -> Option<Line> {
    let n = t.len();
    if n < 3 || y.len() != n || sig.is_some_and(|s| s.len() != n) {
        return None;
    }
    let w: Vec<f64> = match sig {
        Some(s) if s.iter().all(|x| x.is_finite() && *x > 0.0) => {
            s.iter().map(|x| 1.0 / (x * x)).collect()
        }
        Some(_) => return None,
        None => vec![1.0; n],
    };
    let (sw, st, sy): (f64, f64, f64) = (0..n).fold((0.0, 0.0, 0.0), |(a, b, c), i| {
        (a + w[i], b + w[i] * t[i], c + w[i] * y[i])
    });
    let (tm, ym) = (st / sw, sy / sw);
    let stt: f64 = (0..n).map(|i| w[i] * (t[i] - tm).powi(2)).sum();
    if !(stt > 0.0) {
        return None;
    }
    let b = (0..n)
        .map(|i| w[i] * (t[i] - tm) * (y[i] - ym))
        .sum::<f64>()
        / stt;
    let a = ym - b * tm;
    let chi2: f64 = (0..n).map(|i| w[i] * (y[i] - a - b * t[i]).powi(2)).sum();
    let nu = (n - 2) as f64;
    let scale = if sig.is_some() {
        (chi2 / nu).max(1.0)
    } else {
        chi2 / nu
    };
    Some(Line {
        a,
        b,
        sigma_b: (scale / stt).sqrt(),
        n,
    })
}

/// Every record under `roots` (recursively: every `.json` file whose
/// `schema` is a calibration or check record's; a file named is taken as
/// is).
///
/// # Errors
/// A directory that cannot be read.
pub fn find_records(roots: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    let mut stack: Vec<PathBuf> = roots.to_vec();
    while let Some(p) = stack.pop() {
        if p.is_dir() {
            let rd =
                std::fs::read_dir(&p).with_context(|| format!("cannot read {}", p.display()))?;
            for e in rd {
                stack.push(
                    e.with_context(|| format!("cannot read {}", p.display()))?
                        .path(),
                );
            }
        } else if roots.contains(&p) || is_record_name(&p) {
            out.push(p);
        }
    }
    out.sort();
    Ok(out)
}

/// A JSON file whose `schema` (its first field, as the tool writes it) is
/// a calibration or check record's, whatever its name.
fn is_record_name(p: &Path) -> bool {
    if p.extension().is_none_or(|e| e != "json") {
        return false;
    }
    let mut head = [0u8; 96];
    let n = std::fs::File::open(p)
        .and_then(|mut f| std::io::Read::read(&mut f, &mut head))
        .unwrap_or(0);
    let text = String::from_utf8_lossy(&head[..n]);
    text.contains("\"perpend.record/") || text.contains("\"perpend.check/")
}

/// A record of either kind, as read.
#[derive(Debug, Clone)]
pub enum Item {
    /// A calibration record.
    Calibration(Box<Record>),
    /// An interim check record.
    Check(Box<CheckRecord>),
}

impl Item {
    /// Reads a file of either kind (by its `schema`).
    ///
    /// # Errors
    /// Unreadable, malformed, another schema.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let name = path.display().to_string();
        if text.contains("\"perpend.check/") {
            return Ok(Item::Check(Box::new(CheckRecord::parse(&text, &name)?)));
        }
        Ok(Item::Calibration(Box::new(Record::parse(&text, &name)?)))
    }

    /// The head serial, normalised (`None`: no board).
    pub fn serial(&self) -> Option<String> {
        match self {
            Item::Calibration(r) => r.head_serial.as_deref().map(norm_serial),
            Item::Check(c) => Some(norm_serial(&c.head_serial)),
        }
    }

    fn utc(&self) -> &str {
        match self {
            Item::Calibration(r) => &r.utc,
            Item::Check(c) => &c.utc,
        }
    }
}

/// A serial as compared: lower case, `0x` prefix where it is hex.
pub fn norm_serial(s: &str) -> String {
    let t = s.trim().to_lowercase();
    let hex = t.strip_prefix("0x").unwrap_or(&t);
    if !hex.is_empty() && hex.chars().all(|c| c.is_ascii_hexdigit()) {
        format!("0x{hex:0>8}")
    } else {
        t
    }
}

/// One record in a history.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Entry {
    /// The file.
    pub file: String,
    /// `calibration` (files only), `cell calibration` or `check`.
    pub kind: String,
    /// Its outcome (calibrations) or verdict (checks).
    pub outcome: String,
    /// Its `utc`.
    pub utc: String,
    /// Time since the first record, in the history's unit.
    pub t: f64,
    /// Mean normal error before the calibration [deg] (cell calibrations).
    pub before_deg: Option<f64>,
    /// Verified p95 [deg] (`null`: not verified).
    pub p95_deg: Option<f64>,
    /// Its 1σ [deg] (2.11·sd/√n of the per-pose errors).
    pub p95_sigma_deg: Option<f64>,
    /// Whether the p95 is of fresh poses (cell run, check) rather than
    /// cross-validated.
    pub fresh: bool,
    /// The board's store count after the push (applied cell
    /// calibrations: the stamp's sub 3).
    pub store_count: Option<u32>,
    /// The tolerance this record was decided against [deg] (`null`: none
    /// was decided).
    pub tolerance_deg: Option<f64>,
}

/// A parameter's trend.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ParamTrend {
    /// Sensor (1-based).
    pub sensor: usize,
    /// Parameter name.
    pub parameter: String,
    /// Values against `Entry::t` (t, value).
    pub values: Vec<(f64, f64)>,
    /// The line (slope per `History::unit`), when fitted.
    pub line: Option<Line>,
}

/// The history of one head.
#[derive(Debug, Clone, serde::Serialize)]
pub struct History {
    /// Head serial (`null`: records without a board).
    pub serial: Option<String>,
    /// Tolerance of the trend's date [deg].
    pub tolerance_deg: f64,
    /// Where it comes from: `--tolerance-deg`, the latest record's own,
    /// or the default.
    pub tolerance_source: String,
    /// The time unit of `t` and of every slope: `minute`, `hour`, `day`
    /// or `week`.
    pub unit: String,
    /// The records, oldest first.
    pub entries: Vec<Entry>,
    /// Per sensor and parameter (calibrations).
    pub parameters: Vec<ParamTrend>,
    /// Verified p95 trend (slope per `unit`).
    pub verification: Option<Line>,
    /// "recalibrate by DATE", "recalibrate now: …" or "no trend …".
    pub verdict: String,
    /// The date the trend reaches the tolerance, when resolved and rising.
    pub recalibrate_by: Option<String>,
    /// What makes the history itself doubtful: a store count that does
    /// not rise (two boards with one serial, or a board whose storage was
    /// erased), said before any trend.
    pub warnings: Vec<String>,
}

/// 1σ of a p95 from per-pose errors (normal theory:
/// `sqrt(p(1−p))/φ(z_p) ≈ 2.11` standard deviations over √n).
fn p95_sigma(e: &[f64]) -> Option<f64> {
    let n = e.len() as f64;
    if e.len() < 2 {
        return None;
    }
    let m = e.iter().sum::<f64>() / n;
    let sd = (e.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    Some(2.11 * sd / n.sqrt())
}

/// The time unit for a span of `span_s` seconds: (name, seconds).
pub fn unit_for(span_s: f64) -> (&'static str, f64) {
    const UNITS: [(&str, f64); 4] = [
        ("week", 604_800.0),
        ("day", 86_400.0),
        ("hour", 3_600.0),
        ("minute", 60.0),
    ];
    let big = |k: usize| if k == 0 { 20.0 } else { 2.0 };
    UNITS
        .iter()
        .enumerate()
        .find(|(k, (_, s))| span_s >= big(*k) * s)
        .map_or(UNITS[3], |(_, u)| *u)
}

/// The entry of one item at time `t` (in the history's unit).
fn entry(file: &Path, item: &Item, t: f64) -> Entry {
    let (kind, outcome, before, errors, fresh) = match item {
        Item::Calibration(r) => {
            let v = &r.verification;
            let errors: Vec<f64> = if v.is_verified() && on_board_or_file(r) {
                v.poses.iter().map(|p| p.error_deg).collect()
            } else {
                Vec::new()
            };
            let kind = match v.kind.as_str() {
                KIND_CROSS_VALIDATED | KIND_EXPECTED_ONLY => "calibration",
                _ => "cell calibration",
            };
            let fresh = kind != "calibration";
            (
                kind,
                r.outcome_words().to_string(),
                v.before_mean_deg,
                errors,
                fresh,
            )
        }
        Item::Check(c) => {
            let errors: Vec<f64> = c.decision.poses.iter().map(|p| p.error_deg).collect();
            // A check of a board whose stamp is not the record's compared
            // another calibration than the one it names: said with it.
            let other = c
                .against
                .as_ref()
                .is_some_and(|a| a.stamp.is_some() && a.stamp != c.board_stamp);
            let verdict = match other {
                true => format!("{} (board stamp is not the record's)", c.verdict),
                false => c.verdict.clone(),
            };
            ("check", verdict, None, errors, true)
        }
    };
    let store_count = match item {
        Item::Calibration(r) => r.stamp.as_ref().map(|s| s.store_count),
        Item::Check(_) => None,
    };
    let tolerance_deg = match item {
        Item::Calibration(r) => r.decision.as_ref().map(|d| d.tolerance_deg),
        Item::Check(c) => Some(c.decision.tolerance_deg),
    };
    Entry {
        store_count,
        tolerance_deg,
        file: file.display().to_string(),
        kind: kind.into(),
        outcome,
        utc: item.utc().to_string(),
        t,
        before_deg: before,
        p95_deg: perpend_calib::record::p95(&errors),
        p95_sigma_deg: p95_sigma(&errors),
        fresh,
    }
}

/// Whether `r`'s parameters are a head's calibration in force: applied to
/// its board, or computed from files (no board involved). A reverted or
/// failed run's parameters never were.
fn on_board_or_file(r: &Record) -> bool {
    use perpend_calib::record::{OUTCOME_APPLIED, OUTCOME_COMPUTED};
    matches!(
        r.outcome.as_deref(),
        None | Some(OUTCOME_APPLIED | OUTCOME_COMPUTED)
    )
}

/// Reads `files`, leaving out a file whose bytes another one already
/// holds (a copy counts once) and calibration records a cell record of the
/// same parameter file supersedes.
fn read_items(files: &[PathBuf]) -> Result<Vec<(PathBuf, Item)>> {
    let mut seen = std::collections::HashSet::new();
    let mut items = Vec::new();
    for f in files {
        let bytes = std::fs::read(f).with_context(|| format!("{}: cannot read", f.display()))?;
        if seen.insert(perpend_calib::record::sha256_hex(&bytes)) {
            items.push((f.clone(), Item::read(f)?));
        }
    }
    let cell_outputs: Vec<String> = items
        .iter()
        .filter_map(|(_, i)| match i {
            Item::Calibration(r) if r.head_serial.is_some() => {
                r.output.as_ref().map(|o| o.sha256.clone())
            }
            _ => None,
        })
        .collect();
    Ok(items
        .into_iter()
        .filter(|(_, i)| match i {
            Item::Calibration(r) if r.head_serial.is_none() => r
                .output
                .as_ref()
                .is_none_or(|o| !cell_outputs.contains(&o.sha256)),
            _ => true,
        })
        .collect())
}

/// The histories of the records `files`, one per head (or of `serial`).
///
/// # Errors
/// A malformed record (naming it), no record, none of `serial`.
pub fn history(files: &[PathBuf], serial: Option<&str>, tol: Option<f64>) -> Result<Vec<History>> {
    if files.is_empty() {
        bail!("no calibration or check record found (*.record.json, record.json, check.json)");
    }
    let items = read_items(files)?;
    let mut heads: Vec<Option<String>> = items.iter().map(|(_, i)| i.serial()).collect();
    heads.sort();
    heads.dedup();
    if let Some(s) = serial {
        let want = Some(norm_serial(s));
        if !heads.contains(&want) {
            bail!(
                "no record of head {s} (the records are of {})",
                heads
                    .iter()
                    .map(|h| h.clone().unwrap_or_else(|| "no board".into()))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        heads = vec![want];
    }
    heads
        .into_iter()
        .map(|h| {
            let mine: Vec<&(PathBuf, Item)> =
                items.iter().filter(|(_, i)| i.serial() == h).collect();
            one_history(&mine, h, tol)
        })
        .collect()
}

fn one_history(
    items: &[&(PathBuf, Item)],
    serial: Option<String>,
    tol: Option<f64>,
) -> Result<History> {
    let mut timed = Vec::with_capacity(items.len());
    for (f, i) in items {
        timed.push((
            epoch_s(i.utc()).with_context(|| f.display().to_string())?,
            f,
            i,
        ));
    }
    timed.sort_by(|a, b| a.0.total_cmp(&b.0));
    let t0 = timed.first().map_or(0.0, |x| x.0);
    let span = timed.last().map_or(0.0, |x| x.0) - t0;
    let (unit, unit_s) = unit_for(span);
    let entries: Vec<Entry> = timed
        .iter()
        .map(|(t, f, i)| entry(f, i, (t - t0) / unit_s))
        .collect();
    let cals: Vec<(f64, &Record)> = timed
        .iter()
        .filter_map(|(t, _, i)| match i {
            Item::Calibration(r) if on_board_or_file(r) => Some(((t - t0) / unit_s, r.as_ref())),
            _ => None,
        })
        .collect();
    let verification = verification_line(&entries);
    let (tol, tolerance_source) = trend_tolerance(tol, &entries);
    let (verdict, recalibrate_by) = recalibrate(verification, t0, unit, unit_s, &entries, tol);
    Ok(History {
        warnings: store_warnings(&entries),
        serial,
        tolerance_deg: tol,
        tolerance_source,
        unit: unit.into(),
        parameters: param_trends(&cals),
        entries,
        verification,
        verdict,
        recalibrate_by,
    })
}

/// Every store count (0x2011 sub 3) that does not rise over the one
/// before it in time: each push stores once more on the same board, so a
/// count that stands or falls means another board answers to the same
/// serial, or this one's storage was erased (the history then mixes
/// what is not one head's life).
fn store_warnings(entries: &[Entry]) -> Vec<String> {
    let counted: Vec<&Entry> = entries.iter().filter(|e| e.store_count.is_some()).collect();
    counted
        .windows(2)
        .filter_map(|w| {
            let (a, b) = (w[0].store_count?, w[1].store_count?);
            (b <= a).then(|| {
                format!(
                    "store count {b} at {} after {a} at {} ({}, then {}): not one board's \
                     life; two boards with this serial, or its storage erased; check the \
                     boards before reading a trend",
                    w[1].utc, w[0].utc, w[0].file, w[1].file
                )
            })
        })
        .collect()
}

/// The p95 line over fresh entries (cross-validated ones only when there
/// is no fresh one).
fn verification_line(entries: &[Entry]) -> Option<Line> {
    let fresh = entries.iter().any(|e| e.fresh && e.p95_deg.is_some());
    let v: Vec<&Entry> = entries
        .iter()
        .filter(|e| e.p95_deg.is_some() && e.fresh == fresh)
        .collect();
    let t: Vec<f64> = v.iter().map(|e| e.t).collect();
    let y: Vec<f64> = v.iter().filter_map(|e| e.p95_deg).collect();
    let s: Option<Vec<f64>> = v.iter().map(|e| e.p95_sigma_deg).collect();
    fit_line(&t, &y, s.as_deref()).or_else(|| fit_line(&t, &y, None))
}

/// The verdict of the verification trend against `tol`.
fn recalibrate(
    line: Option<Line>,
    t0: f64,
    unit: &str,
    unit_s: f64,
    entries: &[Entry],
    tol: f64,
) -> (String, Option<String>) {
    let Some(l) = line else {
        return ("no trend (fewer than three verified records)".into(), None);
    };
    if !l.resolved() {
        return (
            format!(
                "no trend (slope {:+.2e} ± {:.2e} deg/{unit}, within {TREND_SIGMAS}σ)",
                l.b, l.sigma_b
            ),
            None,
        );
    }
    if l.b <= 0.0 {
        return (
            format!(
                "no trend towards the tolerance (the error falls, {:+.2e} deg/{unit})",
                l.b
            ),
            None,
        );
    }
    let t = (tol - l.a) / l.b;
    let date = iso(t0 + t * unit_s);
    let last = entries.last().map_or(0.0, |e| e.t);
    if t <= last {
        (
            format!("recalibrate now: the trend reached the tolerance on {date}"),
            Some(date),
        )
    } else {
        (format!("recalibrate by {date}"), Some(date))
    }
}

fn param_trends(sorted: &[(f64, &Record)]) -> Vec<ParamTrend> {
    let mut out: Vec<ParamTrend> = Vec::new();
    let mut sig: Vec<Vec<Option<f64>>> = Vec::new();
    for (t, r) in sorted {
        for p in &r.parameters {
            for (name, v, sd, _) in geometry(p) {
                let k = match out
                    .iter()
                    .position(|x| x.sensor == p.sensor && x.parameter == name)
                {
                    Some(k) => k,
                    None => {
                        out.push(ParamTrend {
                            sensor: p.sensor,
                            parameter: name.into(),
                            values: Vec::new(),
                            line: None,
                        });
                        sig.push(Vec::new());
                        out.len() - 1
                    }
                };
                out[k].values.push((*t, v));
                sig[k].push(sd);
            }
        }
    }
    for (p, s) in out.iter_mut().zip(&sig) {
        let (t, y): (Vec<f64>, Vec<f64>) = p.values.iter().copied().unzip();
        let s: Option<Vec<f64>> = s.iter().copied().collect();
        p.line = fit_line(&t, &y, s.as_deref()).or_else(|| fit_line(&t, &y, None));
    }
    out
}

/// The tolerance of the trend's date and where it comes from: the one
/// given, else the latest record's own, else [`DEFAULT_TOLERANCE_DEG`].
fn trend_tolerance(given: Option<f64>, entries: &[Entry]) -> (f64, String) {
    if let Some(t) = given {
        return (t, "--tolerance-deg".into());
    }
    match entries
        .iter()
        .rev()
        .find_map(|e| Some((e.tolerance_deg?, e)))
    {
        Some((t, e)) => (t, format!("the latest record's own ({})", e.file)),
        None => (
            DEFAULT_TOLERANCE_DEG,
            "the default: no record decided one".into(),
        ),
    }
}

/// The histories in words, one section per head.
pub fn history_text(hs: &[History]) -> String {
    let mut o = String::new();
    for h in hs {
        let _ = writeln!(
            o,
            "history of head {} ({} records), tolerance {} deg on the verified p95 ({})",
            h.serial.as_deref().unwrap_or("no board"),
            h.entries.len(),
            h.tolerance_deg,
            h.tolerance_source
        );
        for w in &h.warnings {
            let _ = writeln!(o, "  WARNING: {w}");
        }
        for e in &h.entries {
            let _ = writeln!(
                o,
                "  {}  {:<16} {:<28} before {:>8}  p95 {:>8} deg  tolerance {:>6}  {}",
                e.utc,
                e.kind,
                e.outcome,
                opt_deg(e.before_deg),
                opt_deg(e.p95_deg),
                e.tolerance_deg.map_or("-".into(), |t| t.to_string()),
                e.file
            );
        }
        for p in &h.parameters {
            let t = p.line.map_or("too few records".into(), |l| {
                format!(
                    "{:+.3e} ± {:.1e} per {}{}",
                    l.b,
                    l.sigma_b,
                    h.unit,
                    if l.resolved() { " (trend)" } else { "" }
                )
            });
            let _ = writeln!(o, "  sensor {} {:<7} {t}", p.sensor, p.parameter);
        }
        if let Some(l) = h.verification {
            let _ = writeln!(
                o,
                "verified p95: {:+.3e} ± {:.1e} deg per {}",
                l.b, l.sigma_b, h.unit
            );
        }
        let _ = writeln!(o, "{}\n", h.verdict);
    }
    o
}

/// One panel: the verified p95 (calibrations: dots, checks: squares)
/// against time, the tolerance, the trend line, every mark inside.
fn panel(h: &History, top: f64) -> String {
    let (w, ht, m) = (640.0, 300.0, 56.0);
    let pts: Vec<(f64, f64, bool)> = h
        .entries
        .iter()
        .filter_map(|e| Some((e.t, e.p95_deg?, e.kind == "check")))
        .collect();
    let tmax = pts.iter().map(|p| p.0).fold(1.0, f64::max);
    // The trend line only where the text names a trend.
    let line = h
        .verification
        .filter(|l| l.resolved())
        .map(|l| (l.a, l.a + l.b * tmax));
    let ends = line.map_or(0.0, |(a, b)| a.max(b));
    let lows = line.map_or(0.0, |(a, b)| a.min(b));
    let ymax = pts
        .iter()
        .map(|p| p.1)
        .fold(h.tolerance_deg.max(ends), f64::max)
        * 1.15;
    let ymin = lows.min(0.0);
    let x = |t: f64| m + (w - 2.0 * m) * t / tmax;
    let y = |v: f64| top + ht - m - (ht - 2.0 * m) * (v - ymin) / (ymax - ymin);
    let mut s = format!(
        "<line x1=\"{m}\" y1=\"{b:.1}\" x2=\"{r}\" y2=\"{b:.1}\" stroke=\"black\"/>\
         <line x1=\"{m}\" y1=\"{t:.1}\" x2=\"{m}\" y2=\"{b:.1}\" stroke=\"black\"/>\
         <line x1=\"{m}\" y1=\"{ty:.1}\" x2=\"{r}\" y2=\"{ty:.1}\" stroke=\"#b00\" stroke-dasharray=\"6 3\"/>",
        b = y(ymin),
        t = top + m,
        r = w - m,
        ty = y(h.tolerance_deg)
    );
    s.push_str(&ticks(&x, &y, (tmax, ymin, ymax), &h.unit));
    if let Some(w) = h.warnings.first() {
        let _ = write!(
            s,
            "<text x=\"{m}\" y=\"{:.1}\" font-size=\"10\" fill=\"#b00\">WARNING: {}</text>",
            top + ht - 8.0,
            esc(w.split(':').next().unwrap_or(w))
        );
    }
    for (t, v, check) in &pts {
        let _ = match check {
            true => write!(
                s,
                "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"6\" height=\"6\" fill=\"#a60\"/>",
                x(*t) - 3.0,
                y(*v) - 3.0
            ),
            false => write!(
                s,
                "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3\" fill=\"#48a\"/>",
                x(*t),
                y(*v)
            ),
        };
    }
    if let Some((a, b)) = line {
        let _ = write!(
            s,
            "<line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" stroke=\"#333\"/>",
            x(0.0),
            y(a),
            x(tmax),
            y(b)
        );
    }
    let _ = write!(
        s,
        "<text x=\"{m}\" y=\"{:.1}\" font-size=\"12\">head {}: verified p95 [deg] since {}</text>\
         <text x=\"{m}\" y=\"{:.1}\" font-size=\"11\">dots: calibrations, squares: checks, \
         dashed: tolerance {} deg</text><text x=\"{m}\" y=\"{:.1}\" font-size=\"11\">{}</text>",
        top + 16.0,
        esc(h.serial.as_deref().unwrap_or("no board")),
        esc(h.entries.first().map_or("", |e| e.utc.as_str())),
        top + 30.0,
        esc(&h.tolerance_deg.to_string()),
        top + 44.0,
        esc(&h.verdict)
    );
    s
}

/// A round step (1, 2 or 5 × 10^k) that cuts `span` into at most five.
fn nice_step(span: f64) -> f64 {
    let raw = (span / 5.0).max(1e-12);
    let p = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * p)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * p)
}

/// The round values from `lo` to `hi` (at most six).
fn tick_values(lo: f64, hi: f64) -> Vec<f64> {
    let step = nice_step(hi - lo);
    let first = (lo / step).ceil() as i64;
    (first..)
        .map(|k| k as f64 * step)
        .take_while(|v| *v <= hi + step * 1e-9)
        .take(6)
        .collect()
}

/// Labelled ticks at round values on each axis: time since the first
/// record in `unit`s (0 to `tmax`), the p95 in degrees (`ymin` to
/// `ymax`).
fn ticks(
    x: &dyn Fn(f64) -> f64,
    y: &dyn Fn(f64) -> f64,
    (tmax, ymin, ymax): (f64, f64, f64),
    unit: &str,
) -> String {
    let mut s = String::new();
    let yb = y(ymin);
    for t in tick_values(0.0, tmax) {
        let xt = x(t);
        let _ = write!(
            s,
            "<line x1=\"{xt:.1}\" y1=\"{yb:.1}\" x2=\"{xt:.1}\" y2=\"{:.1}\" stroke=\"black\"/>\
             <text x=\"{xt:.1}\" y=\"{:.1}\" font-size=\"10\" text-anchor=\"middle\">{}</text>",
            yb + 4.0,
            yb + 15.0,
            tick_label(t)
        );
    }
    let x0 = x(0.0);
    for v in tick_values(ymin, ymax) {
        let yv = y(v);
        let _ = write!(
            s,
            "<line x1=\"{:.1}\" y1=\"{yv:.1}\" x2=\"{x0:.1}\" y2=\"{yv:.1}\" stroke=\"black\"/>\
             <text x=\"{:.1}\" y=\"{:.1}\" font-size=\"10\" text-anchor=\"end\">{}</text>",
            x0 - 4.0,
            x0 - 6.0,
            yv + 3.5,
            tick_label(v)
        );
    }
    let _ = write!(
        s,
        "<text x=\"{:.1}\" y=\"{:.1}\" font-size=\"10\" text-anchor=\"end\">{}s</text>",
        x(tmax),
        yb + 28.0,
        esc(unit)
    );
    s
}

/// A tick's label: a round value without trailing zeros.
fn tick_label(v: f64) -> String {
    let t = format!("{v:.6}");
    t.trim_end_matches('0').trim_end_matches('.').to_string()
}

/// The histories as one SVG, a panel per head.
pub fn history_svg(hs: &[History]) -> String {
    let (w, ht) = (640.0, 300.0);
    let total = ht * hs.len().max(1) as f64;
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{total}\" \
         viewBox=\"0 0 {w} {total}\"><rect x=\"0\" y=\"0\" width=\"{w}\" height=\"{total}\" fill=\"white\"/>"
    );
    for (k, h) in hs.iter().enumerate() {
        s.push_str(&panel(h, k as f64 * ht));
    }
    s.push_str("</svg>\n");
    s
}
