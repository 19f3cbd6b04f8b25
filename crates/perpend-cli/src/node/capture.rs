//! `perpend node capture`: one calibration pose from the board. Averages N
//! samples of the distances (0x2004, read by SDO: the default TPDOs do not
//! carry them) and appends one row to `poses.csv` in the exchange format
//! (docs/data-format.md): the plane as given, the mean readings, their
//! standard deviations `s1_mm…`, `n_samples` and `t_s`.
//!
//! * Each sample is a new one (the sample counter 0x2007 advanced); a
//!   sensor's reading counts only when its valid bit (0x2005) is set in the
//!   status read before and after it.
//! * A sensor that was not valid in every sample gets an empty reading (the
//!   row is kept: it still calibrates the others) and a warning with the
//!   reason from the status word.
//! * `t_s` counts from the run's start, which the file records in a comment
//!   when capture creates it (`# perpend node capture: t_s counts from unix
//!   time …`); in a file without it `t_s` stays empty.
//! * A missing file is created with its header; an existing one must have
//!   the columns `pose, a, b, c, d_mm, d1_mm…dN_mm` for the board's N
//!   sensors and not have the pose yet; the row follows its column order
//!   (optional columns it lacks are not recorded, with a warning).
//! * `temp_c` is the mean of the board's die temperature 0x200A read with
//!   every sample (the temperature the board's thermal correction uses,
//!   docs/can.md); it stays empty when the board does not have it (older
//!   firmware: SDO abort; the virtual board: 0x200A at its "unknown" value
//!   -273.15 °C) in any sample.
//! * The plane is checked against the board before anything is sampled
//!   ([`check_plane`], by `perpend node capture`):
//!   the reading each sensor would give on it (the board's calibration,
//!   Chen eq. 7) must lie in the sensor's measuring range (its transfer
//!   function's `mm at 4 mA / 0 V`..`mm at 20 mA / 10 V`, 0x2201..); a plane
//!   that puts a spot outside (by more than [`RANGE_MARGIN`]) is refused with the sensor, the predicted
//!   reading and the range, and named as inches or micrometres when `D`
//!   × 25.4 or × 0.001 would put every spot inside.
//! * Ctrl-C appends nothing.

use std::collections::HashMap;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{bail, Context as _, Result};
use perpend_can::status::{self, SENSOR_VALID};
use perpend_core::geometry::Plane;
use perpend_core::head::Sensor;
use perpend_core::model::distance;
use perpend_formats::progress::Progress;

use super::{words, Node};

/// Options of `capture`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The datum plane `A,B,C,D` (`A·x + B·y + C·z + D = 0`, TCS, mm) the
    /// tracker measured for this pose.
    #[arg(long, allow_hyphen_values = true)]
    pub plane: String,
    /// Pose number (unique in the file).
    #[arg(long, allow_hyphen_values = true)]
    pub pose: i64,
    /// The poses file: created with its header if missing, else appended to.
    #[arg(long)]
    pub out: PathBuf,
    /// Samples averaged (1..100000).
    #[arg(long, default_value_t = 50)]
    pub samples: u32,
}

/// The comment that records the run's start.
const T0_PREFIX: &str = "# perpend node capture: t_s counts from unix time ";

/// What an existing poses file allows.
#[derive(Debug, Clone, PartialEq)]
struct Existing {
    header: Vec<String>,
    t0: Option<f64>,
    newline: bool,
}

fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// The plane's four numbers as given (validated as a plane).
fn parse_abcd(s: &str) -> Result<[f64; 4]> {
    crate::demo::parse_plane(s)?;
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()?;
    v.try_into()
        .map_err(|_| anyhow::anyhow!("plane '{s}': expected four numbers A,B,C,D"))
}

/// Fraction of a sensor's span a predicted spot may lie beyond either end
/// of its range: the prediction uses the board's calibration, which before
/// the first calibration is the nominal head, off by tenths of a mm (Chen
/// Table 2); the board itself flags the samples that do fall outside.
pub const RANGE_MARGIN: f64 = 0.05;

/// Each sensor's measuring range [mm] (low, high), `None` when unknown.
pub type Ranges = [Option<(f64, f64)>];

/// Why the plane `abcd` (as given, mm) cannot be captured by `sensors`
/// with measuring `ranges`: the spots it puts outside (sensor, predicted
/// reading, range) and, when its `D` scaled by 25.4 or 0.001 fits every
/// sensor, that it looks like inches or micrometres. `None`: every spot is
/// in range.
///
/// # Errors
/// `abcd` is not a plane.
pub fn plane_outside(
    sensors: &[Sensor<f64>],
    ranges: &Ranges,
    abcd: [f64; 4],
) -> Result<Option<String>> {
    let misses = |k: f64| -> Result<Vec<String>> {
        let p = Plane::from_abcd(abcd[0], abcd[1], abcd[2], abcd[3] * k)
            .map_err(|e| anyhow::anyhow!("plane {abcd:?}: {e}"))?;
        Ok(sensors
            .iter()
            .zip(ranges)
            .enumerate()
            .filter_map(|(i, (s, r))| {
                let (lo, hi) = (*r)?;
                let m = RANGE_MARGIN * (hi - lo);
                match distance(s, &p, i) {
                    Ok(d) if (lo - m..=hi + m).contains(&d) => None,
                    Ok(d) => Some(format!(
                        "sensor {} would read {d:.2} mm (range {lo}-{hi} mm)",
                        i + 1
                    )),
                    Err(e) => Some(format!("{e} (range {lo}-{hi} mm)")),
                }
            })
            .collect())
    };
    let out = misses(1.0)?;
    if out.is_empty() {
        return Ok(None);
    }
    let mut unit = None;
    for (k, name) in [(25.4, "inches"), (0.001, "micrometres")] {
        if misses(k)?.is_empty() {
            unit = Some((k, name));
            break;
        }
    }
    let fix = match unit {
        Some((k, name)) => format!(
            "the plane looks like {name}: D = {} is {} mm; give it in mm: --plane {},{},{},{}",
            abcd[3],
            short(abcd[3] * k),
            abcd[0],
            abcd[1],
            abcd[2],
            short(abcd[3] * k)
        ),
        None => "check the plane's units (mm), its frame (TCS) and that the tracker measured \
                 this pose"
            .to_string(),
    };
    Ok(Some(format!(
        "the plane puts the spots outside the sensors' measuring range: {}; {fix}",
        out.join("; ")
    )))
}

/// `x` with at most 4 decimals, trailing zeros dropped.
fn short(x: f64) -> String {
    let s = format!("{x:.4}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

/// Refuses a plane outside the board's sensors' ranges ([`plane_outside`]),
/// from the board's calibration and transfer functions: `perpend node
/// capture` runs it before [`run`] (a cell run captures the planes of its
/// plan, in mm by construction, and does not). A calibration the
/// board cannot give (a bus error, one the file format refuses) is a
/// warning: the capture that follows reports the bus itself.
///
/// # Errors
/// The plane refused.
pub fn check_plane(node: &mut Node, a: &Args, cancel: &AtomicBool) -> Result<()> {
    let f = match super::params::pull(node, cancel) {
        Ok(f) => f,
        Err(e) => {
            eprintln!("warning: the plane is not checked against the sensors' ranges: {e:#}");
            return Ok(());
        }
    };
    let sensors = f.sensors()?;
    let ranges: Vec<Option<(f64, f64)>> = f
        .sensors
        .iter()
        .map(|s| {
            let t = s.transfer.as_ref()?;
            Some((t.mm_at_low.min(t.mm_at_high), t.mm_at_low.max(t.mm_at_high)))
        })
        .collect();
    if let Some(why) = plane_outside(&sensors, &ranges, parse_abcd(&a.plane)?)? {
        bail!(
            "--plane {} on {}: {why}; nothing was appended",
            a.plane,
            node.name()
        );
    }
    Ok(())
}

/// The header a new file gets for `n` sensors.
fn new_header(n: usize) -> Vec<String> {
    let mut h: Vec<String> = ["pose", "a", "b", "c", "d_mm"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    h.extend((1..=n).map(|i| format!("d{i}_mm")));
    h.push("t_s".into());
    h.push("temp_c".into());
    h.extend((1..=n).map(|i| format!("s{i}_mm")));
    h.push("n_samples".into());
    h
}

/// Checks an existing file: its columns, its sensor count, the pose.
fn inspect(path: &Path, n: usize, pose: i64) -> Result<Option<Existing>> {
    let name = path.display().to_string();
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("{name}: cannot read")),
    };
    let t0 = text
        .lines()
        .find_map(|l| l.strip_prefix(T0_PREFIX))
        .and_then(|r| r.trim_end_matches(" s").trim().parse::<f64>().ok());
    let mut rd = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .flexible(true)
        .from_reader(text.as_bytes());
    let header: Vec<String> = rd
        .headers()
        .with_context(|| format!("{name}: unreadable header"))?
        .iter()
        .map(|h| h.trim().to_string())
        .collect();
    if header.len() == 1 && header[0].contains(';') {
        bail!("{name}: separated by ';' — poses.csv uses ',' and a decimal point");
    }
    for col in new_header(n).iter().take(5 + n) {
        if !header.contains(col) {
            bail!("{name}: has no column '{col}' (a poses.csv for {n} sensors needs pose, a, b, c, d_mm, d1_mm…d{n}_mm); nothing was appended");
        }
    }
    if header.iter().any(|h| h == &format!("d{}_mm", n + 1)) {
        bail!("{name}: has readings of more than {n} sensors; the board has {n}: this file is for another head");
    }
    let pcol = header.iter().position(|h| h == "pose").unwrap_or(0);
    for rec in rd.records() {
        let rec = rec.with_context(|| format!("{name}: unreadable row"))?;
        if rec.get(pcol).and_then(|p| p.trim().parse::<i64>().ok()) == Some(pose) {
            let line = rec.position().map_or(0, |p| p.line());
            bail!("{name}, line {line}: pose {pose} is already there; choose another --pose (nothing was appended)");
        }
    }
    let newline = text.is_empty() || text.ends_with('\n');
    Ok(Some(Existing {
        header,
        t0,
        newline,
    }))
}

/// The samples of one capture.
#[derive(Debug, Clone, Default)]
struct Acquired {
    /// Valid readings per sensor.
    readings: Vec<Vec<f64>>,
    /// Samples in which each sensor was not valid, and its nibbles then.
    invalid: Vec<(u32, u32)>,
    /// Status bits beyond the sensors seen in any sample.
    flags: u32,
    /// Die temperatures (0x200A), one per sample while every sample had
    /// one.
    temps: Vec<f64>,
    /// A sample had no die temperature.
    no_temp: bool,
    /// Unix time of the middle of the acquisition.
    t_mid: f64,
    /// Duration of the acquisition.
    took: Duration,
}

/// Waits until the sample counter differs from `last`; returns it.
fn next_sample(node: &mut Node, last: Option<u32>) -> Result<u32> {
    let end = Instant::now() + Duration::from_secs(1);
    loop {
        let k = node.client.read_u32(node.id, 0x2007, 0)?;
        if Some(k) != last {
            return Ok(k);
        }
        if Instant::now() > end {
            bail!(
                "{}: the sample counter (0x2007) did not advance for 1 s: is the board \
                 sampling?",
                node.name()
            );
        }
        std::thread::sleep(Duration::from_micros(200));
    }
}

/// Takes `samples` samples of the `n` distances.
fn acquire(node: &mut Node, n: usize, samples: u32, cancel: &AtomicBool) -> Result<Acquired> {
    let id = node.id;
    let bar = Progress::new(samples as u64, "capture");
    let mut acq = Acquired {
        readings: vec![Vec::new(); n],
        invalid: vec![(0, 0); n],
        ..Acquired::default()
    };
    let (t_start, started) = (unix_now(), Instant::now());
    let mut last = None;
    for _ in 0..samples {
        if cancel.load(Ordering::SeqCst) {
            bail!("interrupted (Ctrl-C): nothing was appended");
        }
        last = Some(next_sample(node, last)?);
        let s0 = node.client.read_u32(id, 0x2005, 0)?;
        let mut d = Vec::with_capacity(n);
        for i in 0..n {
            d.push(node.client.read_f32(id, 0x2004, i as u8 + 1)? as f64);
        }
        let s1 = node.client.read_u32(id, 0x2005, 0)?;
        if !acq.no_temp {
            match die_temp(node.client.read_f32(id, 0x200A, 0).ok()) {
                Some(t) => acq.temps.push(t),
                None => acq.no_temp = true,
            }
        }
        acq.flags |= (s0 | s1) & !0xFFFF;
        for (i, &x) in d.iter().enumerate() {
            let (a, b) = (status::sensor_nibble(s0, i), status::sensor_nibble(s1, i));
            if a & b & SENSOR_VALID != 0 && x.is_finite() {
                acq.readings[i].push(x);
            } else {
                acq.invalid[i].0 += 1;
                acq.invalid[i].1 |= (a | b) & !SENSOR_VALID;
            }
        }
        bar.inc();
    }
    acq.took = started.elapsed();
    acq.t_mid = t_start + acq.took.as_secs_f64() / 2.0;
    Ok(acq)
}

/// A die temperature read from 0x200A, if it is one (not the "unknown"
/// value, finite).
fn die_temp(v: Option<f32>) -> Option<f64> {
    v.filter(|t| t.is_finite() && *t > perpend_can::od::DIE_TEMP_UNKNOWN + 1.0)
        .map(f64::from)
}

/// Mean and sample standard deviation (empty for one value).
fn mean_sd(v: &[f64]) -> (f64, Option<f64>) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let sd =
        (v.len() > 1).then(|| (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt());
    (m, sd)
}

/// The row's cells by column name; warnings for sensors left empty.
fn row_cells(
    a: &Args,
    abcd: [f64; 4],
    acq: &Acquired,
    t_s: Option<f64>,
    warn: &mut Vec<String>,
) -> HashMap<String, String> {
    let mut c = HashMap::new();
    c.insert("pose".to_string(), a.pose.to_string());
    for (k, name) in ["a", "b", "c", "d_mm"].iter().enumerate() {
        c.insert(name.to_string(), format!("{}", abcd[k]));
    }
    for (i, r) in acq.readings.iter().enumerate() {
        let (bad, nib) = acq.invalid[i];
        if bad == 0 && !r.is_empty() {
            let (m, sd) = mean_sd(r);
            c.insert(format!("d{}_mm", i + 1), format!("{m:.6}"));
            if let Some(sd) = sd {
                c.insert(format!("s{}_mm", i + 1), format!("{sd:.6}"));
            }
        } else {
            warn.push(format!(
                "sensor {}: {bad} of {} samples not valid ({}): d{}_mm left empty, the row is kept",
                i + 1,
                a.samples,
                words::sensor_words(nib),
                i + 1
            ));
        }
    }
    c.insert("n_samples".into(), a.samples.to_string());
    if let Some(t) = t_s {
        c.insert("t_s".into(), format!("{t:.3}"));
    }
    if !acq.no_temp && !acq.temps.is_empty() {
        let (m, _) = mean_sd(&acq.temps);
        c.insert("temp_c".into(), format!("{m:.3}"));
    }
    c
}

/// Appends (or creates the file with its header and) the row.
fn write_row(
    path: &Path,
    existing: Option<&Existing>,
    n: usize,
    cells: &HashMap<String, String>,
    t0: f64,
    warn: &mut Vec<String>,
) -> Result<()> {
    let name = path.display().to_string();
    let mut text = String::new();
    let header = match existing {
        Some(e) => {
            if !e.newline {
                text.push('\n');
            }
            e.header.clone()
        }
        None => {
            text.push_str(&format!("{T0_PREFIX}{t0:.3} s\n"));
            let h = new_header(n);
            text.push_str(&h.join(","));
            text.push('\n');
            h
        }
    };
    for k in cells.keys() {
        if !header.contains(k) {
            warn.push(format!("{name} has no column '{k}': not recorded"));
        }
    }
    let row: Vec<&str> = header
        .iter()
        .map(|h| cells.get(h).map_or("", String::as_str))
        .collect();
    text.push_str(&row.join(","));
    text.push('\n');
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .with_context(|| format!("{name}: cannot open for appending"))?;
    f.write_all(text.as_bytes())
        .with_context(|| format!("{name}: cannot append"))
}

/// `perpend node capture`.
///
/// # Errors
/// A bad plane or file, a board that does not answer or does not sample,
/// Ctrl-C (nothing appended).
pub fn run(node: &mut Node, a: &Args, cancel: &AtomicBool) -> Result<()> {
    let abcd = parse_abcd(&a.plane)?;
    if !(1..=100_000).contains(&a.samples) {
        bail!("--samples {}: expected 1..100000", a.samples);
    }
    node.hello()?;
    let n = node.sensors()?;
    let existing = inspect(&a.out, n, a.pose)?;
    let acq = acquire(node, n, a.samples, cancel)?;
    let t0 = existing.as_ref().map_or(Some(acq.t_mid), |e| e.t0);
    let t_s = t0.map(|t0| acq.t_mid - t0);
    let mut warn = Vec::new();
    let cells = row_cells(a, abcd, &acq, t_s, &mut warn);
    if existing.is_some() && t0.is_none() {
        warn.push(format!(
            "{} records no run start (it was not created by capture): t_s left empty",
            a.out.display()
        ));
    }
    let valid = acq.invalid.iter().filter(|x| x.0 == 0).count();
    if valid < 3 {
        warn.push(format!(
            "the row has {valid} valid readings: it calibrates those sensors, but no normal can \
             be computed from it"
        ));
    }
    write_row(&a.out, existing.as_ref(), n, &cells, acq.t_mid, &mut warn)?;
    for w in &warn {
        eprintln!("warning: {w}");
    }
    let flags = words::status_words(acq.flags, 0);
    for f in flags {
        eprintln!("note: during the capture the board reported: {f}");
    }
    println!(
        "capture: pose {} appended to {} ({} of {n} readings, {} samples over {:.2} s)",
        a.pose,
        a.out.display(),
        valid,
        a.samples,
        acq.took.as_secs_f64()
    );
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A plane 40 mm away fits a 20-80 mm sensor; the same plane in
    /// inches (and in micrometres) is named as such, with the value in mm;
    /// a plane far away is refused with the predicted reading.
    #[test]
    fn a_plane_outside_the_range_is_named_with_its_unit() {
        let head = perpend_core::head::Head4::cone(15.0, 0.3, 0.0, 0.0).unwrap();
        let sensors = head.sensors.to_vec();
        let ranges = vec![Some((20.0, 80.0)); 4];
        assert_eq!(
            plane_outside(&sensors, &ranges, [0.0, 0.0, 1.0, -40.0]).unwrap(),
            None
        );
        let inch = [0.0, 0.0, 1.0, -40.0 / 25.4];
        let e = plane_outside(&sensors, &ranges, inch).unwrap().unwrap();
        assert!(e.contains("looks like inches"), "{e}");
        assert!(e.contains("--plane 0,0,1,-40"), "{e}");
        assert!(e.contains("(range 20-80 mm)"), "{e}");
        let um = plane_outside(&sensors, &ranges, [0.0, 0.0, 1.0, -40_000.0])
            .unwrap()
            .unwrap();
        assert!(um.contains("looks like micrometres"), "{um}");
        let far = plane_outside(&sensors, &ranges, [0.0, 0.0, 1.0, -300.0])
            .unwrap()
            .unwrap();
        assert!(
            far.contains("sensor 1 would read") && far.contains("check the plane's units"),
            "{far}"
        );
        // unknown ranges are not judged
        assert_eq!(plane_outside(&sensors, &[None; 4], inch).unwrap(), None);
    }

    #[test]
    fn existing_files_are_checked_before_anything_is_measured() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("poses.csv");
        assert_eq!(inspect(&p, 4, 1).unwrap(), None);
        std::fs::write(
            &p,
            "# x\npose,a,b,c,d_mm,d1_mm,d2_mm,d3_mm,d4_mm\n1,0,0,1,-40,1,2,3,4",
        )
        .unwrap();
        let e = inspect(&p, 4, 1).unwrap_err().to_string();
        assert!(e.contains("line 3: pose 1 is already there"), "{e}");
        let ok = inspect(&p, 4, 2).unwrap().unwrap();
        assert!(!ok.newline && ok.t0.is_none());
        let e = inspect(&p, 5, 2).unwrap_err().to_string();
        assert!(e.contains("no column 'd5_mm'"), "{e}");
        let e = inspect(&p, 3, 2).unwrap_err().to_string();
        assert!(e.contains("another head"), "{e}");
        std::fs::write(&p, "pose;a;b\n").unwrap();
        assert!(inspect(&p, 4, 2).unwrap_err().to_string().contains("';'"));
    }

    #[test]
    fn rows_follow_the_file_and_leave_faulty_sensors_empty() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("poses.csv");
        let a = Args {
            plane: "0,0,1,-40".into(),
            pose: 1,
            out: p.clone(),
            samples: 3,
        };
        let acq = Acquired {
            readings: vec![
                vec![40.0, 40.002, 40.004],
                vec![],
                vec![41.0; 3],
                vec![42.0; 3],
            ],
            invalid: vec![(0, 0), (3, status::SENSOR_OPEN_LOOP), (0, 0), (0, 0)],
            ..Acquired::default()
        };
        let mut warn = Vec::new();
        let cells = row_cells(&a, [0.0, 0.0, 1.0, -40.0], &acq, Some(0.0), &mut warn);
        assert!(
            warn[0].contains("sensor 2: 3 of 3 samples not valid (open loop"),
            "{warn:?}"
        );
        write_row(&p, None, 4, &cells, 1000.0, &mut warn).unwrap();
        let ex = inspect(&p, 4, 2).unwrap().unwrap();
        assert_eq!(ex.t0, Some(1000.0));
        let mut cells2 = cells.clone();
        cells2.insert("pose".into(), "2".into());
        write_row(&p, Some(&ex), 4, &cells2, 0.0, &mut warn).unwrap();
        let t = perpend_formats::exchange::read_poses(&p, Some(4)).unwrap();
        assert_eq!(t.rows.len(), 2);
        assert_eq!(t.rows[0].temp_c, None);
        assert_eq!(t.rows[0].readings[1], None);
        assert_eq!(t.rows[0].readings[0], Some(40.002));
        assert_eq!(t.rows[0].noise.n_samples, Some(3));
        assert!((t.rows[0].noise.sd_mm[0].unwrap() - 0.002).abs() < 1e-9);
    }

    #[test]
    fn the_die_temperature_goes_into_temp_c() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("poses.csv");
        let a = Args {
            plane: "0,0,1,-40".into(),
            pose: 1,
            out: p.clone(),
            samples: 3,
        };
        let acq = Acquired {
            readings: vec![vec![40.0; 3]; 4],
            invalid: vec![(0, 0); 4],
            temps: vec![31.0, 31.5, 32.0],
            ..Acquired::default()
        };
        let mut warn = Vec::new();
        let cells = row_cells(&a, [0.0, 0.0, 1.0, -40.0], &acq, Some(0.0), &mut warn);
        write_row(&p, None, 4, &cells, 1000.0, &mut warn).unwrap();
        let t = perpend_formats::exchange::read_poses(&p, Some(4)).unwrap();
        assert_eq!(t.rows[0].temp_c, Some(31.5));
        // a sample without it leaves the column empty
        let acq2 = Acquired {
            no_temp: true,
            ..acq
        };
        let cells = row_cells(&a, [0.0, 0.0, 1.0, -40.0], &acq2, Some(0.0), &mut warn);
        assert!(!cells.contains_key("temp_c"));
        // what 0x200A may hold
        assert_eq!(die_temp(Some(25.25)), Some(25.25));
        assert_eq!(die_temp(Some(perpend_can::od::DIE_TEMP_UNKNOWN)), None);
        assert_eq!(die_temp(Some(f32::NAN)), None);
        assert_eq!(die_temp(None), None);
        assert!(warn.is_empty(), "{warn:?}");
    }
}
