//! `perpend record`: read calibration and check records
//! (`perpend.record/2` and `/1`, `perpend.check/1`; [`perpend_calib::record`],
//! docs/record.md) for people.
//!
//! - `record show FILE`: the record in words, its outcome first, then the
//!   stamp, the decision with its uncertainty, the frame errors and the
//!   events.
//! - `record cert FILE --out cert.html`: the certificate
//!   ([`crate::record_cert`]); refused for a record whose calibration is not
//!   applied and verified (the outcome says why).
//! - `record report FILE --out report.html`: the same figures for any
//!   record, marked as no certificate.
//! - `record find STAMP [DIR...]`: the records that lead from a board's
//!   stamp (`node info`, 0x2011 sub 1) to its calibration: the stamped
//!   record (its SHA-256 begins with the stamp) and the cell record that
//!   names it.
//! - `record history DIR... [--serial S] [--tolerance-deg T] [--plot
//!   FILE.svg] [--json]`: per head, calibrations and checks against time
//!   ([`crate::record_history`]).

use std::fmt::Write as _;
use std::path::PathBuf;

use anyhow::{bail, Context as _, Result};
use perpend_calib::record::{sha256_hex, Record};

pub use crate::record_cert::{cert_html, report_html, write_document};
pub use crate::record_fmt::{deg, esc, iso, sigma, value};
use crate::record_fmt::{geometry, opt_deg};
pub use crate::record_history::{
    find_records, fit_line, history, history_svg, history_text, History, Item, Line, TREND_SIGMAS,
};

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
    /// Print a calibration record in words, its outcome first.
    Show {
        /// The record (`record.json` of a cell run, `params.record.json`).
        file: PathBuf,
    },
    /// Write the calibration certificate (applied and verified calibrations only).
    Cert(DocArgs),
    /// Write a report of any record, marked as no certificate.
    Report(DocArgs),
    /// Find the records a board's calibration stamp leads to.
    Find(FindArgs),
    /// Per head: calibrations and checks against time, trends.
    History(HistoryArgs),
}

/// Arguments of `perpend record cert` and `report`.
#[derive(clap::Args, Debug)]
pub struct DocArgs {
    /// The record.
    pub file: PathBuf,
    /// Write the page here (HTML).
    #[arg(long)]
    pub out: PathBuf,
}

/// Arguments of `perpend record find`.
#[derive(clap::Args, Debug)]
pub struct FindArgs {
    /// The stamp as `perpend node info` prints it (8 hex digits).
    pub stamp: String,
    /// Directories searched recursively (default: the current one).
    pub dirs: Vec<PathBuf>,
}

/// Arguments of `perpend record history`.
#[derive(clap::Args, Debug)]
pub struct HistoryArgs {
    /// Directories searched recursively for records (or record files).
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    /// Only the head with this serial (`0xb143eae7` or `b143eae7`).
    #[arg(long)]
    pub serial: Option<String>,
    /// Tolerance on the verified p95 for the trend's date [deg] (default:
    /// the latest record's own tolerance, else 0.05). Each record is
    /// listed with the tolerance it was decided against.
    #[arg(long)]
    pub tolerance_deg: Option<f64>,
    /// Write a plot of the verified p95 against time (SVG, a panel per head).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Print one JSON object instead of the report.
    #[arg(long)]
    pub json: bool,
}

/// Runs `perpend record`.
///
/// # Errors
/// Unreadable or malformed records, a certificate refused, I/O.
pub fn run(a: &Args) -> Result<()> {
    match &a.cmd {
        Sub::Show { file } => {
            print!("{}", show_text(&Record::read(file)?));
            Ok(())
        }
        Sub::Cert(c) => {
            let r = Record::read(&c.file)?;
            let html = cert_html(&r).with_context(|| c.file.display().to_string())?;
            write_page(&c.out, &html)?;
            println!(
                "{}: {} ({}); certificate written to {}",
                c.file.display(),
                r.decision
                    .as_ref()
                    .map_or("not decided", |d| d.verdict.word()),
                r.outcome_words(),
                c.out.display()
            );
            Ok(())
        }
        Sub::Report(c) => {
            let r = Record::read(&c.file)?;
            write_page(&c.out, &report_html(&r))?;
            println!(
                "{}: outcome {}; report (not a certificate) written to {}",
                c.file.display(),
                r.outcome_words(),
                c.out.display()
            );
            Ok(())
        }
        Sub::Find(f) => run_find(f),
        Sub::History(h) => run_history(h),
    }
}

fn write_page(out: &std::path::Path, html: &str) -> Result<()> {
    std::fs::write(out, html).with_context(|| format!("cannot write {}", out.display()))
}

/// The record in words (`record show`): outcome and what happened first.
pub fn show_text(r: &Record) -> String {
    let mut o = String::new();
    let or = |x: &Option<String>| x.clone().unwrap_or_else(|| "none".into());
    let _ = writeln!(o, "outcome: {}", r.outcome_words());
    if let Some(d) = &r.decision {
        let line = decision_line(d);
        let _ = match r.outcome.as_deref() {
            Some(perpend_calib::record::OUTCOME_APPLIED) => writeln!(o, "{line}"),
            _ => writeln!(
                o,
                "{} (of a calibration that is not on the board)",
                line.replacen(d.verdict.word(), &d.verdict.word().to_lowercase(), 1)
            ),
        };
    }
    for e in &r.events {
        let _ = writeln!(o, "event: {e}");
    }
    let _ = writeln!(o, "calibration record ({}) of {}", r.schema, r.utc);
    let _ = writeln!(
        o,
        "head {} (firmware {}), written by {}",
        or(&r.head_serial),
        or(&r.firmware),
        r.tool_version
    );
    show_stamp(r, &mut o);
    if let Some(c) = &r.certification {
        let _ =
            writeln!(
            o,
            "certificate {}: site {}, operator {}, approver {}; tracker {} serial {} (due {}, {})",
            c.number.as_deref().unwrap_or("none (no certificate for this record)"),
            c.site,
            c.operator,
            c.approver,
            c.tracker.model,
            c.tracker.serial,
            c.tracker.calibration_due,
            c.tracker.traceability
        );
    }
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
    if let Some(f) = &r.frames {
        for l in perpend_calib::frames::report::lines(f) {
            let _ = writeln!(o, "{l}");
        }
    }
    match &r.previous {
        None => {
            let _ = writeln!(o, "replaced: nothing");
        }
        Some(p) => {
            let _ = writeln!(
                o,
                "replaced: parameters sha256 {}, record {}, {}",
                p.params_sha256,
                p.record_hash.as_deref().unwrap_or("none"),
                crate::record_fmt::replaced_stamp(p)
            );
        }
    }
    o
}

/// The decision in one line with its figures.
fn decision_line(d: &perpend_formats::conformity::Decision) -> String {
    let mut s = format!(
        "decision: {} against the tolerance {}° at {} fresh poses, largest expanded uncertainty \
         {}° (k ≤ {:.2} from each pose's degrees of freedom; tracker {}° per axis: {})",
        d.verdict.word(),
        d.tolerance_deg,
        d.poses.len(),
        deg(d.max_expanded_deg),
        d.k,
        deg(d.tracker_u_deg),
        d.tracker_u_source
    );
    if let Some(by) = &d.decide_by {
        s.push_str(&format!("; to decide it: {by}"));
    }
    s
}

fn show_stamp(r: &Record, o: &mut String) {
    match &r.stamp {
        Some(s) => {
            let _ = writeln!(
                o,
                "stamp on the board: {} (stored {}, store #{}): the SHA-256 of {} begins with it \
                 ({})",
                s.record_hash, s.utc, s.store_count, s.stamped_record.path, s.stamped_record.sha256
            );
        }
        None => {
            let _ = writeln!(o, "stamp on the board: none from this record");
        }
    }
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
        "  normal error over {} poses: mean {} deg, p95 {} deg, max {} deg; expected {} deg RMS ({} deg at 95 %); before {} deg",
        v.poses.len(),
        opt_deg(v.mean_deg),
        opt_deg(v.p95_deg),
        opt_deg(v.max_deg),
        opt_deg(v.expected_deg),
        opt_deg(v.expected_p95_deg),
        opt_deg(v.before_mean_deg)
    );
    let applied = r.outcome.as_deref() == Some(perpend_calib::record::OUTCOME_APPLIED);
    if let Some(d) = &r.decision {
        for p in &d.poses {
            // No PASS in words about a calibration that is not on the board.
            let word = match applied {
                true => p.verdict.word().to_string(),
                false => p.verdict.word().to_lowercase(),
            };
            let _ = writeln!(
                o,
                "  pose {}: {} ± {} deg (U, k = {:.2}; {} samples): {word}",
                p.pose,
                deg(p.error_deg),
                deg(p.expanded_deg),
                p.k,
                p.samples
            );
        }
    }
}

/// Where a stamp leads: (file, why it matches, the item).
pub fn find(stamp: &str, dirs: &[PathBuf]) -> Result<Vec<(PathBuf, String, Item)>> {
    let want = stamp.trim().trim_start_matches("0x").to_lowercase();
    if want.len() != 8 || !want.chars().all(|c| c.is_ascii_hexdigit()) {
        bail!(
            "stamp {stamp:?}: expected the 8 hex digits `perpend node info` prints after \
             \"stamp record\""
        );
    }
    let roots = if dirs.is_empty() {
        vec![PathBuf::from(".")]
    } else {
        dirs.to_vec()
    };
    let mut out: Vec<(PathBuf, String, Item)> = Vec::new();
    for f in find_records(&roots)? {
        let Ok(bytes) = std::fs::read(&f) else {
            continue;
        };
        let Ok(item) = Item::read(&f) else {
            continue;
        };
        if sha256_hex(&bytes).starts_with(&want) {
            out.push((
                f,
                "its SHA-256 begins with the stamp: the calibration's own record, written \
                 before the push (the cell record names the board)"
                    .into(),
                item,
            ));
        } else if let Item::Calibration(r) = &item {
            if r.stamp.as_ref().is_some_and(|s| s.record_hash == want) {
                out.push((
                    f,
                    "the cell run that stamped the board with it".into(),
                    item,
                ));
            } else if r
                .previous
                .as_ref()
                .and_then(|p| p.board_stamp.as_ref())
                .is_some_and(|s| s.record_hash == want)
            {
                out.push((
                    f,
                    "a later run that found the board with this stamp and replaced it".into(),
                    item,
                ));
            }
        }
    }
    // The cell record (board, outcome, decision) first, runs that
    // replaced it last.
    out.sort_by_key(|(_, why, _)| {
        if why.starts_with("the cell run") {
            0
        } else if why.starts_with("a later run") {
            2
        } else {
            1
        }
    });
    Ok(out)
}

fn run_find(a: &FindArgs) -> Result<()> {
    let found = find(&a.stamp, &a.dirs)?;
    if found.is_empty() {
        bail!(
            "no record under {} leads to stamp {}: search the directory where the cell runs of \
             this head were filed (perpend record find {} DIR)",
            if a.dirs.is_empty() {
                ".".to_string()
            } else {
                a.dirs
                    .iter()
                    .map(|d| d.display().to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            },
            a.stamp,
            a.stamp
        );
    }
    for (f, why, item) in &found {
        let what = match item {
            Item::Calibration(r) => format!(
                "head {}, {}, outcome {}",
                r.head_serial.as_deref().unwrap_or("no board"),
                r.utc,
                r.outcome_words()
            ),
            Item::Check(c) => format!("check of head {}, {}", c.head_serial, c.utc),
        };
        println!("{}: {why} ({what})", f.display());
    }
    Ok(())
}

fn run_history(a: &HistoryArgs) -> Result<()> {
    if let Some(t) = a.tolerance_deg {
        perpend_calib::cellconfig::check_tolerance(t).context("--tolerance-deg")?;
    }
    let files = find_records(&a.dirs)?;
    let h = history(&files, a.serial.as_deref(), a.tolerance_deg)?;
    if let Some(p) = &a.plot {
        std::fs::write(p, history_svg(&h))
            .with_context(|| format!("cannot write {}", p.display()))?;
    }
    if a.json {
        let v = serde_json::json!({ "heads": h });
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
pub fn beside(params: &std::path::Path) -> PathBuf {
    perpend_calib::record::record_path(params)
}
