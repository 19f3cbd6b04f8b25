//! `docs/sim-vs-measured.md` is what `perpend study paper` writes with its
//! default seeds: the test regenerates the document (the same
//! configuration, seeded and single-threaded, so the run is deterministic)
//! and fails when the committed copy differs. Regenerate with
//! `cargo run -p perpend-cli -- study paper --out docs/sim-vs-measured.md`
//! (or run this test with `PERPEND_UPDATE_DOCS=1`).

use std::path::PathBuf;

use perpend_diagnosis::diagnose::study::{markdown, paper_study, Plan};

fn doc_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../docs/sim-vs-measured.md")
}

#[test]
fn committed_document_is_what_the_study_writes() -> anyhow::Result<()> {
    let st = paper_study(Plan::default())?;
    let fresh = markdown(&st);
    let path = doc_path();
    if std::env::var_os("PERPEND_UPDATE_DOCS").is_some() {
        std::fs::write(&path, &fresh)?;
    }
    let committed = std::fs::read_to_string(&path)?;
    if committed != fresh {
        let line = committed
            .lines()
            .zip(fresh.lines())
            .position(|(a, b)| a != b)
            .map_or(committed.lines().count().min(fresh.lines().count()), |k| k);
        panic!(
            "docs/sim-vs-measured.md differs from `perpend study paper` from line {}:\n  committed: {:?}\n  fresh:     {:?}\n\
             regenerate with `cargo run -p perpend-cli -- study paper --out docs/sim-vs-measured.md`",
            line + 1,
            committed.lines().nth(line),
            fresh.lines().nth(line)
        );
    }
    // The JSON of the same run carries the same comparison.
    let json = serde_json::to_value(&st)?;
    let a = &st.scenarios[0];
    let p = json["scenarios"][0]["table8"]["ekf"]["mean"]["p"].as_f64();
    assert_eq!(p, Some(a.table8.ekf.mean.p));
    assert_eq!(
        json["scenarios"][0]["ranking"][0]["label"].as_str(),
        Some(a.ranking[0].label.as_str())
    );
    assert!(fresh.contains(&format!("{:.4}", a.table8.ekf.mean.median)));
    Ok(())
}
