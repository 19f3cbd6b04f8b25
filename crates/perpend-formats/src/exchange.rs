//! Reading and writing the measured-data exchange format
//! (`shared/data-format.md`): `sensors.csv` (the nominal head) and
//! `poses.csv` (readings of known planes).
//!
//! Both are CSV with a header row; lines starting with `#` are comments
//! anywhere in the file; columns are found by header name in any order;
//! unknown columns are ignored; LF, CRLF and bare CR line ends all work
//! (line numbers count physical lines whatever the ending, a UTF-8
//! byte-order mark is dropped). In
//! `poses.csv` an empty or `NaN` reading is a missing reading (kept as
//! `None`, never as 0), and the reading columns `d1_mm … dN_mm` may be any
//! number of sensors.
//!
//! Every violation is reported as an [`ExchangeError`] naming the file, the
//! line (1-based, comments counted) and the problem: missing column,
//! non-numeric or non-finite value, no pose with three valid readings,
//! degenerate plane normal, duplicate or missing sensor numbers, a pose
//! number that appears twice, negative readings. Rows may come in any
//! order (they are sorted by pose); a pose with fewer than three valid
//! readings is kept (it calibrates the sensors that read; wherever a normal
//! is computed from it, it is skipped).
//!
//! `sensors.csv` may give each sensor's measuring range (`range_min_mm`,
//! `range_max_mm`, mm, optional): the plausibility checks of
//! [`crate::plausible`] use it (or their default) once the files are read.
//!
//! A readings file ([`parse_readings`], what `perpend measure` reads) has
//! the columns of `poses.csv` without the plane: `pose`, `d1_mm … dN_mm`,
//! optionally `t_s` and `temp_c`; plane columns, when present, are ignored.

use std::collections::HashMap;
use std::fmt;
use std::io::{Read, Write};
use std::path::Path;

use nalgebra::Vector3;
use perpend_core::calib::Poses;
use perpend_core::ext::Context;
use perpend_core::geometry::Plane;
use perpend_core::head::Sensor;
use serde::Deserialize;

/// A violation of the exchange format: where and what.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ExchangeError {
    /// File name as given by the caller.
    pub file: String,
    /// 1-based line number, when the problem is on one line.
    pub line: Option<u64>,
    /// What is wrong, in words.
    pub problem: String,
}

impl fmt::Display for ExchangeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.line {
            Some(l) => write!(f, "{}, line {}: {}", self.file, l, self.problem),
            None => write!(f, "{}: {}", self.file, self.problem),
        }
    }
}

impl std::error::Error for ExchangeError {}

fn err(file: &str, line: Option<u64>, problem: impl Into<String>) -> ExchangeError {
    ExchangeError {
        file: file.to_string(),
        line,
        problem: problem.into(),
    }
}

/// One row of `sensors.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorRow {
    /// 1-based sensor number (also the ADC scan order).
    pub sensor: usize,
    /// Nominal zero point `E_i` [mm].
    pub zero_mm: [f64; 3],
    /// Nominal beam direction as written (not necessarily unit length).
    pub dir: [f64; 3],
    /// Datasheet repeatability 1σ [mm], if given.
    pub sigma_mm: Option<f64>,
    /// Start of the measuring range [mm] (`range_min_mm`), if given; the
    /// default is [`crate::plausible::range_of`]'s.
    pub range_min_mm: Option<f64>,
    /// End of the measuring range [mm] (`range_max_mm`), if given.
    pub range_max_mm: Option<f64>,
}

impl SensorRow {
    /// The sensor with its direction normalised.
    ///
    /// # Errors
    /// Zero or non-finite direction / zero point.
    pub fn sensor(&self) -> perpend_core::Result<Sensor<f64>> {
        Sensor::new(Vector3::from(self.zero_mm), Vector3::from(self.dir))
    }
}

/// The nominal head: sensors `1..=N` in order.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SensorTable {
    /// Row `i` is sensor `i + 1`.
    pub rows: Vec<SensorRow>,
}

impl SensorTable {
    /// Number of sensors.
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    /// Whether the table is empty.
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// The sensors (directions normalised), in scan order.
    ///
    /// # Errors
    /// As [`SensorRow::sensor`] (cannot happen for a table read by
    /// [`read_sensors`], which validates).
    pub fn sensors(&self) -> perpend_core::Result<Vec<Sensor<f64>>> {
        self.rows.iter().map(SensorRow::sensor).collect()
    }

    /// A table from sensors (numbered 1..N), optionally with a repeatability.
    pub fn from_sensors(sensors: &[Sensor<f64>], sigma_mm: Option<f64>) -> Self {
        Self {
            rows: sensors
                .iter()
                .enumerate()
                .map(|(i, s)| SensorRow {
                    sensor: i + 1,
                    zero_mm: s.zero.into(),
                    dir: s.dir.into(),
                    sigma_mm,
                    range_min_mm: None,
                    range_max_mm: None,
                })
                .collect(),
        }
    }
}

/// One row of `poses.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseRow {
    /// Line in the file (0 for rows that were not read from a file).
    pub line: u64,
    /// Pose number.
    pub pose: i64,
    /// The plane `a, b, c, d` as written.
    pub abcd: [f64; 4],
    /// The plane, normalised.
    pub plane: Plane<f64>,
    /// Readings [mm] of sensors 1..N; `None` = missing.
    pub readings: Vec<Option<f64>>,
    /// Acquisition time [s], if given.
    pub t_s: Option<f64>,
    /// Head temperature [°C], if given.
    pub temp_c: Option<f64>,
    /// What the row says about its own noise (optional columns).
    pub noise: RowNoise,
}

/// The optional noise columns of a pose row: what the acquisition and the
/// tracker measured about their own scatter.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RowNoise {
    /// `s1_mm … sN_mm`: standard deviation of the samples averaged into
    /// each reading [mm] (empty when the file has none of these columns).
    pub sd_mm: Vec<Option<f64>>,
    /// `n_samples`: samples averaged into each reading.
    pub n_samples: Option<u32>,
    /// `plane_rms_mm`: RMS residual of the tracker's plane fit [mm].
    pub plane_rms_mm: Option<f64>,
    /// `plane_points`: points in that plane fit.
    pub plane_points: Option<u32>,
}

/// The poses of a run.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PoseTable {
    /// Number of reading columns `d1_mm … dN_mm`.
    pub n_sensors: usize,
    /// The rows, ordered by pose number (the reader sorts them; pose
    /// numbers are unique).
    pub rows: Vec<PoseRow>,
}

impl PoseTable {
    /// Whether any row has a time stamp.
    pub fn has_time(&self) -> bool {
        self.rows.iter().any(|r| r.t_s.is_some())
    }

    /// Whether any row has a temperature.
    pub fn has_temperature(&self) -> bool {
        self.rows.iter().any(|r| r.temp_c.is_some())
    }
}

impl Poses<f64> for PoseTable {
    fn len(&self) -> usize {
        self.rows.len()
    }
    fn sensors(&self) -> usize {
        self.n_sensors
    }
    fn plane(&self, k: usize) -> Plane<f64> {
        self.rows[k].plane
    }
    fn reading(&self, k: usize, sensor: usize) -> Option<f64> {
        self.rows[k].readings.get(sensor).copied().flatten()
    }
    fn context(&self, k: usize) -> Context<f64> {
        Context {
            temp_c: self.rows[k].temp_c,
            t_s: self.rows[k].t_s,
        }
    }
}

/// A CSV reader configured for the format (comments are removed before,
/// see [`Text`]): no header handling (done here to know the header's
/// line), trimmed fields.
fn csv_reader(text: &[u8]) -> csv::Reader<&[u8]> {
    csv::ReaderBuilder::new()
        .has_headers(false)
        .trim(csv::Trim::All)
        .flexible(false)
        .from_reader(text)
}

/// The file's text without comment and blank lines, and the original line
/// number of each remaining line. (The csv crate's record positions point
/// at the first skipped line before a record, so its line numbers are wrong
/// after comments or blank lines, and it counts a CRLF record one line
/// early; with those lines removed and every line ended by a bare LF they
/// are exact and are mapped back here.)
///
/// Physical lines end at LF, CRLF or a bare CR (old Mac files); a last
/// line without an ending counts; a UTF-8 byte-order mark is dropped.
struct Text {
    bytes: Vec<u8>,
    lines: Vec<u64>,
}

/// The physical lines of `raw` (without their endings).
fn physical_lines(raw: &[u8]) -> Vec<&[u8]> {
    let raw = raw.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(raw);
    let mut out = Vec::new();
    let mut start = 0;
    let mut i = 0;
    while i < raw.len() {
        match raw[i] {
            b'\n' => {
                out.push(&raw[start..i]);
                start = i + 1;
            }
            b'\r' => {
                out.push(&raw[start..i]);
                if raw.get(i + 1) == Some(&b'\n') {
                    i += 1;
                }
                start = i + 1;
            }
            _ => {}
        }
        i += 1;
    }
    if start < raw.len() {
        out.push(&raw[start..]);
    }
    out
}

/// A JSON text as `serde_json` counts its lines: without a UTF-8
/// byte-order mark (which it refuses as "expected value at line 1") and
/// with every bare CR turned into LF (it counts only LF, so an old-Mac
/// file would be all "line 1"). A raw CR is not allowed inside a JSON
/// string, so the change alters no valid document. CRLF is left as is.
pub fn json_text(text: &str) -> std::borrow::Cow<'_, str> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let bytes = text.as_bytes();
    let bare_cr = bytes
        .iter()
        .enumerate()
        .any(|(i, &b)| b == b'\r' && bytes.get(i + 1) != Some(&b'\n'));
    if !bare_cr {
        return std::borrow::Cow::Borrowed(text);
    }
    std::borrow::Cow::Owned(text.replace("\r\n", "\n").replace('\r', "\n"))
}

impl Text {
    fn read<R: Read>(mut r: R, file: &str) -> Result<Self, ExchangeError> {
        let mut raw = Vec::new();
        r.read_to_end(&mut raw)
            .map_err(|e| err(file, None, format!("cannot read: {e}")))?;
        let mut bytes = Vec::with_capacity(raw.len());
        let mut lines = Vec::new();
        for (n, line) in physical_lines(&raw).into_iter().enumerate() {
            let blank = line.iter().all(|b| b.is_ascii_whitespace());
            if blank || line.first() == Some(&b'#') {
                continue;
            }
            bytes.extend_from_slice(line);
            bytes.push(b'\n');
            lines.push(n as u64 + 1);
        }
        Ok(Self { bytes, lines })
    }

    /// Original 1-based line of line `l` (1-based) of the filtered text.
    fn line(&self, l: u64) -> u64 {
        let i = l.saturating_sub(1) as usize;
        self.lines
            .get(i)
            .copied()
            .unwrap_or_else(|| self.lines.last().map_or(l, |x| x + 1))
    }

    /// Original line where `rec` starts.
    fn line_of(&self, rec: &csv::StringRecord) -> u64 {
        rec.position().map_or(0, |p| self.line(p.line()))
    }
}

fn csv_error(file: &str, text: &Text, e: &csv::Error) -> ExchangeError {
    let line = |p: &Option<csv::Position>| p.as_ref().map(|p| text.line(p.line()));
    match e.kind() {
        csv::ErrorKind::UnequalLengths {
            pos,
            expected_len,
            len,
        } => err(
            file,
            line(pos),
            format!("{len} fields, but the header has {expected_len}"),
        ),
        csv::ErrorKind::Utf8 { pos, .. } => err(file, line(pos), "not valid UTF-8 text"),
        _ => err(
            file,
            e.position().map(|p| text.line(p.line())),
            format!("cannot read CSV: {e}"),
        ),
    }
}

/// Every data record after the header: its line, the typed row and the raw
/// record (for the columns found by position); the first error names file
/// and line.
fn for_each_record<T: serde::de::DeserializeOwned>(
    rdr: &mut csv::Reader<&[u8]>,
    text: &Text,
    file: &str,
    header: &csv::StringRecord,
    mut f: impl FnMut(u64, T, &csv::StringRecord) -> Result<(), ExchangeError>,
) -> Result<(), ExchangeError> {
    let mut rec = csv::StringRecord::new();
    loop {
        match rdr.read_record(&mut rec) {
            Ok(true) => {}
            Ok(false) => return Ok(()),
            Err(e) => return Err(csv_error(file, text, &e)),
        }
        let line = text.line_of(&rec);
        let r: T = rec
            .deserialize(Some(header))
            .map_err(|e| de_error(file, text, line, header, &rec, &e))?;
        f(line, r, &rec)?;
    }
}

/// The values of the columns `cols` (`None`: column absent, a missing
/// value), named `{prefix}{i}_mm` with i from 1 in errors.
fn column_values(
    file: &str,
    line: u64,
    prefix: &str,
    cols: impl Iterator<Item = Option<usize>>,
    rec: &csv::StringRecord,
) -> Result<Vec<Option<f64>>, ExchangeError> {
    cols.enumerate()
        .map(|(i, c)| {
            let name = format!("{prefix}{}_mm", i + 1);
            parse_reading(file, line, &name, c.and_then(|c| rec.get(c)).unwrap_or(""))
        })
        .collect()
}

/// Reads the header row; returns it with its line number.
fn read_header<R: Read>(
    rdr: &mut csv::Reader<R>,
    text: &Text,
    file: &str,
) -> Result<(csv::StringRecord, u64), ExchangeError> {
    let mut rec = csv::StringRecord::new();
    match rdr.read_record(&mut rec) {
        Ok(true) => {
            let line = text.line_of(&rec);
            // A UTF-8 byte order mark would otherwise stick to the first name.
            let cleaned: csv::StringRecord = rec
                .iter()
                .enumerate()
                .map(|(i, f)| {
                    if i == 0 {
                        f.trim_start_matches('\u{feff}').trim()
                    } else {
                        f.trim()
                    }
                })
                .collect();
            Ok((cleaned, line))
        }
        Ok(false) => Err(err(file, None, "empty file: no header row")),
        Err(e) => Err(csv_error(file, text, &e)),
    }
}

/// Turns a serde error of a record into "column X: problem".
fn de_error(
    file: &str,
    text: &Text,
    line: u64,
    header: &csv::StringRecord,
    rec: &csv::StringRecord,
    e: &csv::Error,
) -> ExchangeError {
    if let csv::ErrorKind::Deserialize { err: de, .. } = e.kind() {
        if let Some(i) = de.field() {
            let i = i as usize;
            let name = header.get(i).unwrap_or("?");
            let value = rec.get(i).unwrap_or("");
            let problem = if value.is_empty() {
                format!("column {name}: empty value")
            } else {
                format!("column {name}: '{value}' is not a valid number")
            };
            return err(file, Some(line), problem);
        }
        return err(file, Some(line), format!("{}", de.kind()));
    }
    csv_error(file, text, e)
}

fn require_columns(
    file: &str,
    line: u64,
    header: &csv::StringRecord,
    names: &[&str],
) -> Result<(), ExchangeError> {
    for n in names {
        if !header.iter().any(|h| h == *n) {
            let hint = if header.len() == 1 && header.iter().any(|h| h.contains(';')) {
                " (the header is one column holding `;`: this file is separated by `;`, \
                 perhaps with decimal commas; write `,` between columns and `.` as the decimal point)"
            } else {
                ""
            };
            return Err(err(file, Some(line), format!("missing column {n}{hint}")));
        }
    }
    Ok(())
}

fn check_finite(file: &str, line: u64, name: &str, v: f64) -> Result<f64, ExchangeError> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(err(
            file,
            Some(line),
            format!("column {name}: value must be a finite number, got {v}"),
        ))
    }
}

#[derive(Deserialize)]
struct SensorRecord {
    sensor: i64,
    x_mm: f64,
    y_mm: f64,
    z_mm: f64,
    m: f64,
    n: f64,
    q: f64,
    #[serde(default)]
    sigma_mm: Option<f64>,
    #[serde(default)]
    range_min_mm: Option<f64>,
    #[serde(default)]
    range_max_mm: Option<f64>,
}

/// The optional measuring range of a row: finite, non-negative, the end
/// beyond the start; empty or NaN = not given.
fn sensor_range(
    file: &str,
    line: u64,
    r: &SensorRecord,
) -> Result<(Option<f64>, Option<f64>), ExchangeError> {
    let mut out = [None, None];
    for (slot, (name, v)) in out.iter_mut().zip([
        ("range_min_mm", r.range_min_mm),
        ("range_max_mm", r.range_max_mm),
    ]) {
        *slot = match v {
            Some(x) if x.is_nan() => None,
            Some(x) if !(x.is_finite() && x >= 0.0) => {
                return Err(err(
                    file,
                    Some(line),
                    format!("column {name}: must be a non-negative distance [mm], got {x}"),
                ))
            }
            x => x,
        };
    }
    if let [Some(lo), Some(hi)] = out {
        if hi <= lo {
            return Err(err(
                file,
                Some(line),
                format!("range_max_mm {hi} is not beyond range_min_mm {lo}: give the sensor's measuring range as start, end [mm]"),
            ));
        }
    }
    Ok((out[0], out[1]))
}

/// One row of `sensors.csv` checked: sensor number from 1, finite zero
/// point and direction, a direction of non-zero length, `sigma_mm`
/// non-negative (empty or NaN: not declared).
///
/// # Errors
/// [`ExchangeError`] naming the file, the line and the column.
fn sensor_row(file: &str, line: u64, r: &SensorRecord) -> Result<SensorRow, ExchangeError> {
    if r.sensor < 1 {
        return Err(err(
            file,
            Some(line),
            format!("column sensor: sensor numbers start at 1, got {}", r.sensor),
        ));
    }
    let zero = [
        check_finite(file, line, "x_mm", r.x_mm)?,
        check_finite(file, line, "y_mm", r.y_mm)?,
        check_finite(file, line, "z_mm", r.z_mm)?,
    ];
    let dir = [
        check_finite(file, line, "m", r.m)?,
        check_finite(file, line, "n", r.n)?,
        check_finite(file, line, "q", r.q)?,
    ];
    if Vector3::from(dir).norm() < 1e-9 {
        return Err(err(
            file,
            Some(line),
            "beam direction (m, n, q) has zero length",
        ));
    }
    let sigma_mm = match r.sigma_mm {
        Some(s) if s.is_nan() => None,
        Some(s) if !(s.is_finite() && s >= 0.0) => {
            return Err(err(
                file,
                Some(line),
                format!("column sigma_mm: must be a non-negative number, got {s}"),
            ))
        }
        s => s,
    };
    let (range_min_mm, range_max_mm) = sensor_range(file, line, r)?;
    Ok(SensorRow {
        sensor: r.sensor as usize,
        zero_mm: zero,
        dir,
        sigma_mm,
        range_min_mm,
        range_max_mm,
    })
}

/// Reads `sensors.csv` from `reader`; `file` names it in errors.
///
/// # Errors
/// [`ExchangeError`] for any violation of the format.
pub fn parse_sensors<R: Read>(reader: R, file: &str) -> Result<SensorTable, ExchangeError> {
    let text = Text::read(reader, file)?;
    let mut rdr = csv_reader(&text.bytes);
    let (header, hline) = read_header(&mut rdr, &text, file)?;
    require_columns(
        file,
        hline,
        &header,
        &["sensor", "x_mm", "y_mm", "z_mm", "m", "n", "q"],
    )?;
    let mut rows: Vec<(SensorRow, u64)> = Vec::new();
    let mut rec = csv::StringRecord::new();
    loop {
        match rdr.read_record(&mut rec) {
            Ok(true) => {}
            Ok(false) => break,
            Err(e) => return Err(csv_error(file, &text, &e)),
        }
        let line = text.line_of(&rec);
        let r: SensorRecord = rec
            .deserialize(Some(&header))
            .map_err(|e| de_error(file, &text, line, &header, &rec, &e))?;
        let row = sensor_row(file, line, &r)?;
        if let Some((_, l)) = rows.iter().find(|(x, _)| x.sensor as i64 == r.sensor) {
            return Err(err(
                file,
                Some(line),
                format!("sensor {} appears twice (also on line {l})", r.sensor),
            ));
        }
        rows.push((row, line));
    }
    if rows.is_empty() {
        return Err(err(file, None, "no sensor rows"));
    }
    rows.sort_by_key(|(r, _)| r.sensor);
    for (i, (r, line)) in rows.iter().enumerate() {
        if r.sensor != i + 1 {
            return Err(err(
                file,
                Some(*line),
                format!(
                    "sensors must be numbered 1..{} without gaps: sensor {} is missing",
                    rows.len(),
                    i + 1
                ),
            ));
        }
    }
    Ok(SensorTable {
        rows: rows.into_iter().map(|(r, _)| r).collect(),
    })
}

/// Reads `sensors.csv` from a file.
///
/// # Errors
/// [`ExchangeError`] for an unreadable file or any violation of the format.
pub fn read_sensors(path: &Path) -> Result<SensorTable, ExchangeError> {
    let name = path.display().to_string();
    let f = std::fs::File::open(path).map_err(|e| err(&name, None, format!("cannot open: {e}")))?;
    parse_sensors(f, &name)
}

#[derive(Deserialize)]
struct PoseRecord {
    pose: i64,
    a: f64,
    b: f64,
    c: f64,
    d_mm: f64,
    #[serde(default)]
    t_s: Option<f64>,
    #[serde(default)]
    temp_c: Option<f64>,
    #[serde(default)]
    n_samples: Option<u32>,
    #[serde(default)]
    plane_rms_mm: Option<f64>,
    #[serde(default)]
    plane_points: Option<u32>,
}

/// Parses a reading cell: empty / NaN = missing.
fn parse_reading(
    file: &str,
    line: u64,
    name: &str,
    cell: &str,
) -> Result<Option<f64>, ExchangeError> {
    if cell.is_empty() || cell.eq_ignore_ascii_case("nan") {
        return Ok(None);
    }
    let v: f64 = cell.parse().map_err(|_| {
        err(
            file,
            Some(line),
            format!("column {name}: '{cell}' is not a valid number"),
        )
    })?;
    if !v.is_finite() {
        return Err(err(
            file,
            Some(line),
            format!("column {name}: reading must be finite or empty, got '{cell}'"),
        ));
    }
    if v < 0.0 {
        return Err(err(
            file,
            Some(line),
            format!("column {name}: negative distance {v} (readings are distances along the beam)"),
        ));
    }
    Ok(Some(v))
}

fn optional_finite(
    file: &str,
    line: u64,
    name: &str,
    v: Option<f64>,
) -> Result<Option<f64>, ExchangeError> {
    match v {
        None => Ok(None),
        Some(x) if x.is_nan() => Ok(None),
        Some(x) => check_finite(file, line, name, x).map(Some),
    }
}

/// The columns `d1_mm … dN_mm` of a header, in sensor order. With
/// `expect_sensors` the file must have exactly N of them; without, the
/// columns found decide.
fn reading_columns(
    file: &str,
    hline: u64,
    header: &csv::StringRecord,
    expect_sensors: Option<usize>,
) -> Result<Vec<usize>, ExchangeError> {
    let mut dcols: HashMap<usize, usize> = HashMap::new();
    for (idx, h) in header.iter().enumerate() {
        if let Some(num) = h.strip_prefix('d').and_then(|s| s.strip_suffix("_mm")) {
            if let Ok(i) = num.parse::<usize>() {
                if i == 0 {
                    return Err(err(
                        file,
                        Some(hline),
                        "column d0_mm: sensors are numbered from 1",
                    ));
                }
                if dcols.insert(i, idx).is_some() {
                    return Err(err(file, Some(hline), format!("column {h} appears twice")));
                }
            }
        }
    }
    let found = dcols.keys().copied().max().unwrap_or(0);
    let n = expect_sensors.unwrap_or(found);
    if n == 0 {
        return Err(err(
            file,
            Some(hline),
            "missing column d1_mm: no reading columns d1_mm … dN_mm",
        ));
    }
    for i in 1..=n {
        if !dcols.contains_key(&i) {
            return Err(err(file, Some(hline), format!("missing column d{i}_mm")));
        }
    }
    if found > n {
        return Err(err(
            file,
            Some(hline),
            format!("column d{found}_mm: the head has only {n} sensors"),
        ));
    }
    Ok((1..=n).map(|i| dcols[&i]).collect())
}

/// Reads `poses.csv` from `reader`. `expect_sensors`: the number of sensors
/// of the head (from `sensors.csv`); the file must then have exactly the
/// columns `d1_mm … dN_mm`. Without it the columns found decide.
///
/// # Errors
/// [`ExchangeError`] for any violation of the format.
pub fn parse_poses<R: Read>(
    reader: R,
    file: &str,
    expect_sensors: Option<usize>,
) -> Result<PoseTable, ExchangeError> {
    let text = Text::read(reader, file)?;
    let mut rdr = csv_reader(&text.bytes);
    let (header, hline) = read_header(&mut rdr, &text, file)?;
    require_columns(file, hline, &header, &["pose", "a", "b", "c", "d_mm"])?;
    let cols = reading_columns(file, hline, &header, expect_sensors)?;
    let n = cols.len();
    // Optional per-reading standard deviations s<i>_mm: all or none.
    let scols: Vec<Option<usize>> = (1..=n)
        .map(|i| header.iter().position(|h| h == format!("s{i}_mm")))
        .collect();
    let with_sd = scols.iter().any(Option::is_some);
    if with_sd {
        if let Some(i) = scols.iter().position(Option::is_none) {
            return Err(err(
                file,
                Some(hline),
                format!(
                    "missing column s{}_mm: give s1_mm … s{n}_mm together",
                    i + 1
                ),
            ));
        }
    }

    let mut rows: Vec<PoseRow> = Vec::new();
    for_each_record(
        &mut rdr,
        &text,
        file,
        &header,
        |line, r: PoseRecord, rec| {
            let abcd = [
                check_finite(file, line, "a", r.a)?,
                check_finite(file, line, "b", r.b)?,
                check_finite(file, line, "c", r.c)?,
                check_finite(file, line, "d_mm", r.d_mm)?,
            ];
            let plane = Plane::from_abcd(abcd[0], abcd[1], abcd[2], abcd[3])
                .ok()
                .filter(|_| Vector3::new(abcd[0], abcd[1], abcd[2]).norm() > 1e-9)
                .ok_or_else(|| {
                    err(
                        file,
                        Some(line),
                        "degenerate plane normal: (a, b, c) has zero length",
                    )
                })?;
            let readings = column_values(file, line, "d", cols.iter().map(|&c| Some(c)), rec)?;
            let sd_mm = if with_sd {
                column_values(file, line, "s", scols.iter().copied(), rec)?
            } else {
                Vec::new()
            };
            rows.push(PoseRow {
                line,
                pose: r.pose,
                abcd,
                plane,
                readings,
                t_s: optional_finite(file, line, "t_s", r.t_s)?,
                temp_c: optional_finite(file, line, "temp_c", r.temp_c)?,
                noise: RowNoise {
                    sd_mm,
                    n_samples: r.n_samples,
                    plane_rms_mm: optional_finite(file, line, "plane_rms_mm", r.plane_rms_mm)?,
                    plane_points: r.plane_points,
                },
            });
            Ok(())
        },
    )?;
    order_rows(file, &mut rows, |r| (r.pose, r.line))?;
    check_rows(file, rows.iter().map(|r| r.readings.as_slice()))?;
    Ok(PoseTable { n_sensors: n, rows })
}

/// Refuses a table without rows or without a pose of three valid readings.
fn check_rows<'a>(
    file: &str,
    mut readings: impl ExactSizeIterator<Item = &'a [Option<f64>]>,
) -> Result<(), ExchangeError> {
    if readings.len() == 0 {
        return Err(err(file, None, "no pose rows"));
    }
    if !readings.any(|r| r.iter().filter(|x| x.is_some()).count() >= 3) {
        return Err(err(
            file,
            None,
            "no pose has three valid readings: a normal needs three",
        ));
    }
    Ok(())
}

/// Sorts the rows by pose number (rows may come in any order) and refuses
/// a pose number that appears twice, naming both lines; `key` gives a
/// row's `(pose, line)`.
fn order_rows<R>(
    file: &str,
    rows: &mut [R],
    key: impl Fn(&R) -> (i64, u64),
) -> Result<(), ExchangeError> {
    rows.sort_by_key(&key);
    for w in rows.windows(2) {
        let ((p0, l0), (p1, l1)) = (key(&w[0]), key(&w[1]));
        if p0 == p1 {
            return Err(err(
                file,
                Some(l1),
                format!("pose {p1} appears twice (also on line {l0}): pose numbers are unique"),
            ));
        }
    }
    Ok(())
}

/// Reads `poses.csv` from a file (see [`parse_poses`]).
///
/// # Errors
/// [`ExchangeError`] for an unreadable file or any violation of the format.
pub fn read_poses(path: &Path, expect_sensors: Option<usize>) -> Result<PoseTable, ExchangeError> {
    let name = path.display().to_string();
    let f = std::fs::File::open(path).map_err(|e| err(&name, None, format!("cannot open: {e}")))?;
    parse_poses(f, &name, expect_sensors)
}

/// One row of a readings file (what `perpend measure` reads): a row of
/// `poses.csv` whose plane columns are absent or ignored.
#[derive(Debug, Clone, PartialEq)]
pub struct ReadingRow {
    /// Line in the file.
    pub line: u64,
    /// Pose number.
    pub pose: i64,
    /// Readings [mm] of sensors 1..N; `None` = missing.
    pub readings: Vec<Option<f64>>,
    /// Acquisition time [s], if given.
    pub t_s: Option<f64>,
    /// Head temperature [°C], if given.
    pub temp_c: Option<f64>,
}

impl ReadingRow {
    /// The context of the extension corrections (temperature, time).
    pub fn context(&self) -> Context<f64> {
        Context {
            temp_c: self.temp_c,
            t_s: self.t_s,
        }
    }
}

/// The rows of a readings file, ordered by pose number.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ReadingTable {
    /// Number of reading columns `d1_mm … dN_mm`.
    pub n_sensors: usize,
    /// The rows, ordered by pose number (unique).
    pub rows: Vec<ReadingRow>,
}

#[derive(Deserialize)]
struct ReadingRecord {
    pose: i64,
    #[serde(default)]
    t_s: Option<f64>,
    #[serde(default)]
    temp_c: Option<f64>,
}

/// Reads a readings file: the columns of `poses.csv` without the plane.
/// `pose` and `d1_mm … dN_mm` are required, `t_s` and `temp_c` used when
/// present; `a, b, c, d_mm` and every other column are ignored (a
/// calibration run can be measured as it is). The rules of
/// [`parse_poses`] otherwise hold: comments, any column order, empty or
/// `NaN` = missing, unique pose numbers, at least one pose with three
/// valid readings.
///
/// # Errors
/// [`ExchangeError`] for any violation of the format.
pub fn parse_readings<R: Read>(
    reader: R,
    file: &str,
    expect_sensors: Option<usize>,
) -> Result<ReadingTable, ExchangeError> {
    let text = Text::read(reader, file)?;
    let mut rdr = csv_reader(&text.bytes);
    let (header, hline) = read_header(&mut rdr, &text, file)?;
    require_columns(file, hline, &header, &["pose"])?;
    let cols = reading_columns(file, hline, &header, expect_sensors)?;
    let mut rows: Vec<ReadingRow> = Vec::new();
    for_each_record(
        &mut rdr,
        &text,
        file,
        &header,
        |line, r: ReadingRecord, rec| {
            rows.push(ReadingRow {
                line,
                pose: r.pose,
                readings: column_values(file, line, "d", cols.iter().map(|&c| Some(c)), rec)?,
                t_s: optional_finite(file, line, "t_s", r.t_s)?,
                temp_c: optional_finite(file, line, "temp_c", r.temp_c)?,
            });
            Ok(())
        },
    )?;
    order_rows(file, &mut rows, |r| (r.pose, r.line))?;
    check_rows(file, rows.iter().map(|r| r.readings.as_slice()))?;
    Ok(ReadingTable {
        n_sensors: cols.len(),
        rows,
    })
}

/// Reads a readings file (see [`parse_readings`]).
///
/// # Errors
/// [`ExchangeError`] for an unreadable file or any violation of the format.
pub fn read_readings(
    path: &Path,
    expect_sensors: Option<usize>,
) -> Result<ReadingTable, ExchangeError> {
    let name = path.display().to_string();
    let f = std::fs::File::open(path).map_err(|e| err(&name, None, format!("cannot open: {e}")))?;
    parse_readings(f, &name, expect_sensors)
}

fn num(x: f64) -> String {
    // `+ 0.0` turns a negative zero into 0 (no "-0" in the files).
    format!("{}", x + 0.0)
}

fn opt(x: Option<f64>) -> String {
    x.map(num).unwrap_or_default()
}

/// Writes `sensors.csv`, preceded by `# ` comment lines.
///
/// # Errors
/// I/O errors.
pub fn write_sensors<W: Write>(
    mut w: W,
    table: &SensorTable,
    comments: &[String],
) -> std::io::Result<()> {
    for c in comments {
        writeln!(w, "# {c}")?;
    }
    let with_sigma = table.rows.iter().any(|r| r.sigma_mm.is_some());
    let with_range = table
        .rows
        .iter()
        .any(|r| r.range_min_mm.is_some() || r.range_max_mm.is_some());
    let mut cw = csv::WriterBuilder::new().from_writer(w);
    let mut head = vec!["sensor", "x_mm", "y_mm", "z_mm", "m", "n", "q"];
    if with_sigma {
        head.push("sigma_mm");
    }
    if with_range {
        head.extend(["range_min_mm", "range_max_mm"]);
    }
    cw.write_record(&head)?;
    for r in &table.rows {
        let mut rec = vec![
            r.sensor.to_string(),
            num(r.zero_mm[0]),
            num(r.zero_mm[1]),
            num(r.zero_mm[2]),
            num(r.dir[0]),
            num(r.dir[1]),
            num(r.dir[2]),
        ];
        if with_sigma {
            rec.push(opt(r.sigma_mm));
        }
        if with_range {
            rec.extend([opt(r.range_min_mm), opt(r.range_max_mm)]);
        }
        cw.write_record(&rec)?;
    }
    cw.flush()
}

/// Writes `poses.csv` (with `t_s` / `temp_c` columns when any row has
/// them), preceded by `# ` comment lines.
///
/// # Errors
/// I/O errors.
pub fn write_poses<W: Write>(
    mut w: W,
    table: &PoseTable,
    comments: &[String],
) -> std::io::Result<()> {
    for c in comments {
        writeln!(w, "# {c}")?;
    }
    let (ht, htemp) = (table.has_time(), table.has_temperature());
    let mut cw = csv::WriterBuilder::new().from_writer(w);
    let mut head: Vec<String> = ["pose", "a", "b", "c", "d_mm"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    head.extend((1..=table.n_sensors).map(|i| format!("d{i}_mm")));
    if ht {
        head.push("t_s".into());
    }
    if htemp {
        head.push("temp_c".into());
    }
    let hsd = table.rows.iter().any(|r| !r.noise.sd_mm.is_empty());
    if hsd {
        head.extend((1..=table.n_sensors).map(|i| format!("s{i}_mm")));
    }
    let hn = table.rows.iter().any(|r| r.noise.n_samples.is_some());
    let hp = table.rows.iter().any(|r| r.noise.plane_rms_mm.is_some());
    let hpp = table.rows.iter().any(|r| r.noise.plane_points.is_some());
    for (on, name) in [
        (hn, "n_samples"),
        (hp, "plane_rms_mm"),
        (hpp, "plane_points"),
    ] {
        if on {
            head.push(name.into());
        }
    }
    cw.write_record(&head)?;
    for r in &table.rows {
        let mut rec: Vec<String> = vec![r.pose.to_string()];
        rec.extend(r.abcd.iter().map(|&x| num(x)));
        rec.extend((0..table.n_sensors).map(|i| opt(r.readings.get(i).copied().flatten())));
        if ht {
            rec.push(opt(r.t_s));
        }
        if htemp {
            rec.push(opt(r.temp_c));
        }
        if hsd {
            rec.extend((0..table.n_sensors).map(|i| opt(r.noise.sd_mm.get(i).copied().flatten())));
        }
        let int = |x: Option<u32>| x.map(|v| v.to_string()).unwrap_or_default();
        if hn {
            rec.push(int(r.noise.n_samples));
        }
        if hp {
            rec.push(opt(r.noise.plane_rms_mm));
        }
        if hpp {
            rec.push(int(r.noise.plane_points));
        }
        cw.write_record(&rec)?;
    }
    cw.flush()
}

/// Writes `sensors.csv` and `poses.csv` into `dir` (created if needed).
///
/// # Errors
/// I/O errors, with the path.
pub fn write_dataset(
    dir: &Path,
    sensors: &SensorTable,
    poses: &PoseTable,
    comments: &[String],
) -> anyhow::Result<()> {
    use anyhow::Context as _;
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let sp = dir.join("sensors.csv");
    let f = std::fs::File::create(&sp).with_context(|| format!("cannot write {}", sp.display()))?;
    write_sensors(std::io::BufWriter::new(f), sensors, comments)
        .with_context(|| format!("cannot write {}", sp.display()))?;
    let pp = dir.join("poses.csv");
    let f = std::fs::File::create(&pp).with_context(|| format!("cannot write {}", pp.display()))?;
    write_poses(std::io::BufWriter::new(f), poses, comments)
        .with_context(|| format!("cannot write {}", pp.display()))?;
    Ok(())
}
