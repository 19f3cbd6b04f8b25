//! `perpend record`: the certificate is well-formed XHTML whose figures
//! are the record's and whose strings are escaped; the history finds a
//! known drift and its recalibration date, and says "no trend" on series
//! without one (at a 2σ threshold); a mix of heads is refused.
#![allow(clippy::unwrap_used, missing_docs)]

use perpend_cli::record::{cert_html, deg, history, sigma, value, TREND_SIGMAS};
use perpend_lab::record::{PoseError, Record, Verification, KIND_FRESH};
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

#[test]
fn the_certificate_is_well_formed_and_shows_the_records_figures() {
    let r = example();
    let html = cert_html(&r, 0.05);
    balanced(&html).unwrap();
    assert!(
        !html.contains("http://") || !html.contains("src="),
        "no external resources"
    );
    assert!(html.contains("PASS"));
    let v = &r.verification;
    for x in [
        v.mean_deg,
        v.p95_deg,
        v.max_deg,
        v.expected_deg,
        v.expected_p95_deg,
    ] {
        assert!(html.contains(&format!("<td>{}</td>", deg(x.unwrap()))));
    }
    for p in &v.poses {
        let row = format!("<tr><td>{}</td><td>{}</td>", p.pose, deg(p.error_deg));
        assert!(html.contains(&row), "{row}");
    }
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
fn strings_are_escaped_and_unverified_records_fail() {
    let r = example()
        .with_board("<script>alert(1)</script>&", "1.2 \"x\"")
        .with_verification(Verification::expected_only("none"));
    let html = cert_html(&r, 0.05);
    balanced(&html).unwrap();
    assert!(!html.contains("<script>"));
    assert!(html.contains("&lt;script&gt;alert(1)&lt;/script&gt;&amp;"));
    assert!(html.contains("FAIL") && html.contains("not verified"));
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
        let h = history(&files, None, 0.05).unwrap();
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
        let h = history(&files, None, 0.05).unwrap();
        if h.verdict.starts_with("no trend") {
            quiet += 1;
        }
    }
    assert!(quiet >= 19, "no trend in only {quiet} of 20 seeds");
}

#[test]
fn a_mix_of_heads_is_refused_unless_one_is_picked() {
    let dir = tempfile::tempdir().unwrap();
    series(dir.path(), 1, 3, |_| 0.02);
    let other = example().with_board("H-99", "1.0");
    other.write(&dir.path().join("o.record.json")).unwrap();
    let files = perpend_cli::record::find_records(&[dir.path().to_path_buf()]).unwrap();
    let e = format!("{:#}", history(&files, None, 0.05).unwrap_err());
    assert!(e.contains("--serial") && e.contains("H-99"), "{e}");
    let h = history(&files, Some("H-17"), 0.05).unwrap();
    assert_eq!(h.entries.len(), 3);
}
