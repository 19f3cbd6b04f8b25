//! How `perpend record` and the cell run print figures: angles, parameter
//! values and 1σ, HTML escaping, ISO 8601 times. One place, so that a
//! certificate's figure and the record's agree to the digit.

use std::time::{Duration, UNIX_EPOCH};

use anyhow::{anyhow, Result};

/// An angle [deg] as every output prints it.
pub fn deg(x: f64) -> String {
    format!("{x:.4}")
}

/// A parameter value as printed (`mm` components to 4 decimals, direction
/// cosines to 6).
pub fn value(x: f64, is_dir: bool) -> String {
    if is_dir {
        format!("{x:.6}")
    } else {
        format!("{x:.4}")
    }
}

/// A 1σ as printed.
pub fn sigma(x: f64) -> String {
    format!("{x:.2e}")
}

/// `-` for none, else the angle as [`deg`] prints it.
pub fn opt_deg(x: Option<f64>) -> String {
    x.map_or_else(|| "-".into(), deg)
}

/// The six geometry parameters of a sensor: (name, value, 1σ, direction?).
pub fn geometry(
    p: &perpend_formats::paramfile::SensorParams,
) -> Vec<(&'static str, f64, Option<f64>, bool)> {
    let s = p.sigma.as_ref();
    let names = ["x [mm]", "y [mm]", "z [mm]", "m", "n", "q"];
    (0..6)
        .map(|j| {
            let (v, sd) = if j < 3 {
                (p.zero_mm[j], s.map(|s| s.zero_mm[j]))
            } else {
                (p.dir[j - 3], s.map(|s| s.dir[j - 3]))
            };
            (names[j], v, sd, j >= 3)
        })
        .collect()
}

/// Escapes a string for HTML text and attribute values.
pub fn esc(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&#39;"),
            c => o.push(c),
        }
    }
    o
}

/// Seconds since the epoch of an ISO 8601 time.
///
/// # Errors
/// Not an ISO 8601 time.
pub fn epoch_s(utc: &str) -> Result<f64> {
    let t = humantime::parse_rfc3339_weak(utc).map_err(|e| anyhow!("utc {utc:?}: {e}"))?;
    Ok(t.duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64()))
}

/// The ISO 8601 date-time at `s` seconds since the epoch.
pub fn iso(s: f64) -> String {
    let t = if s >= 0.0 && s.is_finite() {
        UNIX_EPOCH + Duration::from_secs_f64(s.min(1e11))
    } else {
        UNIX_EPOCH
    };
    humantime::format_rfc3339_seconds(t).to_string()
}

/// The stamp the board carried before, in words (`record find` leads to
/// the record that set it).
pub fn replaced_stamp(p: &perpend_calib::record::Previous) -> String {
    p.board_stamp.as_ref().map_or_else(
        || "the board carried no stamp".to_string(),
        |s| {
            format!(
                "the board's stamp {} of {} (store {})",
                s.record_hash, s.utc, s.store_count
            )
        },
    )
}
