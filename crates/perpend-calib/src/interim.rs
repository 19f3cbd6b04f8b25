//! The interim check record (`perpend.check/1`, issue 45): between two
//! calibrations, the board's stored calibration measured at a few fresh
//! poses (`perpend cell check`), decided against the tolerance with the
//! verification's own uncertainty ([`perpend_formats::conformity`]) and compared
//! with what the last calibration record verified.
//!
//! Verdict words: `in tolerance` (the decision is PASS), `recalibrate now`
//! (FAIL), `inconclusive` (with what would decide it). The comparison with
//! the last record is the difference of the mean errors over the poses
//! with its standard uncertainty (each mean's scatter over √poses, in
//! quadrature); it is `significant` beyond 2σ. A change that is
//! significant but within tolerance is a drift to watch, not a verdict.

use std::path::Path;

use anyhow::{anyhow, bail, Context as _, Result};
use serde::{Deserialize, Serialize};

use crate::record::{sha256_hex, FileHash};
use perpend_formats::conformity::{Decision, Verdict};

/// Value of the `schema` field.
pub const SCHEMA: &str = "perpend.check/1";

/// The calibration record a check compares with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Against {
    /// The record file and its SHA-256.
    pub record: FileHash,
    /// Its `utc`.
    pub utc: String,
    /// Its stamp's record hash (`null`: it carries none).
    pub stamp: Option<String>,
    /// The mean error it verified at fresh poses [deg].
    pub mean_deg: f64,
    /// That mean's standard uncertainty [deg] (pose scatter / √poses).
    pub mean_u_deg: f64,
}

/// The change against the last record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Change {
    /// Check mean − record mean [deg].
    pub diff_deg: f64,
    /// Its standard uncertainty [deg].
    pub u_deg: f64,
    /// |diff| > 2u.
    pub significant: bool,
}

/// An interim check.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CheckRecord {
    /// [`SCHEMA`].
    pub schema: String,
    /// When, ISO 8601 UTC.
    pub utc: String,
    /// The tool that made it.
    pub tool_version: String,
    /// The board's serial (0x1018 sub 4).
    pub head_serial: String,
    /// Its software version (0x100A).
    pub firmware: String,
    /// The stamp the board carries (0x2011 sub 1, 8 hex digits; `null`:
    /// none).
    pub board_stamp: Option<String>,
    /// The files the check rests on (plan, verify.csv, configuration).
    pub inputs: Vec<FileHash>,
    /// The last calibration record, when given.
    pub against: Option<Against>,
    /// Mean error over the poses [deg].
    pub mean_deg: f64,
    /// Its standard uncertainty [deg].
    pub mean_u_deg: f64,
    /// The decision against the tolerance.
    pub decision: Decision,
    /// The change against the last record.
    pub change: Option<Change>,
    /// `in tolerance`, `inconclusive` or `recalibrate now`.
    pub verdict: String,
    /// The verdict in a sentence with its figures.
    pub reason: String,
    /// What happened.
    pub events: Vec<String>,
}

/// The verdict words of a decision.
pub fn verdict_words(v: Verdict) -> &'static str {
    match v {
        Verdict::Pass => "in tolerance",
        Verdict::Fail => "recalibrate now",
        Verdict::Inconclusive => "inconclusive",
    }
}

/// Mean and its standard uncertainty (scatter / √n) of `x` (`None` when
/// empty; u = 0 for one value).
pub fn mean_u(x: &[f64]) -> Option<(f64, f64)> {
    let n = x.len();
    if n == 0 {
        return None;
    }
    let m = x.iter().sum::<f64>() / n as f64;
    if n == 1 {
        return Some((m, 0.0));
    }
    let var = x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (n - 1) as f64;
    Some((m, (var / n as f64).sqrt()))
}

/// The change of `mean ± u` against `a`.
pub fn change(mean: f64, u: f64, a: &Against) -> Change {
    let diff = mean - a.mean_deg;
    let uu = u.hypot(a.mean_u_deg);
    Change {
        diff_deg: diff,
        u_deg: uu,
        significant: diff.abs() > 2.0 * uu,
    }
}

impl CheckRecord {
    /// Parses a check record; `name` is the file named in errors.
    ///
    /// # Errors
    /// Syntax, unknown fields, another schema.
    pub fn parse(text: &str, name: &str) -> Result<Self> {
        let r: Self =
            serde_json::from_str(&perpend_formats::exchange::json_text(text)).map_err(|e| {
                anyhow!(
                    "{name}: line {}, column {}: {e} (an interim check record, {SCHEMA})",
                    e.line(),
                    e.column()
                )
            })?;
        if r.schema != SCHEMA {
            bail!("{name}: schema {:?}: expected {SCHEMA:?}", r.schema);
        }
        Ok(r)
    }

    /// Reads a check record.
    ///
    /// # Errors
    /// I/O and [`CheckRecord::parse`].
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Writes it (pretty JSON); returns the SHA-256 of what was written.
    ///
    /// # Errors
    /// I/O, naming the file.
    pub fn write(&self, path: &Path) -> Result<String> {
        let text = serde_json::to_string_pretty(self)? + "\n";
        std::fs::write(path, &text).with_context(|| format!("cannot write {}", path.display()))?;
        Ok(sha256_hex(text.as_bytes()))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn the_mean_and_its_change_carry_their_uncertainty() {
        let (m, u) = mean_u(&[0.01, 0.02, 0.03]).unwrap();
        assert!((m - 0.02).abs() < 1e-15);
        assert!((u - 0.01 / 3f64.sqrt()).abs() < 1e-15);
        assert_eq!(mean_u(&[]), None);
        assert_eq!(mean_u(&[0.5]), Some((0.5, 0.0)));
        let a = Against {
            record: FileHash {
                path: "r".into(),
                sha256: "0".repeat(64),
            },
            utc: "2026-01-01T00:00:00Z".into(),
            stamp: None,
            mean_deg: 0.02,
            mean_u_deg: 0.003,
        };
        let c = change(0.03, 0.004, &a);
        assert!((c.u_deg - 0.005).abs() < 1e-15);
        assert!(!c.significant);
        assert!(change(0.0311, 0.004, &a).significant);
        assert_eq!(verdict_words(Verdict::Fail), "recalibrate now");
    }
}
