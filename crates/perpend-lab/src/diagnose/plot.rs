//! SVG plots of a diagnosis (`perpend diagnose --plot DIR`):
//!
//! * `residuals.svg` — held-out residual of every reading against the
//!   regressor of the named effect (the reading's offset from its mean for
//!   `none` / `unexplained` / `nonlinearity`), with the paper's model
//!   (before) and with the extension (after), one colour per sensor;
//! * `normal_errors.svg` — distributions of the held-out normal errors of
//!   the base and the extended model, means marked.
//!
//! Limits: text is laid out with the SVG backend's font estimate (no font
//! files are read), so labels may sit a little off in some viewers.

use std::path::Path;

use anyhow::{anyhow, Result};
use plotters::prelude::*;

use super::candidates::{regressor, Effect};
use super::cv::CvResult;
use super::Diagnosis;

const COLOURS: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
    RGBColor(23, 190, 207),
    RGBColor(140, 86, 75),
    RGBColor(127, 127, 127),
];

/// Points `(regressor, held-out residual)` of every sensor.
pub fn residual_points(d: &Diagnosis, effect: Effect, cv: &CvResult) -> Vec<Vec<(f64, f64)>> {
    let ns = d.nominal.len();
    (0..ns)
        .map(|i| {
            let geom = &d.measured.base_fit[i].sensor;
            (0..d.poses.rows.len())
                .filter_map(|k| {
                    let r = cv.resid.get(k)?.get(i).copied().flatten()?;
                    let mut x = regressor(effect, &d.refs, &d.poses, k, i, geom)?;
                    if effect == Effect::Thermal {
                        // Show the temperature offset, not the raw term.
                        x = d.poses.rows[k].temp_c.map_or(x, |t| t - d.refs.temp_ref);
                    }
                    Some((x, r))
                })
                .collect()
        })
        .collect()
}

fn range(v: impl Iterator<Item = f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for x in v.filter(|x| x.is_finite()) {
        lo = lo.min(x);
        hi = hi.max(x);
    }
    if !(lo.is_finite() && hi.is_finite()) {
        return (-1.0, 1.0);
    }
    let pad = ((hi - lo) * 0.05).max(1e-9);
    (lo - pad, hi + pad)
}

fn scatter_panel(
    area: &DrawingArea<SVGBackend<'_>, plotters::coord::Shift>,
    title: &str,
    xlabel: &str,
    pts: &[Vec<(f64, f64)>],
    xr: (f64, f64),
    yr: (f64, f64),
) -> Result<()> {
    let mut chart = ChartBuilder::on(area)
        .caption(title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)
        .map_err(|e| anyhow!("plot: {e}"))?;
    chart
        .configure_mesh()
        .x_desc(xlabel)
        .y_desc("held-out residual [mm]")
        .draw()
        .map_err(|e| anyhow!("plot: {e}"))?;
    for (i, s) in pts.iter().enumerate() {
        let c = COLOURS[i % COLOURS.len()];
        chart
            .draw_series(s.iter().map(|&(x, y)| Circle::new((x, y), 2, c.filled())))
            .map_err(|e| anyhow!("plot: {e}"))?
            .label(format!("sensor {}", i + 1))
            .legend(move |(x, y)| Circle::new((x, y), 4, c.filled()));
    }
    chart
        .draw_series(LineSeries::new([(xr.0, 0.0), (xr.1, 0.0)], BLACK.mix(0.5)))
        .map_err(|e| anyhow!("plot: {e}"))?;
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| anyhow!("plot: {e}"))?;
    Ok(())
}

/// Writes `residuals.svg`.
///
/// # Errors
/// I/O and drawing errors.
pub fn residuals(d: &Diagnosis, path: &Path) -> Result<()> {
    let shown = match d.effect {
        Effect::None => None,
        Effect::Unexplained => d.decision.winner,
        e => Some(e),
    };
    let axis_effect = shown.unwrap_or(Effect::None);
    let base_cv = d
        .measured
        .cv_of(Effect::None)
        .ok_or_else(|| anyhow!("no base cross-validation"))?;
    let before = residual_points(d, axis_effect, base_cv);
    let after = shown
        .and_then(|e| d.measured.cv_of(e))
        .map(|c| residual_points(d, axis_effect, c));
    let all = before.iter().chain(after.iter().flatten()).flatten();
    let xr = range(all.clone().map(|p| p.0));
    let yr = range(all.map(|p| p.1));
    let width = if after.is_some() { 1200 } else { 700 };
    let root = SVGBackend::new(path, (width, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| anyhow!("plot: {e}"))?;
    let label = axis_effect.regressor_label();
    match &after {
        Some(a) => {
            let areas = root.split_evenly((1, 2));
            scatter_panel(&areas[0], "before: paper's model", label, &before, xr, yr)?;
            let title = match d.effect {
                Effect::Unexplained => {
                    format!("after: with {} (explains only part)", axis_effect.name())
                }
                e => format!("after: with {}", e.name()),
            };
            scatter_panel(&areas[1], &title, label, a, xr, yr)?;
        }
        None => {
            let title = format!("paper's model (verdict: {})", d.effect.name());
            scatter_panel(&root, &title, label, &before, xr, yr)?;
        }
    }
    root.present()
        .map_err(|e| anyhow!("plot {}: {e}", path.display()))?;
    Ok(())
}

/// Writes `normal_errors.svg`.
///
/// # Errors
/// I/O and drawing errors.
pub fn normal_errors(d: &Diagnosis, path: &Path) -> Result<()> {
    let base: Vec<f64> = d.base_normals.iter().flatten().copied().collect();
    let ext: Vec<f64> = d.ext_normals.iter().flatten().copied().collect();
    let hi = base
        .iter()
        .chain(&ext)
        .copied()
        .fold(0.0f64, f64::max)
        .max(1e-6)
        * 1.05;
    let bins = 20usize;
    let w = hi / bins as f64;
    let hist = |v: &[f64]| {
        let mut h = vec![0usize; bins];
        for x in v {
            let b = ((x / w) as usize).min(bins - 1);
            h[b] += 1;
        }
        h
    };
    let (hb, he) = (hist(&base), hist(&ext));
    let ymax = hb.iter().chain(&he).copied().max().unwrap_or(1).max(1) as f64 * 1.15;
    let root = SVGBackend::new(path, (800, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| anyhow!("plot: {e}"))?;
    let title = if d.ext_model == Effect::None {
        "held-out normal error: paper's model".to_string()
    } else {
        format!(
            "held-out normal error: paper's model vs with {}",
            d.ext_model.name()
        )
    };
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..hi, 0.0..ymax)
        .map_err(|e| anyhow!("plot: {e}"))?;
    chart
        .configure_mesh()
        .x_desc("angle between measured and plane normal [deg]")
        .y_desc("poses")
        .draw()
        .map_err(|e| anyhow!("plot: {e}"))?;
    let mut series = vec![("paper's model", &hb, &base, COLOURS[0])];
    if d.ext_model != Effect::None {
        series.push(("extended", &he, &ext, COLOURS[1]));
    }
    for (name, h, v, c) in series {
        let mean = super::stats::mean(v);
        chart
            .draw_series(h.iter().enumerate().map(|(b, &n)| {
                let x0 = b as f64 * w;
                Rectangle::new([(x0, 0.0), (x0 + w, n as f64)], c.mix(0.35).filled())
            }))
            .map_err(|e| anyhow!("plot: {e}"))?
            .label(format!("{name}: mean {mean:.4}°"))
            .legend(move |(x, y)| {
                Rectangle::new([(x, y - 5), (x + 12, y + 5)], c.mix(0.6).filled())
            });
        chart
            .draw_series(LineSeries::new(
                [(mean, 0.0), (mean, ymax)],
                c.stroke_width(2),
            ))
            .map_err(|e| anyhow!("plot: {e}"))?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| anyhow!("plot: {e}"))?;
    root.present()
        .map_err(|e| anyhow!("plot {}: {e}", path.display()))?;
    Ok(())
}

/// Writes every plot into `dir`.
///
/// # Errors
/// I/O and drawing errors.
pub fn write_all(d: &Diagnosis, dir: &Path) -> Result<()> {
    residuals(d, &dir.join("residuals.svg"))?;
    normal_errors(d, &dir.join("normal_errors.svg"))?;
    Ok(())
}
