//! The calibration record (`perpend.record/2`): `calibrate --out` writes
//! one beside the parameters whose every field reads back as the run made
//! it, a second `--out` names the first as `previous`, and the example in
//! docs/record.md parses as a record.
#![allow(clippy::unwrap_used, missing_docs)]

use clap::Parser;
use perpend_calib::record::{record_path, sha256_hex, Record, KIND_CROSS_VALIDATED, SCHEMA};
use perpend_formats::paramfile::ParamFile;

#[derive(Parser)]
struct Sim {
    #[command(flatten)]
    a: perpend_calib::sim::Args,
}

#[derive(Parser)]
struct Cal {
    #[command(flatten)]
    a: perpend_calib::calibrate::Args,
}

fn doc_example() -> String {
    let doc = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../docs/record.md"))
        .unwrap();
    let start = doc.find("```json\n").unwrap() + 8;
    let end = start + doc[start..].find("```").unwrap();
    doc[start..end].to_string()
}

#[test]
fn the_example_in_the_doc_is_a_record() {
    let r = Record::parse(&doc_example(), "docs/record.md").unwrap();
    assert_eq!(r.schema, SCHEMA);
    assert_eq!(r.parameters.len(), 4);
    assert_eq!(r.verification.kind, KIND_CROSS_VALIDATED);
    assert!(!r.verification.poses.is_empty());
    // The hash is of the canonical bytes: a record read back hashes as written.
    let again = Record::parse(&serde_json::to_string_pretty(&r).unwrap(), "x").unwrap();
    assert_eq!(again.hash().unwrap(), r.hash().unwrap());
}

#[test]
fn calibrate_out_writes_a_record_that_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let sim = Sim::parse_from(["sim", "--out", d.to_str().unwrap(), "--poses", "60"]);
    perpend_calib::sim::run(&sim.a).unwrap();
    let (s, p, out) = (
        d.join("sensors.csv"),
        d.join("poses.csv"),
        d.join("params.json"),
    );
    let args = [
        "cal",
        "--sensors",
        s.to_str().unwrap(),
        "--poses",
        p.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    perpend_calib::calibrate::run(&Cal::parse_from(args).a).unwrap();
    let rp = record_path(&out);
    let r = Record::read(&rp).unwrap();
    let file = ParamFile::read(&out).unwrap();
    assert_eq!(r.schema, SCHEMA);
    assert!(humantime::parse_rfc3339(&r.utc).is_ok(), "{}", r.utc);
    assert!(r
        .tool_version
        .starts_with(&format!("perpend {}", env!("CARGO_PKG_VERSION"))));
    assert_eq!(r.inputs.len(), 2);
    for (f, path) in r.inputs.iter().zip([&s, &p]) {
        assert_eq!(f.path, path.display().to_string());
        assert_eq!(f.sha256, sha256_hex(&std::fs::read(path).unwrap()));
    }
    let o = r.output.as_ref().unwrap();
    assert_eq!(o.sha256, sha256_hex(&std::fs::read(&out).unwrap()));
    assert_eq!((r.head_serial.as_ref(), r.firmware.as_ref()), (None, None));
    assert_eq!((r.method.as_str(), r.model.as_str()), ("lsq", "base"));
    assert_eq!(r.poses_used, file.poses);
    assert_eq!(r.parameters, file.sensors);
    assert!(r
        .parameters
        .iter()
        .all(|p| p.sigma.is_some() && p.identifiability.is_some()));
    assert!(r.dropped_poses.is_empty());
    let v = &r.verification;
    assert_eq!(v.kind, KIND_CROSS_VALIDATED);
    assert_eq!(v.poses.len(), file.poses);
    let e: Vec<f64> = v.poses.iter().map(|p| p.error_deg).collect();
    let mean = e.iter().sum::<f64>() / e.len() as f64;
    assert!((v.mean_deg.unwrap() - mean).abs() < 1e-12);
    assert_eq!(v.max_deg, e.iter().copied().reduce(f64::max));
    assert!(v.p95_deg.unwrap() <= v.max_deg.unwrap());
    assert!(v.expected_deg.unwrap() > 0.0 && v.expected_p95_deg.unwrap() > 0.0);
    assert!(r.previous.is_none());
    assert_eq!(r.events.len(), 1);
    // A second calibration over the same file names what it replaced.
    let first_hash = r.hash().unwrap();
    let first_params = o.sha256.clone();
    perpend_calib::calibrate::run(&Cal::parse_from(args).a).unwrap();
    let r2 = Record::read(&rp).unwrap();
    let prev = r2.previous.unwrap();
    assert_eq!(prev.params_sha256, first_params);
    assert_eq!(prev.record_hash.unwrap(), first_hash);
    assert_eq!(prev.record_utc.unwrap(), r.utc);
}

#[test]
fn read_names_the_file_on_a_wrong_schema() {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("bad.record.json");
    let text = doc_example().replace("perpend.record/2", "perpend.record/9");
    std::fs::write(&f, text).unwrap();
    let e = format!("{:#}", Record::read(&f).unwrap_err());
    assert!(e.contains("bad.record.json") && e.contains("schema"), "{e}");
}
