//! The calibration record (`perpend.record/1`, issue 30): a versioned JSON
//! file written beside every parameter file, `params.json` →
//! `params.record.json`, that makes a calibration traceable: when, by
//! which build, from which files (SHA-256), for which head and firmware,
//! with which method and model, the parameters with 1σ and identifiability
//! (the parameter file's own [`SensorParams`], not recomputed), the poses
//! left out and why, the verification, the file it replaced, and a list of
//! events the cell run appends to. The schema is documented in
//! `docs/record.md`.
//!
//! The API the cell run and `perpend node push` use: [`Record::new`],
//! [`Record::with_board`], [`Record::with_verification`],
//! [`Record::push_event`], [`Record::hash`], [`Record::write_beside`],
//! [`Record::read`], [`Previous::of`], [`FileHash::of`].
//!
//! Limits: the record is written after the parameter file, not atomically
//! with it; [`Record::hash`] is the SHA-256 of the compact serde_json
//! serialisation (fields in declaration order; floats round-trip), so a
//! record read back hashes as written, but a record edited by hand and
//! re-indented does not change its hash while a changed value does.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use perpend_formats::paramfile::{ParamFile, SensorParams};

/// Value of the `schema` field.
pub const SCHEMA: &str = "perpend.record/2";
/// The schema before outcomes, stamps and decisions (read, never written).
pub const SCHEMA_V1: &str = "perpend.record/1";

/// `outcome`: the calibration is on the board and was verified there.
pub const OUTCOME_APPLIED: &str = "applied";
/// `outcome`: it was pushed, then the previous one was pushed back.
pub const OUTCOME_REVERTED: &str = "reverted";
/// `outcome`: the run failed; the board holds its previous calibration.
pub const OUTCOME_FAILED_RESTORED: &str = "failed, restored";
/// `outcome`: the run failed and what the board holds is not known.
pub const OUTCOME_FAILED_UNKNOWN: &str = "failed, board state unknown";
/// `outcome`: parameters computed from files (`calibrate`, `diagnose`),
/// applied to no board by this record.
pub const OUTCOME_COMPUTED: &str = "computed";

/// `verification.kind`: held-out poses of a k-fold cross-validation by pose.
pub const KIND_CROSS_VALIDATED: &str = "cross-validated";
/// `verification.kind`: fresh poses measured after the calibration.
pub const KIND_FRESH: &str = "fresh poses";
/// `verification.kind`: no verification, only the predicted accuracy.
pub const KIND_EXPECTED_ONLY: &str = "expected only";

/// The version of the tool that wrote a record: crate version and the git
/// commit it was built from (`unknown` outside a checkout).
pub fn tool_version() -> String {
    format!("perpend {VERSION}")
}

/// The version `perpend --version` prints after the name, the same as in
/// [`tool_version`]: crate version and git commit.
pub const VERSION: &str = concat!(
    env!("CARGO_PKG_VERSION"),
    " (",
    env!("PERPEND_GIT_HASH"),
    ")"
);

/// Lower-case hex SHA-256 of `bytes`.
pub fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The current time as ISO 8601 UTC, to the second (`2026-01-31T12:00:00Z`).
pub fn utc_now() -> String {
    humantime::format_rfc3339_seconds(std::time::SystemTime::now()).to_string()
}

/// A file and its SHA-256.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileHash {
    /// The path as given on the command line.
    pub path: String,
    /// SHA-256 of its bytes, lower-case hex.
    pub sha256: String,
}

impl FileHash {
    /// Reads `path` and hashes it.
    ///
    /// # Errors
    /// The file cannot be read (message names it).
    pub fn of(path: &Path) -> Result<Self> {
        let bytes =
            std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
        Ok(Self {
            path: path.display().to_string(),
            sha256: sha256_hex(&bytes),
        })
    }
}

/// A pose left out of the calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Dropped {
    /// Pose number (the `pose` column).
    pub pose: i64,
    /// Why it was left out.
    pub reason: String,
    /// Size of the miss: RMS of its residuals under the paper's model
    /// fitted on the other poses [mm].
    pub residual_mm: f64,
}

/// Reason given for poses that disagree with every model.
pub const REASON_OUTLIER: &str =
    "disagrees with every model (tracker blunder, spatter); --keep-outliers keeps it";

impl From<&crate::noise::Outlier> for Dropped {
    fn from(o: &crate::noise::Outlier) -> Self {
        Self {
            pose: o.pose,
            reason: REASON_OUTLIER.into(),
            residual_mm: o.residual_mm,
        }
    }
}

/// The normal error of one verification pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseError {
    /// Pose number.
    pub pose: i64,
    /// Angle between the measured and the true normal [deg].
    pub error_deg: f64,
}

/// How well the calibration measures normals.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Verification {
    /// [`KIND_CROSS_VALIDATED`], [`KIND_FRESH`] or [`KIND_EXPECTED_ONLY`].
    pub kind: String,
    /// How the figures were obtained, in words.
    pub note: String,
    /// Mean normal error over `poses` [deg] (`null`: not verified).
    pub mean_deg: Option<f64>,
    /// 95th percentile (nearest rank) [deg].
    pub p95_deg: Option<f64>,
    /// Largest [deg].
    pub max_deg: Option<f64>,
    /// Per pose (empty: not verified).
    pub poses: Vec<PoseError>,
    /// The calibration's own predicted accuracy: RMS normal error from the
    /// parameters' uncertainty [deg] (`null`: not computed, e.g. EKF).
    pub expected_deg: Option<f64>,
    /// Its 95th percentile [deg].
    pub expected_p95_deg: Option<f64>,
    /// The same fresh poses' mean normal error before the calibration
    /// [deg] (cell runs; absent otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub before_mean_deg: Option<f64>,
}

/// The 95th percentile by nearest rank of `x` (`None` when empty).
pub fn p95(x: &[f64]) -> Option<f64> {
    let mut v: Vec<f64> = x.iter().copied().filter(|e| e.is_finite()).collect();
    v.sort_by(f64::total_cmp);
    let rank = ((0.95 * v.len() as f64).ceil() as usize).max(1);
    v.get(rank - 1).copied()
}

impl Verification {
    /// Figures from per-pose errors (non-finite errors are dropped).
    pub fn from_errors(kind: &str, note: &str, poses: Vec<PoseError>) -> Self {
        let poses: Vec<PoseError> = poses
            .into_iter()
            .filter(|p| p.error_deg.is_finite())
            .collect();
        let e: Vec<f64> = poses.iter().map(|p| p.error_deg).collect();
        let n = e.len();
        Self {
            kind: kind.into(),
            note: note.into(),
            mean_deg: (n > 0).then(|| e.iter().sum::<f64>() / n as f64),
            p95_deg: p95(&e),
            max_deg: e.iter().copied().reduce(f64::max),
            poses,
            expected_deg: None,
            expected_p95_deg: None,
            before_mean_deg: None,
        }
    }

    /// No verification: only the predicted accuracy (if any).
    pub fn expected_only(note: &str) -> Self {
        Self::from_errors(KIND_EXPECTED_ONLY, note, Vec::new())
    }

    /// Adds the calibration's predicted accuracy [deg] (RMS, 95 %).
    pub fn with_expected(mut self, expected: Option<(f64, f64)>) -> Self {
        self.expected_deg = expected.map(|e| e.0);
        self.expected_p95_deg = expected.map(|e| e.1);
        self
    }

    /// Whether there are verified figures (not "expected only").
    pub fn is_verified(&self) -> bool {
        self.kind != KIND_EXPECTED_ONLY && self.p95_deg.is_some()
    }
}

/// What a calibration replaced.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Previous {
    /// SHA-256 of the parameter file overwritten.
    pub params_sha256: String,
    /// [`Record::hash`] of the record that was beside it (`null`: none,
    /// or unreadable: then `record_file_sha256` is set).
    pub record_hash: Option<String>,
    /// SHA-256 of that record file's bytes.
    pub record_file_sha256: Option<String>,
    /// The `utc` of that record.
    pub record_utc: Option<String>,
    /// The stamp the board carried when its calibration was pulled (a
    /// pulled file's `calibration_stamp`): the previous record's
    /// [`BoardStamp::record_hash`], so records chain board by board
    /// (`record find`, `record history`). Absent: no stamp on the board,
    /// or a file that was not pulled.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub board_stamp: Option<perpend_formats::paramfile::CalibrationStamp>,
}

impl Previous {
    /// What writing parameters to `params` would replace: `None` when no
    /// file is there. Call before writing.
    ///
    /// # Errors
    /// A file that exists but cannot be read.
    pub fn of(params: &Path) -> Result<Option<Self>> {
        if !params.exists() {
            return Ok(None);
        }
        let p = FileHash::of(params)?;
        let rec = record_path(params);
        let (mut record_hash, mut record_file_sha256, mut record_utc) = (None, None, None);
        if rec.exists() {
            record_file_sha256 = Some(FileHash::of(&rec)?.sha256);
            if let Ok(r) = Record::read(&rec) {
                record_hash = r.hash().ok();
                record_utc = Some(r.utc);
            }
        }
        // The stamp of a pulled file; a file that does not read as
        // parameters still has its hash above.
        let board_stamp = perpend_formats::paramfile::ParamFile::read(params)
            .ok()
            .and_then(|f| f.calibration_stamp);
        Ok(Some(Self {
            params_sha256: p.sha256,
            record_hash,
            record_file_sha256,
            record_utc,
            board_stamp,
        }))
    }
}

/// The calibration stamp the board carries after the push (0x2011,
/// docs/can.md): it leads from a board on the line to this record
/// (`perpend record find STAMP`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoardStamp {
    /// Sub 1: the first 4 bytes of the stamped record file's SHA-256, as
    /// `node info` prints them (8 hex digits).
    pub record_hash: String,
    /// The record file whose hash it is (the calibration's
    /// `params.record.json`, written before the push), with its SHA-256.
    pub stamped_record: FileHash,
    /// Sub 2: when it was stamped, ISO 8601 UTC.
    pub utc: String,
    /// Sub 3: the board's store count after the push.
    pub store_count: u32,
}

/// The reference standard: the tracker that measured the datum planes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Tracker {
    /// Make and model.
    pub model: String,
    /// Serial number.
    pub serial: String,
    /// When its own calibration falls due (ISO 8601 date).
    pub calibration_due: String,
    /// Its traceability (calibration certificate and laboratory).
    pub traceability: String,
    /// Point noise ξ, 1σ per coordinate [mm].
    pub xi_mm: f64,
    /// Points measured per datum plane.
    pub points: usize,
    /// Side of the patch the points are spread over [mm].
    pub patch_mm: f64,
}

/// What a certificate states beyond the calibration (ISO/IEC 17025:2017
/// §7.8.2 and §7.8.4): its number, who, where, the reference standard,
/// the environment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Certification {
    /// Unique certificate number, `PPD-<head serial>-<UTC of the record>`
    /// (`null`: no certificate was issued for this record).
    pub number: Option<String>,
    /// Who calibrated.
    pub operator: String,
    /// Who approves (name only; the signature is on paper).
    pub approver: String,
    /// Where (site, cell).
    pub site: String,
    /// The laboratory's name and address (absent in records written
    /// before it was kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub laboratory: Option<String>,
    /// The customer (absent: in-house, or not kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub customer: Option<String>,
    /// The reference standard.
    pub tracker: Tracker,
    /// The board's die temperature at the start and end of the run [°C]
    /// (`null`: not measured).
    pub die_temp_c: [Option<f64>; 2],
    /// The cell's air temperature as the configuration states it [°C].
    pub ambient_c: Option<f64>,
    /// The configuration file the fields came from, with its SHA-256
    /// (`null`: none given, the defaults stated).
    pub config: Option<FileHash>,
    /// When the calibration was performed, ISO 8601 UTC: the cell run's
    /// start (the board's calibration pulled) and end (the record
    /// written, after the verification). The record's `utc` is when the
    /// parameters were fitted, inside this span. Absent in records
    /// written before it was kept.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub performed_utc: Option<[String; 2]>,
    /// The planes were measured by a simulated tracker on a virtual
    /// board (`--robot sim:`): its certificate says so on every page and
    /// is no certificate of a real head.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub simulated: bool,
    /// When the certificate was first issued (ISO 8601 UTC); a later
    /// `record cert` prints a copy that says so.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub issued_utc: Option<String>,
}

/// The calibration record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Record {
    /// [`SCHEMA`].
    pub schema: String,
    /// When the calibration was made, ISO 8601 UTC.
    pub utc: String,
    /// [`tool_version`].
    pub tool_version: String,
    /// How it ended: [`OUTCOME_APPLIED`], [`OUTCOME_REVERTED`],
    /// [`OUTCOME_FAILED_RESTORED`], [`OUTCOME_FAILED_UNKNOWN`] or
    /// [`OUTCOME_COMPUTED`] (`null`: a `perpend.record/1` record).
    #[serde(default)]
    pub outcome: Option<String>,
    /// The files calibrated from, with their SHA-256.
    pub inputs: Vec<FileHash>,
    /// The parameter file this record describes, with its SHA-256.
    pub output: Option<FileHash>,
    /// Serial number of the head's board (`null`: no board involved).
    pub head_serial: Option<String>,
    /// Firmware version of that board.
    pub firmware: Option<String>,
    /// Estimator (`lsq`, `ekf`).
    pub method: String,
    /// Reading model (`base` or an extension's name).
    pub model: String,
    /// Poses the parameters were fitted on.
    pub poses_used: usize,
    /// Per sensor, as in the parameter file: values, correction, 1σ,
    /// residual RMS, identifiability.
    pub parameters: Vec<SensorParams>,
    /// Poses left out, with reason and size of the miss.
    pub dropped_poses: Vec<Dropped>,
    /// Verification of the normals.
    pub verification: Verification,
    /// What this calibration replaced (`null`: nothing was overwritten).
    pub previous: Option<Previous>,
    /// What happened, in order (the cell run appends).
    pub events: Vec<String>,
    /// The cell's frame errors estimated with the head (`cell run
    /// --reversal`, issue 36; absent otherwise, so older records read).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames: Option<crate::frames::report::FrameEstimates>,
    /// The stamp the board carries (cell runs that applied it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stamp: Option<BoardStamp>,
    /// The verification's decision against the tolerance (cell runs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub decision: Option<perpend_formats::conformity::Decision>,
    /// Certificate fields (cell runs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub certification: Option<Certification>,
}

/// The record path beside a parameter file: `dir/params.json` →
/// `dir/params.record.json` (`params` → `params.record.json`).
pub fn record_path(params: &Path) -> PathBuf {
    let stem = params
        .file_stem()
        .map_or_else(|| "params".into(), |s| s.to_string_lossy().into_owned());
    params.with_file_name(format!("{stem}.record.json"))
}

impl Record {
    /// A record of the calibration `file` computed from `inputs` (hashed
    /// now), stamped with the current time and this build; not verified,
    /// no board, nothing replaced, no events.
    ///
    /// # Errors
    /// An input that cannot be read.
    pub fn new(inputs: &[&Path], file: &ParamFile) -> Result<Self> {
        Ok(Self {
            schema: SCHEMA.into(),
            utc: utc_now(),
            tool_version: tool_version(),
            outcome: Some(OUTCOME_COMPUTED.into()),
            inputs: inputs
                .iter()
                .map(|p| FileHash::of(p))
                .collect::<Result<_>>()?,
            output: None,
            head_serial: None,
            firmware: None,
            method: file.method.clone(),
            model: file.model.clone(),
            poses_used: file.poses,
            parameters: file.sensors.clone(),
            dropped_poses: Vec::new(),
            verification: Verification::expected_only("not verified"),
            previous: None,
            events: Vec::new(),
            frames: None,
            stamp: None,
            decision: None,
            certification: None,
        })
    }

    /// The frame errors estimated with the head.
    pub fn with_frames(mut self, f: crate::frames::report::FrameEstimates) -> Self {
        self.frames = Some(f);
        self
    }

    /// The board the head was calibrated on.
    pub fn with_board(mut self, serial: &str, firmware: &str) -> Self {
        self.head_serial = Some(serial.into());
        self.firmware = Some(firmware.into());
        self
    }

    /// Replaces the verification.
    pub fn with_verification(mut self, v: Verification) -> Self {
        self.verification = v;
        self
    }

    /// Sets the poses left out.
    pub fn with_dropped(mut self, d: Vec<Dropped>) -> Self {
        self.dropped_poses = d;
        self
    }

    /// Sets what the calibration replaced.
    pub fn with_previous(mut self, p: Option<Previous>) -> Self {
        self.previous = p;
        self
    }

    /// Appends an event (prefixed with the current UTC time).
    pub fn push_event(&mut self, what: &str) {
        self.events.push(format!("{} {what}", utc_now()));
    }

    /// SHA-256 (hex) of the record's canonical bytes: the compact JSON
    /// serialisation, fields in declaration order.
    ///
    /// # Errors
    /// A value JSON cannot hold (non-finite number).
    pub fn hash(&self) -> Result<String> {
        Ok(sha256_hex(&serde_json::to_vec(self)?))
    }

    /// Checks the schema and the figures a reader relies on.
    ///
    /// # Errors
    /// The field and the problem.
    pub fn validate(&self) -> Result<()> {
        if self.schema != SCHEMA && self.schema != SCHEMA_V1 {
            bail!(
                "schema = {:?}: this tool reads {SCHEMA:?} records (a newer tool wrote it?)",
                self.schema
            );
        }
        humantime::parse_rfc3339_weak(&self.utc).map_err(|e| {
            anyhow::anyhow!(
                "utc = {:?}: not an ISO 8601 time ({e}); write e.g. 2026-01-31T12:00:00Z",
                self.utc
            )
        })?;
        for f in self.inputs.iter().chain(&self.output) {
            if f.sha256.len() != 64 || !f.sha256.bytes().all(|b| b.is_ascii_hexdigit()) {
                bail!("{}: sha256 {:?} is not 64 hex digits", f.path, f.sha256);
            }
        }
        Ok(())
    }

    /// Parses a record; `name` is the file named in errors.
    ///
    /// # Errors
    /// Syntax (with line and column), unknown or missing fields, wrong
    /// schema.
    pub fn parse(text: &str, name: &str) -> Result<Self> {
        let json = perpend_formats::exchange::json_text(text);
        if let Ok(v) = serde_json::from_str::<serde_json::Value>(&json) {
            match v.get("schema").and_then(|s| s.as_str()) {
                Some(s) if !s.starts_with("perpend.record/") && s.starts_with("perpend.") => bail!(
                    "{name}: a {s} file, not a calibration record ({SCHEMA}): a cell run's \
                     record is record.json beside its cell.json"
                ),
                _ => {}
            }
        }
        let r: Self =
            serde_json::from_str(&perpend_formats::exchange::json_text(text)).map_err(|e| {
                anyhow::anyhow!(
                "{name}: line {}, column {}: {e} (a calibration record, {SCHEMA}: docs/record.md)",
                e.line(),
                e.column()
            )
            })?;
        r.validate().with_context(|| name.to_string())?;
        Ok(r)
    }

    /// Reads a record file.
    ///
    /// # Errors
    /// I/O and [`Record::parse`] errors, naming the file.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Whether this record describes a calibration applied to a board and
    /// verified there (fresh poses, decided against a tolerance: PASS,
    /// INCONCLUSIVE, or FAIL kept with `--keep-worse`, each stated), with
    /// its reference standard named by a cell configuration: the only kind
    /// a certificate is issued for.
    pub fn is_certifiable(&self) -> bool {
        self.outcome.as_deref() == Some(OUTCOME_APPLIED)
            && self.verification.kind == KIND_FRESH
            && self.verification.is_verified()
            && self
                .decision
                .as_ref()
                .is_some_and(|d| d.verdict == perpend_formats::conformity::Verdict::Pass)
            && self.frame_beyond_tolerance().is_none()
            && self
                .certification
                .as_ref()
                .is_some_and(|c| c.config.is_some())
    }

    /// A significant frame error of the reference (a tracker tilt) larger
    /// than the decision's tolerance, in words: the tracker's planes the
    /// verification rests on are then off by more than what it decides.
    pub fn frame_beyond_tolerance(&self) -> Option<String> {
        let tol = self.decision.as_ref()?.tolerance_deg;
        self.frames.as_ref()?.errors.iter().find_map(|e| {
            let (v, sd) = (e.value?, e.sigma.unwrap_or(0.0));
            let deg = (v.abs() * 1e-6).to_degrees();
            (e.significant && e.unit == "µrad" && deg > tol).then(|| {
                format!(
                    "{} = {v:.0} ± {sd:.0} µrad ({deg:.4}°) is beyond the tolerance {tol}°: \
                     the reference is mis-registered; re-register the tracker and run again",
                    e.name
                )
            })
        })
    }

    /// The outcome in words, for people.
    pub fn outcome_words(&self) -> &str {
        self.outcome
            .as_deref()
            .unwrap_or("not recorded (a perpend.record/1 record, written before outcomes)")
    }

    /// Writes the record (pretty JSON) to `path`.
    ///
    /// # Errors
    /// I/O (naming the file), non-finite numbers.
    pub fn write(&self, path: &Path) -> Result<()> {
        let text = serde_json::to_string_pretty(self)? + "\n";
        std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))
    }

    /// Writes the record beside the parameter file `params` ([`record_path`]),
    /// with `output` set to that file and its current hash; returns the
    /// record's path.
    ///
    /// # Errors
    /// `params` unreadable, I/O.
    pub fn write_beside(&mut self, params: &Path) -> Result<PathBuf> {
        self.output = Some(FileHash::of(params)?);
        let path = record_path(params);
        self.write(&path)?;
        Ok(path)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn sha256_of_abc_is_the_standard_vector() {
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }

    #[test]
    fn record_path_sits_beside_the_params() {
        assert_eq!(
            record_path(Path::new("d/params.json")),
            Path::new("d/params.record.json")
        );
        assert_eq!(
            record_path(Path::new("params")),
            Path::new("params.record.json")
        );
    }

    #[test]
    fn p95_is_nearest_rank() {
        let x: Vec<f64> = (1..=20).map(f64::from).collect();
        assert_eq!(p95(&x), Some(19.0));
        assert_eq!(p95(&[3.0]), Some(3.0));
        assert_eq!(p95(&[]), None);
    }

    #[test]
    fn parse_errors_name_the_file_and_line() {
        let e = Record::parse("{\n \"schema\": 3 }", "x.record.json").unwrap_err();
        let s = format!("{e:#}");
        assert!(s.contains("x.record.json") && s.contains("line 2"), "{s}");
    }
}
