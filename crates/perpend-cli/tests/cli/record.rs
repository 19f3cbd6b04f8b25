//! `perpend record`: the certificate is well-formed XHTML whose figures
//! are the record's and whose strings are escaped, and it is issued only
//! for an applied, decided calibration: every other outcome gets a report
//! that says it is none and shows no PASS; the history finds a known drift
//! and its recalibration date, says "no trend" on series without one (at
//! a 2σ threshold), reports each head of a mix and puts checks with the
//! calibrations.
#![allow(clippy::unwrap_used, missing_docs)]

use perpend_calib::record::{
    BoardStamp, Certification, FileHash, PoseError, Record, Verification, KIND_FRESH,
    OUTCOME_APPLIED, OUTCOME_COMPUTED, OUTCOME_FAILED_RESTORED, OUTCOME_FAILED_UNKNOWN,
    OUTCOME_REVERTED,
};
use perpend_cli::record::{cert_html, deg, history, report_html, sigma, value, TREND_SIGMAS};
use perpend_formats::conformity::{decide, Measured};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
fn example() -> Record {
    let doc = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../docs/record.md"))
        .unwrap();
    let start = doc.find("```json\n").unwrap() + 8;
    let end = start + doc[start..].find("```").unwrap();
    Record::parse(&doc[start..end], "docs/record.md").unwrap()
}

/// Tags balance (a tiny XML well-formedness check: no attributes with `>`).
fn balanced(html: &str) -> Result<(), String> {
    let mut stack: Vec<String> = Vec::new();
    let mut rest = html;
    while let Some(i) = rest.find('<') {
        rest = &rest[i + 1..];
        let j = rest.find('>').ok_or("unclosed <")?;
        let tag = &rest[..j];
        rest = &rest[j + 1..];
        if tag.starts_with('!') || tag.ends_with('/') {
            continue;
        }
        let name = tag
            .trim_start_matches('/')
            .split_whitespace()
            .next()
            .unwrap_or("");
        if tag.starts_with('/') {
            match stack.pop() {
                Some(open) if open == name => {}
                other => return Err(format!("</{name}> closes {other:?}")),
            }
        } else {
            stack.push(name.to_string());
        }
    }
    if stack.is_empty() {
        Ok(())
    } else {
        Err(format!("unclosed: {stack:?}"))
    }
}

/// The example as a cell run records an applied calibration: fresh
/// poses decided against 0.05°, a stamp, the certificate's fields.
fn applied() -> Record {
    let mut r = example().with_board("0xb143eae7", "perpend 0.1.0");
    let measured: Vec<Measured> = r
        .verification
        .poses
        .iter()
        .take(8)
        .map(|p| Measured {
            pose: p.pose,
            error_deg: p.error_deg,
            readings_u_deg: 0.002,
            samples: 20,
        })
        .collect();
    let poses = measured
        .iter()
        .map(|m| PoseError {
            pose: m.pose,
            error_deg: m.error_deg,
        })
        .collect();
    r = r.with_verification(Verification::from_errors(KIND_FRESH, "fresh", poses));
    r.decision = Some(decide(&measured, 0.05, 0.006, "test tracker"));
    r.outcome = Some(OUTCOME_APPLIED.into());
    r.stamp = Some(BoardStamp {
        record_hash: "0507bf5a".into(),
        stamped_record: FileHash {
            path: "run/params.record.json".into(),
            sha256: format!("0507bf5a{}", "0".repeat(56)),
        },
        utc: "2026-12-01T10:00:00Z".into(),
        store_count: 3,
    });
    r.certification = Some(Certification {
        number: Some("PPD-B143EAE7-20261201T100000Z".into()),
        operator: "A. Operator".into(),
        approver: "Q. Engineer".into(),
        site: "Plant 2, cell 4".into(),
        laboratory: Some("Metrology lab, 1 Plant Road, Town".into()),
        customer: None,
        performed_utc: Some(["2026-12-01T09:00:00Z".into(), "2026-12-01T10:05:00Z".into()]),
        simulated: false,
        issued_utc: Some("2026-12-01T10:06:00Z".into()),
        tracker: perpend_calib::cellconfig::paper_tracker("Tracker T1"),
        die_temp_c: [Some(31.5), Some(32.0)],
        ambient_c: Some(21.5),
        config: Some(FileHash {
            path: "cell-config.json".into(),
            sha256: "1".repeat(64),
        }),
    });
    r
}

#[test]
fn the_certificate_is_well_formed_and_shows_the_records_figures() {
    let r = applied();
    let html = cert_html(&r).unwrap();
    balanced(&html).unwrap();
    assert!(
        !html.contains("http://") || !html.contains("src="),
        "no external resources"
    );
    let d = r.decision.as_ref().unwrap();
    assert!(html.contains(&format!("id=\"verdict\">{}</h2>", d.verdict.word())));
    assert!(html.contains("Outcome: applied"));
    assert!(!html.contains("NOT A CERTIFICATE"));
    // Each printed page names the certificate and counts the pages; the
    // end is marked; the laboratory, customer and the run's span shown.
    assert!(html.contains(
        "@bottom-left{content:\"Calibration certificate No. PPD-B143EAE7-20261201T100000Z\""
    ));
    assert!(html.contains("counter(pages)"));
    assert!(html.contains("End of certificate No. PPD-B143EAE7-20261201T100000Z.</p></body>"));
    assert!(html.contains("Metrology lab, 1 Plant Road, Town"));
    assert!(html.contains("none named (in-house)"));
    assert!(html.contains("2026-12-01T09:00:00Z to 2026-12-01T10:05:00Z (parameters fitted"));
    // Printed again: the first issue's date, said to be a copy of it.
    assert!(html.contains("2026-12-01T10:06:00Z (this copy printed"));
    assert!(html.contains("Not assessed: the run turned no joint"));
    assert!(!html.contains("SIMULATION"));
    let v = &r.verification;
    for x in [v.mean_deg, v.p95_deg, v.max_deg] {
        assert!(html.contains(&format!("<td>{}</td>", deg(x.unwrap()))));
    }
    for p in &d.poses {
        let row = format!(
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.2}</td><td>{}</td><td>{}</td>\
             <td>{}</td></tr>",
            p.pose,
            deg(p.error_deg),
            deg(p.readings_u_deg),
            deg(p.u_deg),
            p.k,
            deg(p.expanded_deg),
            p.samples,
            p.verdict.word()
        );
        assert!(html.contains(&row), "{row}");
    }
    for want in [
        "0507bf5a",
        "perpend record find 0507bf5a DIR",
        "PPD-B143EAE7-20261201T100000Z",
        "Q. Engineer",
        "Tracker T1",
        "31.5 °C / 32.0 °C",
        "Approval",
    ] {
        assert!(html.contains(want), "{want}");
    }
    assert!(html.contains(&deg(d.max_expanded_deg)));
    for f in &r.inputs {
        assert!(html.contains(&f.sha256));
    }
    for p in &r.parameters {
        let s = p.sigma.unwrap();
        for j in 0..3 {
            assert!(html.contains(&format!("<td>{}</td>", value(p.zero_mm[j], false))));
            assert!(html.contains(&format!("<td>{}</td>", value(p.dir[j], true))));
            assert!(html.contains(&format!("<td>{}</td>", sigma(s.zero_mm[j]))));
            assert!(html.contains(&format!("<td>{}</td>", sigma(s.dir[j]))));
        }
    }
}

#[test]
fn strings_are_escaped_and_unverified_records_get_no_certificate() {
    let mut r = applied()
        .with_board("<script>alert(1)</script>&", "1.2 \"x\"")
        .with_verification(Verification::expected_only("none"));
    r.decision = None;
    let e = format!("{:#}", cert_html(&r).unwrap_err());
    assert!(e.contains("no certificate"), "{e}");
    let html = report_html(&r);
    balanced(&html).unwrap();
    assert!(!html.contains("<script>"));
    assert!(html.contains("&lt;script&gt;alert(1)&lt;/script&gt;&amp;"));
    assert!(html.contains("NOT A CERTIFICATE"));
}

/// A failed, reverted or file-only calibration: no certificate, and its
/// report carries no PASS anywhere, whatever its cross-validated figures.
#[test]
fn no_pass_for_a_calibration_that_is_not_on_the_board() {
    for outcome in [
        OUTCOME_REVERTED,
        OUTCOME_FAILED_RESTORED,
        OUTCOME_FAILED_UNKNOWN,
        OUTCOME_COMPUTED,
    ] {
        let mut r = applied();
        r.outcome = Some(outcome.into());
        let e = format!("{:#}", cert_html(&r).unwrap_err());
        assert!(e.contains("no certificate"), "{outcome}: {e}");
        let html = report_html(&r);
        balanced(&html).unwrap();
        assert!(html.contains("NOT A CERTIFICATE"), "{outcome}");
        assert!(html.contains(&format!("Outcome: {outcome}")), "{outcome}");
        assert!(!html.contains("PASS"), "{outcome}: PASS in the report");
        assert!(!html.contains("Approval"), "{outcome}: an approval block");
        let shown = perpend_cli::record::show_text(&r);
        assert!(
            shown.starts_with(&format!("outcome: {outcome}\n")),
            "{shown}"
        );
        assert!(!shown.contains("PASS"), "{outcome}: {shown}");
    }
    // The doc's example, a calibrate record (cross-validated p95 within
    // 0.05°), was a PASS certificate before outcomes: no more.
    assert!(cert_html(&example()).is_err());
}

/// A series of `n` weekly records of head `serial` whose per-pose errors
/// (40 poses) scatter by 0.003° about `level(day)`.
fn series(dir: &std::path::Path, seed: u64, n: usize, level: impl Fn(f64) -> f64) {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let base = example().with_board("H-17", "1.0");
    let t0 = humantime::parse_rfc3339("2026-01-01T00:00:00Z").unwrap();
    for k in 0..n {
        let day = 7.0 * k as f64;
        let noise = Normal::new(level(day), 0.003).unwrap();
        let poses = (0..40)
            .map(|p| PoseError {
                pose: p,
                error_deg: noise.sample(&mut rng).abs(),
            })
            .collect();
        let mut r = base
            .clone()
            .with_verification(Verification::from_errors(KIND_FRESH, "test", poses));
        let t = t0 + std::time::Duration::from_secs_f64(day * 86400.0 + rng.gen_range(0.0..3600.0));
        r.utc = humantime::format_rfc3339_seconds(t).to_string();
        r.write(&dir.join(format!("w{k}.record.json"))).unwrap();
    }
}

#[test]
fn a_known_drift_gives_its_recalibration_date() {
    // Level 0.010° + 0.0005°/day, p95 ≈ level + 1.645·0.003: the trend
    // reaches 0.05° at day (0.05 − 0.010 − 0.0049)/0.0005 ≈ 70, after the
    // last of 8 weekly records (day 49): a date ahead, "recalibrate by".
    for seed in 1..=5 {
        let dir = tempfile::tempdir().unwrap();
        series(dir.path(), seed, 8, |d| 0.010 + 0.0005 * d);
        let files = perpend_cli::record::find_records(&[dir.path().to_path_buf()]).unwrap();
        let h = history(&files, None, Some(0.05)).unwrap().remove(0);
        assert_eq!(h.unit, "day");
        let l = h.verification.unwrap();
        assert!(l.resolved(), "seed {seed}: {l:?}");
        assert!(
            (l.b - 0.0005).abs() < 4.0 * l.sigma_b + 5e-5,
            "seed {seed}: {l:?}"
        );
        let date = h.recalibrate_by.clone().unwrap();
        let when = humantime::parse_rfc3339(&date).unwrap();
        let t0 = humantime::parse_rfc3339("2026-01-01T00:00:00Z").unwrap();
        let day = when.duration_since(t0).unwrap().as_secs_f64() / 86400.0;
        assert!(
            (day - 70.2).abs() < 7.0,
            "seed {seed}: day {day}, {}",
            h.verdict
        );
        assert!(h.verdict.starts_with("recalibrate by"), "{}", h.verdict);
    }
}

#[test]
fn no_drift_says_no_trend_at_2_sigma() {
    assert_eq!(TREND_SIGMAS, 2.0);
    let mut quiet = 0;
    for seed in 100..120 {
        let dir = tempfile::tempdir().unwrap();
        series(dir.path(), seed, 12, |_| 0.02);
        let files = perpend_cli::record::find_records(&[dir.path().to_path_buf()]).unwrap();
        let h = history(&files, None, Some(0.05)).unwrap().remove(0);
        if h.verdict.starts_with("no trend") {
            quiet += 1;
        }
    }
    assert!(quiet >= 19, "no trend in only {quiet} of 20 seeds");
}

#[test]
fn each_head_of_a_mix_gets_its_section_and_serials_match_as_typed() {
    let dir = tempfile::tempdir().unwrap();
    series(dir.path(), 1, 3, |_| 0.02);
    let other = example().with_board("0xB143EAE7", "1.0");
    other.write(&dir.path().join("o.record.json")).unwrap();
    let files = perpend_cli::record::find_records(&[dir.path().to_path_buf()]).unwrap();
    let hs = history(&files, None, Some(0.05)).unwrap();
    assert_eq!(hs.len(), 2);
    let text = perpend_cli::record::history_text(&hs);
    assert!(
        text.contains("history of head 0xb143eae7 (1 records)"),
        "{text}"
    );
    assert!(text.contains("history of head h-17 (3 records)"), "{text}");
    let h = history(&files, Some("H-17"), Some(0.05)).unwrap();
    assert_eq!((h.len(), h[0].entries.len()), (1, 3));
    let h = history(&files, Some("b143eae7"), Some(0.05)).unwrap();
    assert_eq!(h[0].entries.len(), 1);
    let e = format!(
        "{:#}",
        history(&files, Some("0x1"), Some(0.05)).unwrap_err()
    );
    assert!(e.contains("no record of head 0x1"), "{e}");
    let svg = perpend_cli::record::history_svg(&hs);
    assert!(svg.contains("height=\"600\""), "a panel per head");
}

/// A store count that falls between two applied calibrations of one
/// serial is said before any trend; one that rises is not; the plot has
/// labelled ticks on both axes.
#[test]
fn a_falling_store_count_is_a_warning_and_the_plot_has_ticks() {
    for (counts, warned) in [([3u32, 4, 5], false), ([7, 8, 2], true)] {
        let dir = tempfile::tempdir().unwrap();
        series(dir.path(), 7, 3, |_| 0.02);
        for (k, c) in counts.iter().enumerate() {
            let f = dir.path().join(format!("w{k}.record.json"));
            let mut r = Record::read(&f).unwrap();
            r.outcome = Some(OUTCOME_APPLIED.into());
            r.stamp = Some(BoardStamp {
                record_hash: format!("{k:08x}"),
                stamped_record: FileHash {
                    path: "params.record.json".into(),
                    sha256: "0".repeat(64),
                },
                utc: r.utc.clone(),
                store_count: *c,
            });
            r.write(&f).unwrap();
        }
        let files = perpend_cli::record::find_records(&[dir.path().to_path_buf()]).unwrap();
        let hs = history(&files, None, Some(0.05)).unwrap();
        assert_eq!(!hs[0].warnings.is_empty(), warned, "{counts:?}");
        let text = perpend_cli::record::history_text(&hs);
        assert_eq!(text.contains("WARNING: store count 2 at"), warned, "{text}");
        let svg = perpend_cli::record::history_svg(&hs);
        assert_eq!(svg.contains(">WARNING: store count 2 at"), warned);
        assert!(
            svg.contains(">days</text>") && svg.contains(">10</text>"),
            "{svg}"
        );
        assert!(svg.contains(">0.04</text>"), "{svg}");
    }
}

/// A board's stamp leads to the cell run that set it, then to the later
/// run that found it on the board and replaced it (`previous.board_stamp`).
#[test]
fn a_stamp_leads_to_its_run_and_to_the_run_that_replaced_it() {
    let dir = tempfile::tempdir().unwrap();
    let first = applied();
    let stamp = first.stamp.clone().unwrap();
    first.write(&dir.path().join("run1.record.json")).unwrap();
    let mut later = applied();
    later.utc = "2026-12-08T10:00:00Z".into();
    later.stamp.as_mut().unwrap().record_hash = "11223344".into();
    later.previous = Some(perpend_calib::record::Previous {
        params_sha256: "2".repeat(64),
        record_hash: None,
        record_file_sha256: None,
        record_utc: None,
        board_stamp: Some(perpend_formats::paramfile::CalibrationStamp {
            record_hash: stamp.record_hash.clone(),
            utc: stamp.utc.clone(),
            utc_s: 1_796_119_200,
            store_count: stamp.store_count,
        }),
    });
    later.write(&dir.path().join("run2.record.json")).unwrap();
    let found = perpend_cli::record::find(&stamp.record_hash, &[dir.path().to_path_buf()]).unwrap();
    let names: Vec<String> = found
        .iter()
        .map(|(f, why, _)| format!("{}: {why}", f.file_name().unwrap().to_string_lossy()))
        .collect();
    assert_eq!(names.len(), 2, "{names:?}");
    assert!(
        names[0].starts_with("run1.record.json: the cell run"),
        "{names:?}"
    );
    assert!(
        names[1].starts_with("run2.record.json: a later run"),
        "{names:?}"
    );
    let shown = perpend_cli::record::show_text(&later);
    assert!(
        shown.contains("the board's stamp 0507bf5a of 2026-12-01T10:00:00Z (store 3)"),
        "{shown}"
    );
}

/// Records minutes apart get slopes per minute, not per day.
#[test]
fn the_slope_unit_fits_the_span() {
    use perpend_cli::record_history::unit_for;
    assert_eq!(unit_for(600.0).0, "minute");
    assert_eq!(unit_for(3.0 * 3600.0).0, "hour");
    assert_eq!(unit_for(5.0 * 86400.0).0, "day");
    assert_eq!(unit_for(200.0 * 86400.0).0, "week");
}

/// `perpend --version` prints the version string every record carries.
#[test]
fn the_version_is_the_records_version() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_perpend"))
        .arg("--version")
        .output()
        .unwrap();
    assert!(out.status.success());
    let v = String::from_utf8(out.stdout).unwrap();
    assert_eq!(v.trim(), perpend_calib::record::tool_version());
    assert!(v.contains(" ("), "{v}");
}

#[test]
fn history_lists_each_record_s_own_tolerance_and_dates_with_the_latest() {
    let dir = tempfile::tempdir().unwrap();
    let mut a = applied();
    a.utc = "2026-12-01T10:00:00Z".into();
    a.write(&dir.path().join("a.record.json")).unwrap();
    let mut b = applied();
    b.utc = "2026-12-08T10:00:00Z".into();
    b.decision.as_mut().unwrap().tolerance_deg = 0.03;
    b.write(&dir.path().join("b.record.json")).unwrap();
    let files = perpend_cli::record::find_records(&[dir.path().to_path_buf()]).unwrap();
    let h = history(&files, None, None).unwrap().remove(0);
    let tols: Vec<Option<f64>> = h.entries.iter().map(|e| e.tolerance_deg).collect();
    assert_eq!(tols, [Some(0.05), Some(0.03)]);
    assert_eq!(h.tolerance_deg, 0.03);
    assert!(
        h.tolerance_source.contains("latest record"),
        "{}",
        h.tolerance_source
    );
    let text = perpend_cli::record::history_text(std::slice::from_ref(&h));
    assert!(text.contains("tolerance   0.05"), "{text}");
    assert!(text.contains("tolerance   0.03"), "{text}");
    // Given on the command line, it dates the trend; the entries keep theirs.
    let h = history(&files, None, Some(0.08)).unwrap().remove(0);
    assert_eq!(
        (h.tolerance_deg, h.entries[1].tolerance_deg),
        (0.08, Some(0.03))
    );
    assert_eq!(h.tolerance_source, "--tolerance-deg");
}
