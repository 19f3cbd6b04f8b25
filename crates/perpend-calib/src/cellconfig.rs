//! The cell configuration (`perpend.cell-config/1`, docs/record.md): what
//! a certificate states beyond the calibration and what the operator
//! would otherwise type at every run: the laboratory's name and address,
//! the customer (if any), site, operator, approver, the
//! tolerance, the cell's air temperature, and the reference standard (the
//! laser tracker: model, serial, calibration due date, traceability and
//! the point noise, count and patch its plane uncertainty follows from,
//! [`perpend_formats::conformity::tracker_u_rad`]).
//!
//! Every figure is checked by physics where it is read: a tolerance
//! outside (0, 5]°, a point noise that looks like micrometres, a patch
//! smaller than a hand, a due date that has passed (the reference
//! standard is out of calibration: no certificate can rest on it) are
//! refused with the field and the fix.

use std::path::Path;

use anyhow::{anyhow, bail, Context as _, Result};
use serde::Deserialize;

use crate::record::{FileHash, Tracker};

/// Value of the `schema` field.
pub const SCHEMA: &str = "perpend.cell-config/1";

/// The tracker of Chen et al. 2018 §5 (20 points, ξ = 0.02 mm, a 150 mm
/// patch: [`crate::sim::Tracker::paper`]), stated when no configuration
/// names one.
pub fn paper_tracker(what: &str) -> Tracker {
    let t = crate::sim::Tracker::paper();
    Tracker {
        model: what.into(),
        serial: "not given".into(),
        calibration_due: "not given".into(),
        traceability: "not given".into(),
        xi_mm: t.xi_mm,
        points: t.points,
        patch_mm: t.patch_mm,
    }
}

/// The configuration as read.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CellConfig {
    /// [`SCHEMA`].
    pub schema: String,
    /// The calibrating laboratory: its name and address (ISO/IEC 17025
    /// §7.8.2.1 b), on every certificate.
    pub laboratory: String,
    /// The customer, when the head is calibrated for another party
    /// (absent: in-house).
    #[serde(default)]
    pub customer: Option<String>,
    /// Site and cell.
    pub site: String,
    /// Who calibrates.
    pub operator: String,
    /// Who approves certificates.
    pub approver: String,
    /// Maximum permissible normal error [deg].
    pub tolerance_deg: f64,
    /// The cell's air temperature [°C], if measured.
    #[serde(default)]
    pub ambient_c: Option<f64>,
    /// The reference standard.
    pub tracker: Tracker,
}

impl CellConfig {
    /// Reads and checks a configuration file; also its hash.
    ///
    /// # Errors
    /// Unreadable file, syntax (line, column), a field out of its physics.
    pub fn read(path: &Path) -> Result<(Self, FileHash)> {
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).with_context(|| format!("{name}: cannot read"))?;
        Ok((Self::parse(&text, &name)?, FileHash::of(path)?))
    }

    /// Parses and checks a configuration; `name` is the file named in
    /// errors.
    ///
    /// # Errors
    /// Syntax (line, column), a field out of its physics.
    pub fn parse(text: &str, name: &str) -> Result<Self> {
        let c: Self =
            serde_json::from_str(&perpend_formats::exchange::json_text(text)).map_err(|e| {
                anyhow!(
                "{name}: line {}, column {}: {e} (a cell configuration, {SCHEMA}: docs/record.md)",
                e.line(),
                e.column()
            )
            })?;
        c.check().with_context(|| name.to_string())?;
        Ok(c)
    }

    /// The physics checks of [`CellConfig::read`], against today's date.
    ///
    /// # Errors
    /// The field and the fix.
    pub fn check(&self) -> Result<()> {
        if self.schema != SCHEMA {
            bail!("schema = {:?}: expected {SCHEMA:?}", self.schema);
        }
        check_tolerance(self.tolerance_deg)?;
        let t = &self.tracker;
        for (field, v) in [
            ("laboratory", &self.laboratory),
            ("site", &self.site),
            ("operator", &self.operator),
            ("approver", &self.approver),
            ("tracker.model", &t.model),
            ("tracker.serial", &t.serial),
            ("tracker.traceability", &t.traceability),
        ] {
            if v.trim().is_empty() {
                bail!("{field} is empty: a certificate names it");
            }
        }
        if self.customer.as_ref().is_some_and(|c| c.trim().is_empty()) {
            bail!("customer is empty: name the customer, or leave the field out (in-house)");
        }
        if self.operator.trim() == self.approver.trim() {
            bail!(
                "operator and approver are both {:?}: the approver checks the operator's work, \
                 name another person",
                self.operator
            );
        }
        if let Some(t) = self.ambient_c {
            if !(-10.0..=60.0).contains(&t) {
                bail!("ambient_c = {t}: not an air temperature of a cell in °C (-10 to 60)");
            }
        }
        check_tracker(&self.tracker, std::time::SystemTime::now())
    }
}

/// A tolerance [deg] a cell can verify: in (0, 5].
///
/// # Errors
/// Outside that range, with the reason.
pub fn check_tolerance(t: f64) -> Result<()> {
    if !(t.is_finite() && t > 0.0 && t <= 5.0) {
        bail!(
            "tolerance {t}°: a normal-error tolerance is a positive number of degrees up to 5 \
             (radians? 0.05° is 0.00087 rad)"
        );
    }
    Ok(())
}

/// The tracker's figures by physics, and its due date against `now`.
///
/// # Errors
/// The field and the fix.
pub fn check_tracker(t: &Tracker, now: std::time::SystemTime) -> Result<()> {
    if !(t.xi_mm > 0.0 && t.xi_mm <= 1.0) {
        let hint = if t.xi_mm > 1.0 && t.xi_mm <= 1000.0 {
            format!(" (micrometres? {} µm is {} mm)", t.xi_mm, t.xi_mm / 1000.0)
        } else {
            String::new()
        };
        bail!(
            "tracker.xi_mm = {}: a tracker's point noise is above 0 and at most 1 mm{hint}",
            t.xi_mm
        );
    }
    if !(3..=100_000).contains(&t.points) {
        bail!(
            "tracker.points = {}: a plane takes 3 to 100000 points",
            t.points
        );
    }
    if !(10.0..=10_000.0).contains(&t.patch_mm) {
        bail!(
            "tracker.patch_mm = {}: the side of the patch the points cover, 10 to 10000 mm",
            t.patch_mm
        );
    }
    let due =
        humantime::parse_rfc3339_weak(&format!("{}T23:59:59", t.calibration_due)).map_err(|e| {
            anyhow!(
                "tracker.calibration_due = {:?}: not a date ({e}); write e.g. 2027-06-30",
                t.calibration_due
            )
        })?;
    if due < now {
        bail!(
            "tracker {} (serial {}) was due for calibration on {}: a certificate cannot rest \
             on a reference standard out of calibration; recalibrate the tracker and update \
             calibration_due",
            t.model,
            t.serial,
            t.calibration_due
        );
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn good() -> String {
        r#"{"schema": "perpend.cell-config/1",
         "laboratory": "Metrology lab, 1 Plant Road, Town", "site": "Plant 2, cell 4",
            "operator": "A. Operator", "approver": "Q. Engineer",
            "tolerance_deg": 0.05, "ambient_c": 21.5,
            "tracker": {"model": "Tracker T1", "serial": "T1-0042",
              "calibration_due": "2099-06-30", "traceability": "cert 17-123, NMI",
              "xi_mm": 0.02, "points": 20, "patch_mm": 150}}"#
            .into()
    }

    fn read(text: &str) -> Result<CellConfig> {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("cell-config.json");
        std::fs::write(&p, text).unwrap();
        CellConfig::read(&p).map(|c| c.0)
    }

    #[test]
    fn a_good_configuration_reads() {
        let c = read(&good()).unwrap();
        assert_eq!(c.tracker.serial, "T1-0042");
        assert_eq!(c.ambient_c, Some(21.5));
    }

    #[test]
    fn figures_out_of_their_physics_are_refused_by_name() {
        let cases = [
            ("\"xi_mm\": 0.02", "\"xi_mm\": 20", "micrometres"),
            (
                "\"tolerance_deg\": 0.05",
                "\"tolerance_deg\": 0",
                "tolerance 0",
            ),
            ("\"patch_mm\": 150", "\"patch_mm\": 1", "patch_mm = 1"),
            ("\"points\": 20", "\"points\": 2", "points = 2"),
            (
                "2099-06-30",
                "2001-01-31",
                "due for calibration on 2001-01-31",
            ),
            ("2099-06-30", "soon", "not a date"),
            (
                "\"ambient_c\": 21.5",
                "\"ambient_c\": 295",
                "ambient_c = 295",
            ),
            ("\"T1-0042\"", "\" \"", "tracker.serial is empty"),
            (
                "\"Metrology lab, 1 Plant Road, Town\"",
                "\"\"",
                "laboratory is empty",
            ),
            (
                "\"site\"",
                "\"customer\": \" \", \"site\"",
                "customer is empty",
            ),
            (
                "Q. Engineer",
                "A. Operator",
                "operator and approver are both",
            ),
        ];
        for (from, to, want) in cases {
            let e = format!("{:#}", read(&good().replace(from, to)).unwrap_err());
            assert!(e.contains(want), "{to}: {e}");
        }
        let e = format!(
            "{:#}",
            read(&good().replace("\"site\"", "\"sight\"")).unwrap_err()
        );
        assert!(e.contains("line 2") && e.contains("sight"), "{e}");
        let e = format!(
            "{:#}",
            read(&good().replace("\"laboratory\"", "\"lab\"")).unwrap_err()
        );
        assert!(
            e.contains("laboratory"),
            "a certificate names its laboratory: {e}"
        );
        let c = read(&good().replace("\"site\"", "\"customer\": \"Acme\", \"site\""));
        assert_eq!(c.unwrap().customer.as_deref(), Some("Acme"));
    }
}
