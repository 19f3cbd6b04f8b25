//! Step 6 of a cell run: `DIR/record.json` (the calibration's record with
//! the run's outcome, board, stamp, previous calibration, verification,
//! decision, certificate fields and events) and `DIR/cert.html` or
//! `DIR/report.html`.

use std::path::PathBuf;

use anyhow::Result;

use super::args::RunArgs;
use super::figures::Figures;
use super::judge::{Outcome, Report};
use super::session::Session;

/// `DIR/record.json` of a run that calibrated: the calibration's record
/// (`params.record.json`, written by `perpend calibrate`) with the plan,
/// the verification file and the true head among its inputs, the
/// outcome, the board's serial, firmware and stamp, the board's previous
/// calibration (`previous.json`) as `previous`, the verification at the
/// fresh poses after the push and its decision (when the run got that
/// far), the certificate's fields and what the run did as events. Then
/// `DIR/cert.html` when the calibration is applied and verified, else
/// `DIR/report.html` (marked: no certificate). A run that stopped before it
/// calibrated has nothing to record (cell.json says why).
pub(super) fn write_record(
    a: &RunArgs,
    s: &Session<'_>,
    report: &Report,
) -> Result<Option<PathBuf>> {
    use perpend_calib::record::{self as rec, FileHash, Previous, Record};
    let params = a.out.join("params.json");
    if !params.exists() {
        return Ok(None);
    }
    let beside = rec::record_path(&params);
    let mut r = if beside.exists() {
        Record::read(&beside)?
    } else {
        let file = perpend_formats::paramfile::ParamFile::read(&params)?;
        Record::new(&[&a.sensors, &a.out.join("poses.csv")], &file)?
    };
    let csv = a.out.join("verify.csv");
    for f in [
        Some(&a.plan),
        Some(&csv).filter(|c| c.exists()),
        a.truth.as_ref(),
    ]
    .into_iter()
    .flatten()
    {
        r.inputs.push(FileHash::of(f)?);
    }
    r = super::frames::into_record(r, &a.out, &params)?;
    r = r
        .with_board(&s.serial, &s.firmware)
        .with_previous(Previous::of(&s.previous)?);
    r.outcome = Some(report.outcome.word().into());
    // The stamp the run last wrote: on the board when applied, perhaps
    // still there when the board's state is unknown (said as such).
    if matches!(report.outcome, Outcome::Applied | Outcome::FailedUnknown) {
        r.stamp = s.stamp.clone();
    }
    if let Some(f) = &report.figures {
        r = r.with_verification(fresh_verification(f, a));
        r.decision = Some(f.decision.clone());
    } else if report.before_deg.is_some() {
        // A run that failed after its before pass: what the board was
        // found at is kept; the after pass did not happen.
        r.verification.before_mean_deg = report.before_deg;
    }
    r.certification = Some(certification(s, &r.utc));
    let certifiable = r.is_certifiable();
    if let Some(c) = r.certification.as_mut() {
        c.simulated = a.m.simulated();
        if certifiable {
            c.issued_utc = Some(perpend_calib::record::utc_now());
        } else {
            c.number = None;
        }
    }
    if let Some(c) = &report.first_cause {
        r.push_event(&format!("first cause: {c}"));
    }
    if let Some(st) = &s.stamp {
        r.push_event(&format!(
            "pushed: written, stored (0x1010), reset, read back identical; stamp {} stored {}, \
             store #{}",
            st.record_hash, st.utc, st.store_count
        ));
    }
    r.push_event(&format!(
        "perpend cell run: {}: {}",
        report.outcome.word(),
        report.reason
    ));
    for d in &report.restored {
        r.push_event(&format!("put back: {d}"));
    }
    for p in &report.problems {
        r.push_event(&format!("not put back: {p}"));
    }
    let path = a.out.join("record.json");
    r.write(&path)?;
    crate::record::write_document(&r, &a.out)?;
    Ok(Some(path))
}

/// The certificate's fields of this run: the configuration's (or what
/// stands for it), the number, the die temperatures.
fn certification(s: &Session<'_>, utc: &str) -> perpend_calib::record::Certification {
    let cfg = s.reference.config.as_ref();
    let given = |f: fn(&perpend_calib::cellconfig::CellConfig) -> &String| {
        cfg.map_or_else(
            || "not given (no --config)".to_string(),
            |c| f(&c.0).clone(),
        )
    };
    let stamp: String = utc.chars().filter(|c| c.is_ascii_alphanumeric()).collect();
    perpend_calib::record::Certification {
        number: Some(format!(
            "PPD-{}-{stamp}",
            s.serial.trim_start_matches("0x").to_uppercase()
        )),
        operator: given(|c| &c.operator),
        approver: given(|c| &c.approver),
        site: given(|c| &c.site),
        laboratory: Some(given(|c| &c.laboratory)),
        customer: cfg.and_then(|c| c.0.customer.clone()),
        tracker: s.reference.tracker.clone(),
        die_temp_c: s.die_temp_c,
        ambient_c: cfg.and_then(|c| c.0.ambient_c),
        config: cfg.map(|c| c.1.clone()),
        performed_utc: Some([s.started_utc.clone(), perpend_calib::record::utc_now()]),
        simulated: false,
        issued_utc: None,
    }
}

/// The after pass as the record's verification: each fresh pose's error,
/// against the calibration's expected error, with the before figure.
fn fresh_verification(f: &Figures, a: &RunArgs) -> perpend_calib::record::Verification {
    use perpend_calib::record::{PoseError, Verification, KIND_FRESH};
    let poses = f
        .decision
        .poses
        .iter()
        .map(|p| PoseError {
            pose: p.pose,
            error_deg: p.error_deg,
        })
        .collect();
    let note = format!(
        "the board's own normal (θ1/θ2 from its TPDO, averaged over {} samples a pose, after \
         the push and reset) against the tracker's plane at {} fresh poses inside the plan's \
         reach (seed {}; planes and normals in verify.csv); before the calibration {:.4}°, the \
         floor ({} head at the measured reading noise) {:.4}°",
        f.verify_samples,
        f.verify_poses,
        a.seed(),
        f.before_deg,
        f.floor_head,
        f.floor_deg
    );
    let mut v = Verification::from_errors(KIND_FRESH, &note, poses)
        .with_expected(Some((f.expected_deg, f.expected_p95_deg)));
    v.before_mean_deg = Some(f.before_deg);
    v
}
