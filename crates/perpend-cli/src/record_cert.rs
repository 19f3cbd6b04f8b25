//! The calibration certificate and the calibration report (issue 45):
//! one self-contained XHTML page each (no external resources, plots
//! inline SVG, every string from the record escaped).
//!
//! A **certificate** is issued only for a record whose calibration was
//! applied to a board and verified there against a tolerance
//! ([`Record::is_certifiable`]); it carries the fields of ISO/IEC
//! 17025:2017 §7.8.2 and §7.8.4: a unique number, the item (head serial,
//! firmware, the stamp the board carries and how to find this record from
//! it), who calibrated, where and when, the reference standard (the
//! tracker, its serial, calibration due date and traceability), the
//! environment, the method, the results per pose with their expanded
//! uncertainty (k from each pose's degrees of freedom), the decision rule and the statement of
//! conformity, the frame errors and what was done with them, the files
//! and their SHA-256, and an approval block. Every other record (a failed,
//! reverted or file-only calibration) gets a **report** with the same
//! figures under a banner that says it is not a certificate and why.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};
use perpend_calib::record::Record;
use perpend_formats::conformity::{Decision, Verdict};

use crate::record_fmt::{deg, esc, geometry, opt_deg, sigma, value};

const STYLE: &str = "body{font-family:sans-serif;max-width:60em;margin:2em auto}\
table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #999;padding:2px 6px;\
text-align:right}th{background:#eee}.pass{color:#070}.fail{color:#b00}.open{color:#a60}\
.banner{border:3px solid #b00;color:#b00;padding:0.5em;font-weight:bold}code{font-size:90%}\
.sign td{height:2.5em;min-width:12em;text-align:left}";

/// Every printed page names the document and says "page N of M" (CSS
/// page margin boxes, printed by Chromium 131 and later), so a loose page
/// is known for a part of its whole (ISO/IEC 17025 §7.8.2.1 d); the last
/// line says where it ends.
fn page_style(title: &str) -> String {
    // Inside <style> nothing is unescaped: keep the characters a CSS
    // string and HTML both take as they are.
    let title: String = title
        .chars()
        .filter(|c| c.is_ascii_alphanumeric() || " -.()".contains(*c))
        .collect();
    format!(
        "@page{{margin:2cm 1.5cm;@bottom-left{{content:\"{title}\";font-size:8pt}}\
         @bottom-right{{content:\"page \" counter(page) \" of \" counter(pages);font-size:8pt}}}}"
    )
}

/// Why `r` gets no certificate (`None`: it does).
pub fn refusal(r: &Record) -> Option<String> {
    if r.is_certifiable() {
        return None;
    }
    let outcome = r.outcome_words();
    if r.outcome.as_deref() == Some(perpend_calib::record::OUTCOME_APPLIED) {
        if let Some(why) = r.frame_beyond_tolerance() {
            return Some(why);
        }
        if let Some(d) = r.decision.as_ref().filter(|d| d.verdict != Verdict::Pass) {
            return Some(format!(
                "the verification is {} against the tolerance {}°, not PASS{}",
                d.verdict.word(),
                d.tolerance_deg,
                d.decide_by
                    .as_ref()
                    .map_or(String::new(), |by| format!(" ({by})"))
            ));
        }
    }
    if r.outcome.as_deref() == Some(perpend_calib::record::OUTCOME_FAILED_UNKNOWN) {
        return Some(match &r.stamp {
            Some(s) => format!(
                "the board's state is unknown (outcome {outcome}): it may hold this calibration, \
                 stored and stamped {} at {}, or the previous one; read its stamp (perpend node \
                 info) before use",
                s.record_hash, s.utc
            ),
            None => format!(
                "the board's state is unknown (outcome {outcome}): read its stamp (perpend node \
                 info) before use"
            ),
        });
    }
    Some(match r.outcome.as_deref() {
        Some(perpend_calib::record::OUTCOME_APPLIED) if r.decision.is_some() => {
            "no cell configuration named the reference standard (the tracker's serial, \
             calibration due date and traceability, who calibrated and who approves): run \
             with --config"
                .into()
        }
        Some(perpend_calib::record::OUTCOME_APPLIED) => format!(
            "the calibration was applied but its verification was not decided against a \
             tolerance (outcome {outcome}, verification {})",
            r.verification.kind
        ),
        Some(perpend_calib::record::OUTCOME_COMPUTED) => "the parameters were computed from \
             files and not applied to a board and verified there (perpend cell run does both)"
            .into(),
        _ => format!("the calibration is not on the board: outcome {outcome}"),
    })
}

/// The certificate of `r`.
///
/// # Errors
/// `r` is not certifiable ([`refusal`]).
pub fn cert_html(r: &Record) -> Result<String> {
    if let Some(why) = refusal(r) {
        bail!("no certificate for this record: {why}; `perpend record report` writes a report");
    }
    Ok(document(r, None))
}

/// The report of `r`: every figure of a certificate under a banner that
/// says it is none and why.
pub fn report_html(r: &Record) -> String {
    let why = refusal(r).unwrap_or_else(|| "a report was asked for".into());
    document(r, Some(&why))
}

/// Writes `dir/cert.html` for a certifiable record, else `dir/report.html`.
///
/// # Errors
/// I/O, naming the file.
pub fn write_document(r: &Record, dir: &Path) -> Result<PathBuf> {
    let (name, html) = match cert_html(r) {
        Ok(h) => ("cert.html", h),
        Err(_) => ("report.html", report_html(r)),
    };
    let path = dir.join(name);
    std::fs::write(&path, html).with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(path)
}

/// The verdict word and its CSS class.
fn verdict_class(d: Option<&Decision>) -> (&'static str, &'static str) {
    match d.map(|d| d.verdict) {
        Some(Verdict::Pass) => ("PASS", "pass"),
        Some(Verdict::Fail) => ("FAIL", "fail"),
        Some(Verdict::Inconclusive) => ("INCONCLUSIVE", "open"),
        None => ("NOT DECIDED", "open"),
    }
}

fn document(r: &Record, not_cert: Option<&str>) -> String {
    let mut h = String::new();
    let c = r.certification.as_ref();
    let number = c.and_then(|c| c.number.as_deref()).unwrap_or("-");
    let simulated = c.is_some_and(|c| c.simulated);
    let sim = if simulated { " (SIMULATION)" } else { "" };
    let title = match not_cert {
        None => format!("Calibration certificate No. {}{sim}", esc(number)),
        Some(_) => format!("Calibration report (not a certificate){sim}"),
    };
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html xmlns=\"http://www.w3.org/1999/xhtml\"><head><meta charset=\"utf-8\"/>\
         <title>{title}</title><style>{STYLE}{}</style></head><body><h1>{title}</h1>",
        page_style(&title)
    );
    if let Some(why) = not_cert {
        let _ = write!(
            h,
            "<p class=\"banner\" id=\"not-a-certificate\">NOT A CERTIFICATE: {}.</p>",
            esc(why)
        );
    }
    if simulated {
        h.push_str(
            "<p class=\"banner\" id=\"simulation\">SIMULATION: the datum planes were \
             measured by a simulated tracker on a virtual board (--robot sim:); no real head \
             was calibrated and no real reference standard was used.</p>",
        );
    }
    let _ = write!(
        h,
        "<p id=\"outcome\"><b>Outcome: {}</b></p>",
        esc(r.outcome_words())
    );
    doc_conformity(r, not_cert.is_some(), &mut h);
    doc_item(r, &mut h);
    doc_reference(r, &mut h);
    cert_verification(r, not_cert.is_some(), &mut h);
    doc_frames(r, &mut h);
    cert_parameters(r, &mut h);
    cert_files(r, &mut h);
    cert_dropped(r, &mut h);
    doc_events(r, &mut h);
    if not_cert.is_none() {
        doc_approval(r, &mut h);
    }
    h.push_str(
        "<p>The results relate only to the item calibrated, at the poses verified. The 1σ of \
         the parameters are standard uncertainties (k = 1).</p>",
    );
    let _ = writeln!(
        h,
        "<p id=\"end\">End of {}.</p></body></html>",
        match not_cert {
            None => format!("certificate No. {}", esc(number)),
            Some(_) => "report (not a certificate)".into(),
        }
    );
    h
}

fn doc_conformity(r: &Record, not_cert: bool, h: &mut String) {
    let d = r.decision.as_ref();
    let (word, class) = verdict_class(d);
    let _ = match not_cert {
        false => write!(h, "<h2 class=\"{class}\" id=\"verdict\">{word}</h2>"),
        true => {
            let of = match r.outcome.as_deref() {
                Some(perpend_calib::record::OUTCOME_APPLIED) => {
                    "of a calibration on the board, with no certificate"
                }
                Some(perpend_calib::record::OUTCOME_FAILED_UNKNOWN) => {
                    "of a calibration the board may or may not hold"
                }
                _ => "of a calibration that is not on the board",
            };
            write!(
                h,
                "<h2 class=\"open\" id=\"verdict\">Verification decision {of}: {}</h2>",
                if d.is_some() {
                    word.to_lowercase()
                } else {
                    "none".into()
                }
            )
        }
    };
    match d {
        Some(d) => {
            let _ = write!(
                h,
                "<p>Tolerance (maximum permissible normal error at every verified pose): \
                 <b>{}°</b>. Largest expanded uncertainty U = {}° (U = k·u, k for about \
                 95 % coverage of the error along its own direction, which decides near the \
                 tolerance: 2 with many samples, Student's t at the pose's Welch–Satterthwaite \
                 degrees of freedom with few; largest k here {:.2}). Decision rule: {}. The \
                 tracker's standard uncertainty per axis of a plane normal: {}° ({}).</p>",
                esc(&d.tolerance_deg.to_string()),
                deg(d.max_expanded_deg),
                d.k,
                esc(&d.rule),
                deg(d.tracker_u_deg),
                esc(&d.tracker_u_source)
            );
            if let Some(by) = &d.decide_by {
                let _ = write!(
                    h,
                    "<p class=\"open\">What would decide it: {}.</p>",
                    esc(by)
                );
            }
        }
        None => {
            let why = match r.outcome.as_deref() {
                Some(perpend_calib::record::OUTCOME_COMPUTED) | None => {
                    "the parameters were not verified on a board against a tolerance"
                }
                _ => "the run stopped before the calibration was verified on the board",
            };
            let _ = write!(h, "<p>No conformity decision: {why}.</p>");
        }
    }
}

fn row(h: &mut String, k: &str, v: &str) {
    let _ = write!(h, "<tr><th>{}</th><td>{}</td></tr>", esc(k), esc(v));
}

fn doc_item(r: &Record, h: &mut String) {
    h.push_str("<h2>Item, place and people</h2><table>");
    row(
        h,
        "head serial",
        r.head_serial.as_deref().unwrap_or("no board"),
    );
    row(h, "firmware", r.firmware.as_deref().unwrap_or("-"));
    match &r.stamp {
        Some(s) => {
            row(h, "stamp on the board (0x2011)", &s.record_hash);
            row(
                h,
                "stamped",
                &format!("{} (store #{})", s.utc, s.store_count),
            );
            row(
                h,
                "stamped record",
                &format!(
                    "{} sha256 {}",
                    s.stamped_record.path, s.stamped_record.sha256
                ),
            );
            row(
                h,
                "find this record from a board",
                &format!("perpend record find {} DIR", s.record_hash),
            );
        }
        None => row(h, "stamp on the board (0x2011)", "none from this record"),
    }
    let performed = r
        .certification
        .as_ref()
        .and_then(|c| c.performed_utc.as_ref())
        .map_or_else(
            || format!("{} (parameters fitted; the run's span was not kept)", r.utc),
            |[a, b]| format!("{a} to {b} (parameters fitted {})", r.utc),
        );
    row(h, "date of calibration (UTC)", &performed);
    let now = perpend_calib::record::utc_now();
    let issued = match r.certification.as_ref().and_then(|c| c.issued_utc.as_ref()) {
        Some(first) if first != &now => {
            format!("{first} (this copy printed {now}: a copy of that issue, not a new one)")
        }
        Some(first) => first.clone(),
        None => now,
    };
    row(h, "date of issue (UTC)", &issued);
    row(h, "tool", &r.tool_version);
    row(
        h,
        "method, model",
        &format!(
            "{}, {}: Chen et al. 2018 (the reading model of eq. 3-9 by least squares; spot \
             points eq. 17, then the micro-plane normal), the cell run of docs/record.md",
            r.method, r.model
        ),
    );
    row(h, "poses used", &r.poses_used.to_string());
    if let Some(c) = &r.certification {
        row(
            h,
            "certificate number",
            c.number
                .as_deref()
                .unwrap_or("none: no certificate for this record"),
        );
        row(
            h,
            "laboratory",
            c.laboratory.as_deref().unwrap_or("not kept in this record"),
        );
        row(
            h,
            "customer",
            c.customer.as_deref().unwrap_or("none named (in-house)"),
        );
        row(h, "site", &c.site);
        row(h, "calibrated by", &c.operator);
        let t = |x: Option<f64>| x.map_or("not measured".to_string(), |t| format!("{t:.1} °C"));
        row(
            h,
            "board die temperature (0x200A), start / end",
            &format!("{} / {}", t(c.die_temp_c[0]), t(c.die_temp_c[1])),
        );
        row(h, "cell air temperature (as configured)", &t(c.ambient_c));
    }
    h.push_str("</table>");
}

fn doc_reference(r: &Record, h: &mut String) {
    let Some(c) = &r.certification else {
        return;
    };
    let t = &c.tracker;
    h.push_str("<h2>Reference standard</h2><table>");
    row(h, "tracker", &t.model);
    row(h, "serial", &t.serial);
    row(h, "calibration due", &t.calibration_due);
    row(h, "traceability", &t.traceability);
    row(
        h,
        "point noise, points, patch",
        &format!("{} mm, {}, {} mm", t.xi_mm, t.points, t.patch_mm),
    );
    match &c.config {
        Some(f) => row(
            h,
            "cell configuration",
            &format!("{} sha256 {}", f.path, f.sha256),
        ),
        None => row(
            h,
            "cell configuration",
            "none given: the figures above are stated defaults",
        ),
    }
    h.push_str("</table>");
}

fn doc_frames(r: &Record, h: &mut String) {
    let Some(f) = &r.frames else {
        if r.decision.is_some() {
            h.push_str(
                "<h2>Frame errors</h2><p id=\"frames\">Not assessed: the run turned no joint \
                 about the spindle axis (cell run --reversal), so a tilt of the tracker's frame \
                 would be absorbed by the calibration and the verification alike (docs/frames.md).\
                 </p>",
            );
        }
        return;
    };
    h.push_str(
        "<h2>Frame errors (reversal)</h2><table><tr><th>frame error</th><th>value</th>\
         <th>1σ</th><th>significant</th><th>resolved</th></tr>",
    );
    let o = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{v:.1}"));
    for e in &f.errors {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{} {}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            esc(&e.name),
            o(e.value),
            esc(&e.unit),
            o(e.sigma),
            if e.significant { "yes" } else { "no" },
            if e.resolved { "yes" } else { "no" }
        );
    }
    h.push_str("</table>");
    for w in &f.warnings {
        let _ = write!(h, "<p class=\"fail\">Warning: {}</p>", esc(w));
    }
    h.push_str(
        "<p>What was done: the head was calibrated against the tracker's planes corrected \
         by the estimated frame errors; the cell's frames themselves were not changed.</p>",
    );
}

fn doc_events(r: &Record, h: &mut String) {
    h.push_str("<h2>Events</h2><ul>");
    for e in &r.events {
        let _ = write!(h, "<li>{}</li>", esc(e));
    }
    h.push_str("</ul>");
}

fn doc_approval(r: &Record, h: &mut String) {
    let c = r.certification.as_ref();
    let who = |f: fn(&perpend_calib::record::Certification) -> &String| {
        c.map_or(String::new(), |c| esc(f(c)))
    };
    let _ = write!(
        h,
        "<h2>Approval</h2><table class=\"sign\"><tr><th></th><th>name</th><th>signature</th>\
         <th>date</th></tr><tr><th>calibrated by</th><td>{}</td><td></td><td></td></tr>\
         <tr><th>approved by</th><td>{}</td><td></td><td></td></tr></table>",
        who(|c| &c.operator),
        who(|c| &c.approver)
    );
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
            "<p>Replaces parameters <code>{}</code> (record {}; {}).</p>",
            esc(&p.params_sha256),
            esc(p.record_hash.as_deref().unwrap_or("none")),
            esc(&crate::record_fmt::replaced_stamp(p))
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

fn cert_verification(r: &Record, not_cert: bool, h: &mut String) {
    let tol = r.decision.as_ref().map(|d| d.tolerance_deg);
    let v = &r.verification;
    let _ = write!(
        h,
        "<h2>Verification</h2><p>{}: {}</p><table><tr><th>mean [deg]</th><th>p95 [deg]</th>\
         <th>max [deg]</th><th>expected RMS [deg]</th><th>expected 95 % [deg]</th>\
         <th>before, mean [deg]</th></tr>\
         <tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr></table>",
        esc(&v.kind),
        esc(&v.note),
        opt_deg(v.mean_deg),
        opt_deg(v.p95_deg),
        opt_deg(v.max_deg),
        opt_deg(v.expected_deg),
        opt_deg(v.expected_p95_deg),
        opt_deg(v.before_mean_deg)
    );
    if v.poses.is_empty() {
        h.push_str("<p>Not verified: no per-pose errors.</p>");
        return;
    }
    h.push_str(&bars_svg(v, r.decision.as_ref()));
    match &r.decision {
        Some(d) => cert_decision_table(d, not_cert, h),
        None => {
            h.push_str("<table><tr><th>pose</th><th>normal error [deg]</th></tr>");
            for p in &v.poses {
                let _ = write!(
                    h,
                    "<tr><td>{}</td><td>{}</td></tr>",
                    p.pose,
                    deg(p.error_deg)
                );
            }
            h.push_str("</table>");
        }
    }
    if tol.is_none() {
        h.push_str("<p>No tolerance was decided on for this record.</p>");
    }
}

/// The per-pose table; in a report (`lower`) the verdicts in lower case,
/// so that no PASS stands on a page about a calibration not on the board.
fn cert_decision_table(d: &Decision, lower: bool, h: &mut String) {
    h.push_str(
        "<table><tr><th>pose</th><th>normal error [deg]</th><th>u (readings) [deg]</th>\
         <th>u (combined) [deg]</th><th>k</th><th>U = k·u [deg]</th><th>samples</th>\
         <th>verdict</th></tr>",
    );
    for p in &d.poses {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.2}</td><td>{}</td><td>{}</td>\
             <td>{}</td></tr>",
            p.pose,
            deg(p.error_deg),
            deg(p.readings_u_deg),
            deg(p.u_deg),
            p.k,
            deg(p.expanded_deg),
            p.samples,
            if lower {
                p.verdict.word().to_lowercase()
            } else {
                p.verdict.word().to_string()
            }
        );
    }
    h.push_str("</table>");
}

/// Per-pose errors with their expanded uncertainty against the tolerance
/// line (inline SVG).
fn bars_svg(v: &perpend_calib::record::Verification, d: Option<&Decision>) -> String {
    let (w, ht, m) = (640.0, 220.0, 40.0);
    let tol = d.map_or(f64::NAN, |d| d.tolerance_deg);
    let big_u = |k: usize| {
        d.and_then(|d| d.poses.get(k))
            .map_or(0.0, |p| p.expanded_deg)
    };
    let top = v
        .poses
        .iter()
        .enumerate()
        .map(|(k, p)| p.error_deg + big_u(k))
        .fold(if tol.is_nan() { 0.0 } else { tol }, f64::max)
        * 1.1;
    let y = |e: f64| ht - m - (ht - 2.0 * m) * e / top;
    let bw = (w - 2.0 * m) / v.poses.len() as f64;
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{ht}\" \
         viewBox=\"0 0 {w} {ht}\"><rect x=\"0\" y=\"0\" width=\"{w}\" height=\"{ht}\" fill=\"white\"/>"
    );
    for (i, p) in v.poses.iter().enumerate() {
        let fill = if d.is_none() || p.error_deg <= tol {
            "#48a"
        } else {
            "#c33"
        };
        let x = m + i as f64 * bw;
        let _ = write!(
            s,
            "<rect x=\"{x:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"{fill}\"/>",
            y(p.error_deg),
            (bw * 0.8).max(0.5),
            (ht - m - y(p.error_deg)).max(0.0)
        );
        let u = big_u(i);
        if u > 0.0 {
            let cx = x + (bw * 0.4).max(0.25);
            let _ = write!(
                s,
                "<line x1=\"{cx:.1}\" y1=\"{:.1}\" x2=\"{cx:.1}\" y2=\"{:.1}\" stroke=\"black\"/>",
                y(p.error_deg + u),
                y((p.error_deg - u).max(0.0))
            );
        }
    }
    if d.is_some() {
        let _ = write!(
            s,
            "<line x1=\"{m}\" y1=\"{ty:.1}\" x2=\"{x2}\" y2=\"{ty:.1}\" stroke=\"#b00\" \
             stroke-dasharray=\"6 3\"/><text x=\"{m}\" y=\"{tl:.1}\" font-size=\"11\" \
             fill=\"#b00\">tolerance {}°</text>",
            tol,
            ty = y(tol),
            x2 = w - m,
            tl = y(tol) - 3.0,
        );
    }
    let whiskers = if d.is_some() {
        "; whiskers: ± U (k·u)"
    } else {
        ""
    };
    let _ = write!(
        s,
        "<line x1=\"{m}\" y1=\"{b}\" x2=\"{x2}\" y2=\"{b}\" stroke=\"black\"/>\
         <text x=\"{m}\" y=\"{bl:.1}\" font-size=\"11\">normal error per verification pose \
         [deg], 0 to {top}{whiskers}</text></svg>",
        x2 = w - m,
        b = ht - m,
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
