//! SVG plots of a diagnosis (`perpend diagnose --plot DIR`):
//!
//! * `residuals.svg` — one row per sensor: held-out residual of every
//!   reading against the regressor of the named effect (the reading's
//!   offset from its mean for `none` / `unexplained` / `nonlinearity`),
//!   with the paper's model (left) and with the extension (right), over
//!   the expected reading noise band (±1σ estimated from the run) and the
//!   simulated held-out RMS floor; the legend sits in a strip above;
//! * `normal_errors.svg` — histograms (integer pose counts) of the held-out
//!   normal errors of the base and the extended model, means marked, the
//!   legend beside the data.
//!
//! Limits: text is laid out with the SVG backend's font estimate (no font
//! files are read), so labels may sit a little off in some viewers.

use std::path::Path;

use anyhow::{anyhow, Result};
use plotters::prelude::*;

use super::diagnosis::Diagnosis;
use perpend_calib::candidates::{regressor, Effect};
use perpend_calib::cv::CvResult;

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
    let ns = d.run.nominal.len();
    (0..ns)
        .map(|i| {
            let geom = &d.fits.measured.base_fit[i].sensor;
            (0..d.run.poses.rows.len())
                .filter_map(|k| {
                    let r = cv.resid.get(k)?.get(i).copied().flatten()?;
                    let mut x = regressor(effect, &d.run.refs, &d.run.poses, k, i, geom)?;
                    if effect == Effect::Thermal {
                        // Show the temperature offset, not the raw term.
                        x = d.run.poses.rows[k]
                            .temp_c
                            .map_or(x, |t| t - d.run.refs.temp_ref);
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

/// What one residual panel shows besides its points.
struct Panel<'a> {
    title: String,
    xlabel: &'a str,
    colour: RGBColor,
    /// Expected reading noise of this sensor (1σ) [mm].
    sigma: f64,
    /// Simulated held-out RMS floor of this model [mm].
    floor: f64,
}

fn scatter_panel(
    area: &DrawingArea<SVGBackend<'_>, plotters::coord::Shift>,
    p: &Panel<'_>,
    pts: &[(f64, f64)],
    xr: (f64, f64),
    yr: (f64, f64),
) -> Result<()> {
    let e = |e: DrawingAreaErrorKind<std::io::Error>| anyhow!("plot: {e}");
    let mut chart = ChartBuilder::on(area)
        .caption(&p.title, ("sans-serif", 15))
        .margin(8)
        .x_label_area_size(40)
        .y_label_area_size(62)
        .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc(p.xlabel)
        .y_desc("held-out residual [mm]")
        .max_light_lines(0)
        .draw()
        .map_err(e)?;
    // The expected noise band (±1σ, shaded) and the simulated floor
    // (±RMS, dashed), drawn under the points.
    chart
        .draw_series([Rectangle::new(
            [(xr.0, -p.sigma), (xr.1, p.sigma)],
            RGBColor(200, 200, 200).mix(0.5).filled(),
        )])
        .map_err(e)?;
    for y in [-p.floor, p.floor] {
        chart
            .draw_series(DashedLineSeries::new(
                [(xr.0, y), (xr.1, y)],
                6,
                4,
                BLACK.mix(0.7).into(),
            ))
            .map_err(e)?;
    }
    chart
        .draw_series(LineSeries::new([(xr.0, 0.0), (xr.1, 0.0)], BLACK.mix(0.4)))
        .map_err(e)?;
    let c = p.colour;
    chart
        .draw_series(pts.iter().map(|&(x, y)| Circle::new((x, y), 2, c.filled())))
        .map_err(e)?;
    Ok(())
}

/// Height [px] of the legend strip above the residual panels: three lines,
/// one per item, so that the legend fits a single column of panels (560 px
/// wide) whatever the verdict's length.
const LEGEND_H: u32 = 62;

/// A legend strip above the panels (outside every data area): one item a
/// line.
fn legend_strip(
    area: &DrawingArea<SVGBackend<'_>, plotters::coord::Shift>,
    text: &str,
) -> Result<()> {
    let e = |e: DrawingAreaErrorKind<std::io::Error>| anyhow!("plot: {e}");
    let font = ("sans-serif", 13);
    area.draw(&Rectangle::new(
        [(10, 6), (34, 18)],
        RGBColor(200, 200, 200).mix(0.5).filled(),
    ))
    .map_err(e)?;
    area.draw(&Text::new(
        "expected reading noise ±1σ (estimated from the run)",
        (40, 6),
        font,
    ))
    .map_err(e)?;
    area.draw(&PathElement::new(
        vec![(10, 30), (34, 30)],
        BLACK.mix(0.7).stroke_width(1),
    ))
    .map_err(e)?;
    area.draw(&Text::new(
        "simulated held-out RMS floor (±)",
        (40, 24),
        font,
    ))
    .map_err(e)?;
    area.draw(&Text::new(text, (10, 42), font)).map_err(e)?;
    Ok(())
}

/// Writes `residuals.svg`: one row of panels per sensor, the paper's model
/// on the left and, when an effect is named, the extended model on the
/// right, each with the expected noise band and the simulated floor.
///
/// # Errors
/// I/O and drawing errors.
pub fn residuals(d: &Diagnosis, path: &Path) -> Result<()> {
    let shown = match d.decided.effect {
        Effect::None => None,
        Effect::Unexplained => d.decided.decision.winner,
        e => Some(e),
    };
    let axis_effect = shown.unwrap_or(Effect::None);
    let base_cv = d
        .fits
        .measured
        .cv_of(Effect::None)
        .ok_or_else(|| anyhow!("no base cross-validation"))?;
    let before = residual_points(d, axis_effect, base_cv);
    // After: the model with every effect named (the last forward step).
    let after_cv = d
        .decided
        .also
        .last()
        .map(|st| &st.cv)
        .or(shown.and_then(|e| d.fits.measured.cv_of(e)));
    let after = after_cv.map(|c| residual_points(d, axis_effect, c));
    let names = effects_label(d);
    let all = before.iter().chain(after.iter().flatten()).flatten();
    let xr = range(all.clone().map(|p| p.0));
    let yr = range(all.map(|p| p.1));
    let ns = before.len().max(1);
    let cols = if after.is_some() { 2 } else { 1 };
    let size = (560 * cols as u32, LEGEND_H + 260 * ns as u32);
    let root = SVGBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(|e| anyhow!("plot: {e}"))?;
    let (top, body) = root.split_vertically(LEGEND_H);
    let verdict = if names.is_empty() {
        d.decided.effect.name().to_string()
    } else {
        names.clone()
    };
    legend_strip(
        &top,
        &format!("points: held-out residuals; verdict: {verdict}"),
    )?;
    let areas = body.split_evenly((ns, cols));
    let floor = |e: Effect| d.decided.expected.rms_of(e).map_or(0.0, |s| s.mean);
    for (i, pts) in before.iter().enumerate() {
        let panel = Panel {
            title: format!("sensor {}: paper's model", i + 1),
            xlabel: axis_effect.regressor_label(),
            colour: COLOURS[i % COLOURS.len()],
            sigma: d.decided.estimate.reading_mm.get(i).copied().unwrap_or(0.0),
            floor: floor(Effect::None),
        };
        scatter_panel(&areas[i * cols], &panel, pts, xr, yr)?;
        if let (Some(a), Some(e)) = (&after, shown) {
            let title = match d.decided.effect {
                Effect::Unexplained => {
                    format!("sensor {}: with {} (explains only part)", i + 1, e.name())
                }
                _ => format!("sensor {}: with {names}", i + 1),
            };
            let p = Panel {
                title,
                floor: d
                    .decided
                    .also
                    .last()
                    .map_or(floor(e), |st| st.verdict.expected.mean),
                ..panel
            };
            scatter_panel(
                &areas[i * cols + 1],
                &p,
                a.get(i).map_or(&[][..], |v| &v[..]),
                xr,
                yr,
            )?;
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
    let base: Vec<f64> = d.scores.base_normals.iter().flatten().copied().collect();
    let ext: Vec<f64> = d.scores.ext_normals.iter().flatten().copied().collect();
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
    let ymax = (hb.iter().chain(&he).copied().max().unwrap_or(1).max(1) as f64 * 1.15).ceil();
    let root = SVGBackend::new(path, (800, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| anyhow!("plot: {e}"))?;
    // The legend goes in a strip to the right of the data.
    let (root, side) = root.split_horizontally(590);
    let title = if d.scores.ext_model == Effect::None {
        "held-out normal error: paper's model".to_string()
    } else {
        format!(
            "held-out normal error: paper's model vs with {}",
            effects_label(d)
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
        .max_light_lines(0)
        .y_label_formatter(&|v| format!("{v:.0}"))
        .y_labels((ymax as usize).clamp(2, 10))
        .draw()
        .map_err(|e| anyhow!("plot: {e}"))?;
    let mut series = vec![("paper's model", &hb, &base, COLOURS[0])];
    if d.scores.ext_model != Effect::None {
        series.push(("extended model", &he, &ext, COLOURS[1]));
    }
    for (j, (name, h, v, c)) in series.into_iter().enumerate() {
        let mean = perpend_calib::stats::mean(v);
        chart
            .draw_series(h.iter().enumerate().map(|(b, &n)| {
                let x0 = b as f64 * w;
                Rectangle::new([(x0, 0.0), (x0 + w, n as f64)], c.mix(0.35).filled())
            }))
            .map_err(|e| anyhow!("plot: {e}"))?;
        chart
            .draw_series(LineSeries::new(
                [(mean, 0.0), (mean, ymax)],
                c.stroke_width(2),
            ))
            .map_err(|e| anyhow!("plot: {e}"))?;
        // Legend entry in the strip right of the data.
        let y = 50 + 40 * j as i32;
        side.draw(&Rectangle::new([(8, y), (22, y + 12)], c.mix(0.6).filled()))
            .map_err(|e| anyhow!("plot: {e}"))?;
        side.draw(&Text::new(name.to_string(), (28, y), ("sans-serif", 13)))
            .map_err(|e| anyhow!("plot: {e}"))?;
        side.draw(&Text::new(
            format!("mean {mean:.4}° (line)"),
            (28, y + 16),
            ("sans-serif", 13),
        ))
        .map_err(|e| anyhow!("plot: {e}"))?;
    }
    root.present()
        .map_err(|e| anyhow!("plot {}: {e}", path.display()))?;
    Ok(())
}

/// The effects named, joined by ` + `.
fn effects_label(d: &Diagnosis) -> String {
    d.effects()
        .iter()
        .map(|e| e.name())
        .collect::<Vec<_>>()
        .join(" + ")
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
