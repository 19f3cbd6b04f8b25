//! `perpend record`: read calibration records (`perpend.record/1`,
//! [`perpend_lab::record`], docs/record.md) for people.
//!
//! - `record show FILE`: the record in words.
//! - `record cert FILE --out cert.html [--tolerance-deg 0.05]`: one
//!   self-contained XHTML page (no external resources, the plot inline
//!   SVG): head, date, inputs and hashes, parameters with 1σ, the
//!   verification table and per-pose error bars against the tolerance, the
//!   poses left out and why, and PASS/FAIL. PASS means the 95th percentile
//!   of the verified per-pose normal errors is within the tolerance; a
//!   record without verification ("expected only") FAILs as "not verified".
//!   Every string from the record is HTML-escaped.
//! - `record history DIR... [--serial S] [--tolerance-deg 0.05]
//!   [--plot FILE.svg] [--json]`: every `*.record.json` under the
//!   directories (recursively) of one head, each parameter and the
//!   verification error (p95) against date, and their trend: a weighted
//!   least-squares line ([`fit_line`]) with its 1σ slope. A slope counts as
//!   resolved when |slope| > [`TREND_SIGMAS`]·σ; then "recalibrate by DATE"
//!   is the date where the verification trend reaches the tolerance, else
//!   "no trend".
//!
//! Limits: the verification trend uses the records that carry verified
//! figures; the 1σ of a record's p95 is taken as 2.11·sd/√n of its
//! per-pose errors (the normal-theory standard error of a 95th
//! percentile), and every slope's σ is scaled up by the scatter about the
//! line when that exceeds the weights (Birge ratio), so a series noisier
//! than its 1σ is not called a trend. Only the geometry (x, y, z, m, n, q)
//! is trended, not the extension coefficients.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, UNIX_EPOCH};

use anyhow::{anyhow, bail, Context as _, Result};
use perpend_lab::record::Record;

/// Default tolerance on the normal error [deg].
pub const TOLERANCE_DEG: f64 = 0.05;
/// A slope is a trend when it exceeds this many of its 1σ.
pub const TREND_SIGMAS: f64 = 2.0;

/// Arguments of `perpend record`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// What to do with the records.
    #[command(subcommand)]
    pub cmd: Sub,
}

/// The `record` subcommands.
#[derive(clap::Subcommand, Debug)]
pub enum Sub {
    /// Print a calibration record in words.
    Show {
        /// The record (`params.record.json`).
        file: PathBuf,
    },
    /// Write a calibration certificate (one self-contained HTML page).
    Cert(CertArgs),
    /// The history of one head: parameters and verification against date, trends.
    History(HistoryArgs),
}

/// Arguments of `perpend record cert`.
#[derive(clap::Args, Debug)]
pub struct CertArgs {
    /// The record (`params.record.json`).
    pub file: PathBuf,
    /// Write the certificate here (HTML).
    #[arg(long)]
    pub out: PathBuf,
    /// Tolerance on the normal error (95th percentile of the verification) [deg].
    #[arg(long, default_value_t = TOLERANCE_DEG)]
    pub tolerance_deg: f64,
}

/// Arguments of `perpend record history`.
#[derive(clap::Args, Debug)]
pub struct HistoryArgs {
    /// Directories searched recursively for `*.record.json` (or record files).
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    /// The head serial to follow when the records are of several heads.
    #[arg(long)]
    pub serial: Option<String>,
    /// Tolerance on the verification error (p95) [deg].
    #[arg(long, default_value_t = TOLERANCE_DEG)]
    pub tolerance_deg: f64,
    /// Write a plot of the verification error against date (SVG).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Print one JSON object instead of the report.
    #[arg(long)]
    pub json: bool,
}

/// Runs `perpend record`.
///
/// # Errors
/// Unreadable or malformed records, a mix of heads, I/O.
pub fn run(a: &Args) -> Result<()> {
    match &a.cmd {
        Sub::Show { file } => {
            print!("{}", show_text(&Record::read(file)?));
            Ok(())
        }
        Sub::Cert(c) => {
            check_tolerance(c.tolerance_deg)?;
            let r = Record::read(&c.file)?;
            let html = cert_html(&r, c.tolerance_deg);
            std::fs::write(&c.out, html)
                .with_context(|| format!("cannot write {}", c.out.display()))?;
            println!(
                "{}: {} (tolerance {} deg); certificate written to {}",
                c.file.display(),
                verdict(&r, c.tolerance_deg).0,
                c.tolerance_deg,
                c.out.display()
            );
            Ok(())
        }
        Sub::History(h) => run_history(h),
    }
}

fn check_tolerance(t: f64) -> Result<()> {
    if !(t.is_finite() && t > 0.0) {
        bail!("--tolerance-deg {t}: the tolerance must be a positive number of degrees");
    }
    Ok(())
}

/// An angle [deg] as every output prints it.
pub fn deg(x: f64) -> String {
    format!("{x:.4}")
}

/// A parameter value as printed (`mm` components to 4 decimals, direction
/// cosines to 6).
pub fn value(x: f64, is_dir: bool) -> String {
    if is_dir {
        format!("{x:.6}")
    } else {
        format!("{x:.4}")
    }
}

/// A 1σ as printed.
pub fn sigma(x: f64) -> String {
    format!("{x:.2e}")
}

fn opt_deg(x: Option<f64>) -> String {
    x.map_or_else(|| "-".into(), deg)
}

/// PASS/FAIL of a record against `tol` [deg], with the reason.
pub fn verdict(r: &Record, tol: f64) -> (&'static str, String) {
    let v = &r.verification;
    match v.p95_deg.filter(|_| v.is_verified()) {
        None => (
            "FAIL",
            "not verified: the record carries no verified normal errors".into(),
        ),
        Some(p) if p <= tol => (
            "PASS",
            format!("95th percentile {} deg ≤ tolerance {tol} deg", deg(p)),
        ),
        Some(p) => (
            "FAIL",
            format!("95th percentile {} deg > tolerance {tol} deg", deg(p)),
        ),
    }
}

/// The six geometry parameters of a sensor: (name, value, 1σ, direction?).
fn geometry(
    p: &perpend_lab::paramfile::SensorParams,
) -> Vec<(&'static str, f64, Option<f64>, bool)> {
    let s = p.sigma.as_ref();
    let names = ["x [mm]", "y [mm]", "z [mm]", "m", "n", "q"];
    (0..6)
        .map(|j| {
            let (v, sd) = if j < 3 {
                (p.zero_mm[j], s.map(|s| s.zero_mm[j]))
            } else {
                (p.dir[j - 3], s.map(|s| s.dir[j - 3]))
            };
            (names[j], v, sd, j >= 3)
        })
        .collect()
}

/// The record in words (`record show`).
pub fn show_text(r: &Record) -> String {
    let mut o = String::new();
    let or = |x: &Option<String>| x.clone().unwrap_or_else(|| "none".into());
    let _ = writeln!(o, "calibration record ({}) of {}", r.schema, r.utc);
    let _ = writeln!(
        o,
        "head {} (firmware {}), written by {}",
        or(&r.head_serial),
        or(&r.firmware),
        r.tool_version
    );
    let _ = writeln!(
        o,
        "method {}, model {}, {} poses used",
        r.method, r.model, r.poses_used
    );
    for f in &r.inputs {
        let _ = writeln!(o, "  input  {}  sha256 {}", f.path, f.sha256);
    }
    if let Some(f) = &r.output {
        let _ = writeln!(o, "  output {}  sha256 {}", f.path, f.sha256);
    }
    for p in &r.parameters {
        let id = p
            .identifiability
            .as_ref()
            .map_or("not assessed".to_string(), |i| i.status.clone());
        let _ = writeln!(o, "sensor {} ({id}):", p.sensor);
        for (name, v, sd, dir) in geometry(p) {
            let sd = sd.map_or("-".into(), sigma);
            let _ = writeln!(o, "  {name:<7} {:>12}  1σ {sd}", value(v, dir));
        }
    }
    show_dropped(r, &mut o);
    show_verification(r, &mut o);
    match &r.previous {
        None => {
            let _ = writeln!(o, "replaced: nothing");
        }
        Some(p) => {
            let _ = writeln!(
                o,
                "replaced: parameters sha256 {}, record {}",
                p.params_sha256,
                p.record_hash.as_deref().unwrap_or("none")
            );
        }
    }
    for e in &r.events {
        let _ = writeln!(o, "event: {e}");
    }
    o
}

fn show_dropped(r: &Record, o: &mut String) {
    if r.dropped_poses.is_empty() {
        let _ = writeln!(o, "left out: no pose");
    }
    for d in &r.dropped_poses {
        let _ = writeln!(
            o,
            "left out: pose {} ({:.3} mm RMS): {}",
            d.pose, d.residual_mm, d.reason
        );
    }
}

fn show_verification(r: &Record, o: &mut String) {
    let v = &r.verification;
    let _ = writeln!(o, "verification: {} ({})", v.kind, v.note);
    let _ = writeln!(
        o,
        "  normal error over {} poses: mean {} deg, p95 {} deg, max {} deg; expected {} deg RMS ({} deg at 95 %)",
        v.poses.len(),
        opt_deg(v.mean_deg),
        opt_deg(v.p95_deg),
        opt_deg(v.max_deg),
        opt_deg(v.expected_deg),
        opt_deg(v.expected_p95_deg)
    );
}

/// Escapes a string for HTML text and attribute values.
pub fn esc(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&#39;"),
            c => o.push(c),
        }
    }
    o
}

const STYLE: &str = "body{font-family:sans-serif;max-width:60em;margin:2em auto}\
table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #999;padding:2px 6px;\
text-align:right}th{background:#eee}.pass{color:#070}.fail{color:#b00}code{font-size:90%}";

/// The certificate page (`record cert`).
pub fn cert_html(r: &Record, tol: f64) -> String {
    let (word, why) = verdict(r, tol);
    let mut h = String::new();
    let head = esc(r.head_serial.as_deref().unwrap_or("no serial (no board)"));
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html xmlns=\"http://www.w3.org/1999/xhtml\"><head><meta charset=\"utf-8\"/>\
         <title>Calibration certificate {head}</title><style>{STYLE}</style></head><body>\
         <h1>Calibration certificate</h1><table>\
         <tr><th>head serial</th><td>{head}</td></tr>\
         <tr><th>firmware</th><td>{}</td></tr><tr><th>date (UTC)</th><td>{}</td></tr>\
         <tr><th>tool</th><td>{}</td></tr><tr><th>method, model</th><td>{}, {}</td></tr>\
         <tr><th>poses used</th><td>{}</td></tr></table>",
        esc(r.firmware.as_deref().unwrap_or("-")),
        esc(&r.utc),
        esc(&r.tool_version),
        esc(&r.method),
        esc(&r.model),
        r.poses_used
    );
    let class = if word == "PASS" { "pass" } else { "fail" };
    let _ = write!(
        h,
        "<h2 class=\"{class}\">{word}</h2><p>{} (tolerance {} deg on the 95th percentile of the \
         verified normal errors)</p>",
        esc(&why),
        esc(&tol.to_string())
    );
    cert_files(r, &mut h);
    cert_parameters(r, &mut h);
    cert_verification(r, tol, &mut h);
    cert_dropped(r, &mut h);
    h.push_str("</body></html>\n");
    h
}

fn cert_files(r: &Record, h: &mut String) {
    h.push_str("<h2>Files</h2><table><tr><th>role</th><th>path</th><th>SHA-256</th></tr>");
    let rows = r
        .inputs
        .iter()
        .map(|f| ("input", f))
        .chain(r.output.iter().map(|f| ("parameters", f)));
    for (role, f) in rows {
        let _ = write!(
            h,
            "<tr><td>{role}</td><td>{}</td><td><code>{}</code></td></tr>",
            esc(&f.path),
            esc(&f.sha256)
        );
    }
    h.push_str("</table>");
    if let Some(p) = &r.previous {
        let _ = write!(
            h,
            "<p>Replaces parameters <code>{}</code> (record {}).</p>",
            esc(&p.params_sha256),
            esc(p.record_hash.as_deref().unwrap_or("none"))
        );
    }
}

fn cert_parameters(r: &Record, h: &mut String) {
    h.push_str("<h2>Parameters</h2><table><tr><th>sensor</th><th>parameter</th><th>value</th><th>1σ</th><th>identifiability</th></tr>");
    for p in &r.parameters {
        let id = esc(p
            .identifiability
            .as_ref()
            .map_or("not assessed", |i| i.status.as_str()));
        for (name, v, sd, dir) in geometry(p) {
            let _ = write!(
                h,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{id}</td></tr>",
                p.sensor,
                esc(name),
                value(v, dir),
                sd.map_or("-".into(), sigma)
            );
        }
    }
    h.push_str("</table>");
}

fn cert_verification(r: &Record, tol: f64, h: &mut String) {
    let v = &r.verification;
    let _ = write!(
        h,
        "<h2>Verification</h2><p>{}: {}</p><table><tr><th>mean [deg]</th><th>p95 [deg]</th>\
         <th>max [deg]</th><th>expected RMS [deg]</th><th>expected 95 % [deg]</th></tr>\
         <tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr></table>",
        esc(&v.kind),
        esc(&v.note),
        opt_deg(v.mean_deg),
        opt_deg(v.p95_deg),
        opt_deg(v.max_deg),
        opt_deg(v.expected_deg),
        opt_deg(v.expected_p95_deg)
    );
    if v.poses.is_empty() {
        h.push_str("<p>Not verified: no per-pose errors.</p>");
        return;
    }
    h.push_str(&bars_svg(v, tol));
    h.push_str("<table><tr><th>pose</th><th>normal error [deg]</th><th>within tolerance</th></tr>");
    for p in &v.poses {
        let ok = if p.error_deg <= tol { "yes" } else { "no" };
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{ok}</td></tr>",
            p.pose,
            deg(p.error_deg)
        );
    }
    h.push_str("</table>");
}

/// Per-pose error bars against the tolerance line (inline SVG).
fn bars_svg(v: &perpend_lab::record::Verification, tol: f64) -> String {
    let (w, ht, m) = (640.0, 220.0, 40.0);
    let top = v.poses.iter().map(|p| p.error_deg).fold(tol, f64::max) * 1.1;
    let y = |e: f64| ht - m - (ht - 2.0 * m) * e / top;
    let bw = (w - 2.0 * m) / v.poses.len() as f64;
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{ht}\" \
         viewBox=\"0 0 {w} {ht}\"><rect x=\"0\" y=\"0\" width=\"{w}\" height=\"{ht}\" fill=\"white\"/>"
    );
    for (i, p) in v.poses.iter().enumerate() {
        let fill = if p.error_deg <= tol { "#48a" } else { "#c33" };
        let _ = write!(
            s,
            "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"{fill}\"/>",
            m + i as f64 * bw,
            y(p.error_deg),
            (bw * 0.8).max(0.5),
            (ht - m - y(p.error_deg)).max(0.0)
        );
    }
    let _ = write!(
        s,
        "<line x1=\"{m}\" y1=\"{ty:.1}\" x2=\"{x2}\" y2=\"{ty:.1}\" stroke=\"#b00\" stroke-dasharray=\"6 3\"/>\
         <text x=\"{m}\" y=\"{tl:.1}\" font-size=\"11\" fill=\"#b00\">tolerance</text>\
         <line x1=\"{m}\" y1=\"{b}\" x2=\"{x2}\" y2=\"{b}\" stroke=\"black\"/>\
         <text x=\"{m}\" y=\"{bl:.1}\" font-size=\"11\">normal error per verification pose [deg], 0 to {top}</text></svg>",
        ty = y(tol),
        x2 = w - m,
        b = ht - m,
        tl = y(tol) - 3.0,
        bl = ht - m + 16.0,
        top = deg(top)
    );
    s
}

fn cert_dropped(r: &Record, h: &mut String) {
    h.push_str("<h2>Left out</h2>");
    if r.dropped_poses.is_empty() {
        h.push_str("<p>No pose was left out.</p>");
        return;
    }
    h.push_str("<table><tr><th>pose</th><th>residual RMS [mm]</th><th>reason</th></tr>");
    for d in &r.dropped_poses {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{:.3}</td><td>{}</td></tr>",
            d.pose,
            d.residual_mm,
            esc(&d.reason)
        );
    }
    h.push_str("</table>");
}

// ---------------------------------------------------------------- history

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

/// Seconds since the epoch of an ISO 8601 time.
fn epoch_s(utc: &str) -> Result<f64> {
    let t = humantime::parse_rfc3339_weak(utc).map_err(|e| anyhow!("utc {utc:?}: {e}"))?;
    Ok(t.duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64()))
}

/// The ISO 8601 date-time at `s` seconds since the epoch.
fn iso(s: f64) -> String {
    let t = if s >= 0.0 && s.is_finite() {
        UNIX_EPOCH + Duration::from_secs_f64(s.min(1e11))
    } else {
        UNIX_EPOCH
    };
    humantime::format_rfc3339_seconds(t).to_string()
}

/// Every `*.record.json` under `roots` (recursively; a file is taken as is).
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
        } else if roots.contains(&p) || p.to_string_lossy().ends_with(".record.json") {
            out.push(p);
        }
    }
    out.sort();
    Ok(out)
}

/// One record in a history.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Entry {
    /// The file.
    pub file: String,
    /// Its `utc`.
    pub utc: String,
    /// Days since the first record.
    pub day: f64,
    /// Verification p95 [deg] (`null`: not verified).
    pub p95_deg: Option<f64>,
    /// Its 1σ [deg] (2.11·sd/√n of the per-pose errors).
    pub p95_sigma_deg: Option<f64>,
}

/// A parameter's trend.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ParamTrend {
    /// Sensor (1-based).
    pub sensor: usize,
    /// Parameter name.
    pub parameter: String,
    /// Values against `Entry::day` (day, value).
    pub values: Vec<(f64, f64)>,
    /// The line (slope per day), when fitted.
    pub line: Option<Line>,
}

/// The history of one head.
#[derive(Debug, Clone, serde::Serialize)]
pub struct History {
    /// Head serial (`null`: records without a board).
    pub serial: Option<String>,
    /// Tolerance [deg].
    pub tolerance_deg: f64,
    /// The records, oldest first.
    pub entries: Vec<Entry>,
    /// Per sensor and parameter.
    pub parameters: Vec<ParamTrend>,
    /// Verification p95 trend (slope per day).
    pub verification: Option<Line>,
    /// "recalibrate by DATE", "recalibrate now: …" or "no trend".
    pub verdict: String,
    /// The date the trend reaches the tolerance, when resolved and rising.
    pub recalibrate_by: Option<String>,
}

/// 1σ of a record's p95 from its per-pose errors (normal theory:
/// `sqrt(p(1−p))/φ(z_p) ≈ 2.11` standard deviations over √n).
fn p95_sigma(r: &Record) -> Option<f64> {
    let e: Vec<f64> = r.verification.poses.iter().map(|p| p.error_deg).collect();
    let n = e.len() as f64;
    if e.len() < 2 {
        return None;
    }
    let m = e.iter().sum::<f64>() / n;
    let sd = (e.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    Some(2.11 * sd / n.sqrt())
}

/// Picks the records of one head: `serial`, or the only one there is.
///
/// # Errors
/// Several heads and no `serial`, or none of `serial`.
fn one_head(recs: Vec<(PathBuf, Record)>, serial: Option<&str>) -> Result<Vec<(PathBuf, Record)>> {
    let mut serials: Vec<Option<String>> =
        recs.iter().map(|(_, r)| r.head_serial.clone()).collect();
    serials.sort();
    serials.dedup();
    let pick = match serial {
        Some(s) => Some(s.to_string()),
        None if serials.len() <= 1 => serials.into_iter().flatten().next(),
        None => bail!(
            "the records are of {} heads ({}): pick one with --serial S",
            serials.len(),
            serials
                .iter()
                .map(|s| s.clone().unwrap_or_else(|| "no serial".into()))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let out: Vec<_> = recs
        .into_iter()
        .filter(|(_, r)| r.head_serial == pick)
        .collect();
    if out.is_empty() {
        bail!(
            "no record of head {}",
            pick.unwrap_or_else(|| "without serial".into())
        );
    }
    Ok(out)
}

/// The history of the records `files` (one head, or `serial`).
///
/// # Errors
/// A malformed record (naming it), a mix of heads, no record.
pub fn history(files: &[PathBuf], serial: Option<&str>, tol: f64) -> Result<History> {
    if files.is_empty() {
        bail!("no *.record.json found");
    }
    let recs = files
        .iter()
        .map(|f| Ok((f.clone(), Record::read(f)?)))
        .collect::<Result<Vec<_>>>()?;
    let mut recs = one_head(recs, serial)?;
    let mut times = Vec::with_capacity(recs.len());
    for (f, r) in &recs {
        times.push(epoch_s(&r.utc).with_context(|| f.display().to_string())?);
    }
    let mut order: Vec<usize> = (0..recs.len()).collect();
    order.sort_by(|&i, &j| times[i].total_cmp(&times[j]));
    let t0 = order.first().map_or(0.0, |&i| times[i]);
    let mut sorted = Vec::with_capacity(recs.len());
    for &i in &order {
        sorted.push(((times[i] - t0) / 86400.0, recs[i].clone()));
    }
    recs.clear();
    let entries: Vec<Entry> = sorted
        .iter()
        .map(|(day, (f, r))| Entry {
            file: f.display().to_string(),
            utc: r.utc.clone(),
            day: *day,
            p95_deg: r
                .verification
                .p95_deg
                .filter(|_| r.verification.is_verified()),
            p95_sigma_deg: p95_sigma(r),
        })
        .collect();
    let verification = verification_line(&entries);
    let (verdict, recalibrate_by) = recalibrate(verification, t0, &entries, tol);
    Ok(History {
        serial: sorted.first().and_then(|(_, (_, r))| r.head_serial.clone()),
        tolerance_deg: tol,
        parameters: param_trends(&sorted),
        entries,
        verification,
        verdict,
        recalibrate_by,
    })
}

fn verification_line(entries: &[Entry]) -> Option<Line> {
    let v: Vec<&Entry> = entries.iter().filter(|e| e.p95_deg.is_some()).collect();
    let t: Vec<f64> = v.iter().map(|e| e.day).collect();
    let y: Vec<f64> = v.iter().filter_map(|e| e.p95_deg).collect();
    let s: Option<Vec<f64>> = v.iter().map(|e| e.p95_sigma_deg).collect();
    fit_line(&t, &y, s.as_deref()).or_else(|| fit_line(&t, &y, None))
}

/// The verdict of the verification trend against `tol`.
fn recalibrate(
    line: Option<Line>,
    t0: f64,
    entries: &[Entry],
    tol: f64,
) -> (String, Option<String>) {
    let Some(l) = line else {
        return ("no trend (fewer than three verified records)".into(), None);
    };
    if !l.resolved() {
        return (
            format!(
                "no trend (slope {:+.2e} ± {:.2e} deg/day, within {TREND_SIGMAS}σ)",
                l.b, l.sigma_b
            ),
            None,
        );
    }
    if l.b <= 0.0 {
        return (
            format!(
                "no trend towards the tolerance (the error falls, {:+.2e} deg/day)",
                l.b
            ),
            None,
        );
    }
    let day = (tol - l.a) / l.b;
    let date = iso(t0 + day * 86400.0);
    let last = entries.last().map_or(0.0, |e| e.day);
    if day <= last {
        (
            format!("recalibrate now: the trend reached the tolerance on {date}"),
            Some(date),
        )
    } else {
        (format!("recalibrate by {date}"), Some(date))
    }
}

fn param_trends(sorted: &[(f64, (PathBuf, Record))]) -> Vec<ParamTrend> {
    let mut out: Vec<ParamTrend> = Vec::new();
    let mut sig: Vec<Vec<Option<f64>>> = Vec::new();
    for (day, (_, r)) in sorted {
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
                out[k].values.push((*day, v));
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

/// The history in words.
pub fn history_text(h: &History) -> String {
    let mut o = String::new();
    let _ = writeln!(
        o,
        "history of head {} ({} records), tolerance {} deg on the verification p95",
        h.serial.as_deref().unwrap_or("without serial"),
        h.entries.len(),
        h.tolerance_deg
    );
    for e in &h.entries {
        let _ = writeln!(
            o,
            "  {}  day {:>7.1}  p95 {:>8} deg  {}",
            e.utc,
            e.day,
            opt_deg(e.p95_deg),
            e.file
        );
    }
    for p in &h.parameters {
        let t = p.line.map_or("too few records".into(), |l| {
            format!(
                "{:+.3e} ± {:.1e} per day{}",
                l.b,
                l.sigma_b,
                if l.resolved() { " (trend)" } else { "" }
            )
        });
        let _ = writeln!(o, "  sensor {} {:<7} {t}", p.sensor, p.parameter);
    }
    if let Some(l) = h.verification {
        let _ = writeln!(
            o,
            "verification p95: {:+.3e} ± {:.1e} deg per day",
            l.b, l.sigma_b
        );
    }
    let _ = writeln!(o, "{}", h.verdict);
    o
}

/// The verification p95 against date, with its trend and the tolerance (SVG).
pub fn history_svg(h: &History) -> String {
    let (w, ht, m) = (640.0, 300.0, 50.0);
    let pts: Vec<(f64, f64)> = h
        .entries
        .iter()
        .filter_map(|e| Some((e.day, e.p95_deg?)))
        .collect();
    let tmax = pts.iter().map(|p| p.0).fold(1.0, f64::max);
    let ymax = pts.iter().map(|p| p.1).fold(h.tolerance_deg, f64::max) * 1.15;
    let x = |t: f64| m + (w - 2.0 * m) * t / tmax;
    let y = |v: f64| ht - m - (ht - 2.0 * m) * v / ymax;
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{ht}\" viewBox=\"0 0 {w} {ht}\">\
         <rect x=\"0\" y=\"0\" width=\"{w}\" height=\"{ht}\" fill=\"white\"/>\
         <line x1=\"{m}\" y1=\"{b}\" x2=\"{r}\" y2=\"{b}\" stroke=\"black\"/>\
         <line x1=\"{m}\" y1=\"{m}\" x2=\"{m}\" y2=\"{b}\" stroke=\"black\"/>\
         <line x1=\"{m}\" y1=\"{ty:.1}\" x2=\"{r}\" y2=\"{ty:.1}\" stroke=\"#b00\" stroke-dasharray=\"6 3\"/>",
        b = ht - m,
        r = w - m,
        ty = y(h.tolerance_deg)
    );
    for (t, v) in &pts {
        let _ = write!(
            s,
            "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3\" fill=\"#48a\"/>",
            x(*t),
            y(*v)
        );
    }
    if let Some(l) = h.verification {
        let _ = write!(
            s,
            "<line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" stroke=\"#333\"/>",
            x(0.0),
            y(l.a),
            x(tmax),
            y(l.a + l.b * tmax)
        );
    }
    let _ = writeln!(
        s,
        "<text x=\"{m}\" y=\"20\" font-size=\"12\">verification p95 [deg] (0 to {}) against days since {}; dashed: tolerance; {}</text></svg>",
        deg(ymax),
        esc(h.entries.first().map_or("", |e| e.utc.as_str())),
        esc(&h.verdict)
    );
    s
}

fn run_history(a: &HistoryArgs) -> Result<()> {
    check_tolerance(a.tolerance_deg)?;
    let files = find_records(&a.dirs)?;
    let h = history(&files, a.serial.as_deref(), a.tolerance_deg)?;
    if let Some(p) = &a.plot {
        std::fs::write(p, history_svg(&h))
            .with_context(|| format!("cannot write {}", p.display()))?;
    }
    if a.json {
        let v = serde_json::to_value(&h)?;
        println!(
            "{}",
            crate::schema::tagged(crate::schema::RECORD_HISTORY, &v)
        );
    } else {
        print!("{}", history_text(&h));
        if let Some(p) = &a.plot {
            println!("plot written to {}", p.display());
        }
    }
    Ok(())
}

/// The record path beside a parameter file (re-exported for the cell run).
pub fn beside(params: &Path) -> PathBuf {
    perpend_lab::record::record_path(params)
}
