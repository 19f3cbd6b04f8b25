//! `perpend node push` and `pull`: a params.json into the board's
//! calibration objects and back.
//!
//! Push, in this order, stopping at the first problem:
//! 1. read and check the file (`ParamFile::read`), its sensor count against
//!    the board's (0x2004 sub 0), every value against the range the board
//!    accepts (nothing is written if one is out);
//! 2. the NMT state from the heartbeat: a board in operational (or
//!    stopped) is refused unless `--preop`, which switches it to
//!    pre-operational (the robot controller may be using its PDOs);
//! 3. unlock (0x2010 ← "ucal"), write every value of 0x2101.. (25 per
//!    sensor: sub 1..15, the linearity table's knots 16..20 and
//!    values 21..23, zeros when the file has no table, the spot
//!    coefficients 24..25 from `ext.spot_mm`, zeros when absent; firmware
//!    before them, sub 0 = 23, is refused when the file has spot terms and
//!    gets sub 1..23 when not), the head's thermal
//!    time constant 0x2105 (`thermal_tau_s`; firmware without the object
//!    is refused when the file has τ > 0 and left alone when τ = 0) and,
//!    when the file has them, 0x2201.. (4 per sensor), then read each one
//!    back and
//!    compare bit for bit; check that the board finds the result valid
//!    (status bit 21 clear). The board refuses knots that are not
//!    ascending under an active table, so a table whose knots change is
//!    switched off first (its coefficients zeroed), then the knots and the
//!    coefficients are written;
//! 4. stamp the calibration (0x2011 sub 1 ← the first 4 bytes, big-endian,
//!    of the SHA-256 of the calibration record's bytes where the caller
//!    has one ([`push_with_record`]), else of the params file's;
//!    sub 2 ← UTC seconds now) and read it back; a firmware without the
//!    object (abort 0x06020000 on the first write) is pushed without a
//!    stamp, and the report says so;
//! 5. store (0x1010 sub 3 "save application parameters" where the firmware
//!    has it, else sub 1 "save all"; answered after the flash write), reset node,
//!    wait for the boot-up, read everything back again (the stamp
//!    included, with the board's store count 0x2011 sub 3), lock
//!    (0x2010 ← 0).
//!
//! Nothing is stored before every value was written and verified: a
//! failure or Ctrl-C before step 5 relocks the board and resets it, so it
//! runs its previous stored calibration again, and says so.
//!
//! Pull reads the same objects into a params.json (`method` "board",
//! `model` from the non-zero extension terms, `linearity_table` when a
//! coefficient is non-zero, `thermal_tau_s` from 0x2105, 0 on firmware
//! without it, `calibration_stamp` from 0x2011 when the board has a
//! non-zero one; push ignores it) that push and
//! `ParamFile::read` accept; a beam direction the board holds with a
//! length off 1 by more than 1e-6 is normalised in the file (the board
//! normalises it too) with a warning.

use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{anyhow, bail, Context as _, Result};
use perpend_can::config::{CAL_SUB_COEFFS, CAL_SUB_KNOTS, CAL_SUB_SPOT, CAL_VALUES};
use perpend_can::od::{self, Limits, SAVE_SIGNATURE, UNLOCK_SIGNATURE};
use perpend_formats::paramfile::{
    CalibrationStamp, ExtParams, ParamFile, SensorParams, TableParams, TransferParams,
    TRANSFER_CURRENT, TRANSFER_VOLTAGE,
};
use perpend_formats::progress::Progress;
use sha2::{Digest as _, Sha256};

use super::Node;
use crate::canopen::NodeState;

/// Options of `push`.
#[derive(clap::Args, Debug)]
pub struct PushArgs {
    /// The calibration file (`perpend calibrate --out`, `perpend node pull`).
    pub file: PathBuf,
    /// Switch a board found operational (or stopped) to pre-operational
    /// for the push (without it, such a board is refused).
    #[arg(long)]
    pub preop: bool,
    /// The calibration record whose hash stamps the board (0x2011); by
    /// default the record `perpend calibrate --out` wrote beside the file
    /// (`params.record.json`), else the file itself.
    #[arg(long, value_name = "FILE")]
    pub record: Option<PathBuf>,
}

/// Options of `pull`.
#[derive(clap::Args, Debug)]
pub struct PullArgs {
    /// Write the file here (default: standard output).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Names of the calibration sub-indices 1..25.
const CAL_NAMES: [&str; CAL_VALUES] = [
    "zero x",
    "zero y",
    "zero z",
    "direction x",
    "direction y",
    "direction z",
    "d_ref",
    "gain",
    "nonlinearity 2",
    "nonlinearity 3",
    "incidence",
    "crosstalk",
    "thermal",
    "temp_ref",
    "drift",
    "linearity table knot 0",
    "linearity table knot 1",
    "linearity table knot 2",
    "linearity table knot 3",
    "linearity table knot 4",
    "linearity table value 0",
    "linearity table value 1",
    "linearity table value 2",
    "spot cos",
    "spot sin",
];
/// Index of the first knot and the first coefficient in the calibration
/// values (sub-index − 1).
const KNOT0: usize = CAL_SUB_KNOTS as usize - 1;
const COEFF0: usize = CAL_SUB_COEFFS as usize - 1;
/// Index of the first spot coefficient in the calibration values.
const SPOT0: usize = CAL_SUB_SPOT as usize - 1;
/// Names of the transfer-function sub-indices 1..4.
const TF_NAMES: [&str; 4] = ["kind", "scale", "mm at 4 mA / 0 V", "mm at 20 mA / 10 V"];

/// How long the store (flash write) may take.
const STORE_TIMEOUT: Duration = Duration::from_secs(5);
/// How long a reset may take until the boot-up.
const BOOT_TIMEOUT: Duration = Duration::from_secs(5);

/// One value to write.
#[derive(Debug, Clone, PartialEq)]
pub struct Value {
    /// Object.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// The bytes (little endian).
    pub bytes: Vec<u8>,
    /// `sensor 2 gain`, for messages.
    pub label: String,
    /// The value as the file has it, for messages.
    pub shown: f64,
}

/// What a push did.
#[derive(Debug, Clone, PartialEq)]
pub struct PushReport {
    /// `node N on BUS`.
    pub node: String,
    /// Values written and verified.
    pub values: usize,
    /// Of these, how many differed from what the board held before.
    pub changed: usize,
    /// Whether the board was switched from operational to pre-operational.
    pub switched: bool,
    /// Whether the file had transfer functions.
    pub transfer: bool,
    /// The calibration stamp as read back after the reset (`None`: the
    /// firmware has no 0x2011).
    pub stamp: Option<Stamp>,
}

/// The calibration stamp 0x2011.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stamp {
    /// Sub 1: the first 4 bytes (big-endian) of the record's SHA-256.
    pub record_hash: u32,
    /// Sub 2: UTC seconds since 1970 of the push.
    pub utc_s: u32,
    /// Sub 3: the board's count of calibration stores.
    pub store_count: u32,
}

impl Stamp {
    /// `utc_s` in ISO 8601 (`2026-11-27T10:58:43Z`).
    pub fn utc(&self) -> String {
        let t = std::time::UNIX_EPOCH + Duration::from_secs(self.utc_s.into());
        humantime::format_rfc3339_seconds(t).to_string()
    }

    /// The stamp as a parameter file holds it.
    pub fn to_file(&self) -> CalibrationStamp {
        CalibrationStamp {
            record_hash: format!("{:08x}", self.record_hash),
            utc: self.utc(),
            utc_s: self.utc_s,
            store_count: self.store_count,
        }
    }
}

impl fmt::Display for Stamp {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "stamp {:08x} stored {}, store #{}",
            self.record_hash,
            self.utc(),
            self.store_count
        )
    }
}

impl fmt::Display for PushReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "push: {} values written to {} ({} changed{}), read back identical, stored \
             (0x1010), node reset, read back identical after the boot-up; calibration locked",
            self.values,
            self.node,
            self.changed,
            if self.transfer {
                ", transfer functions included"
            } else {
                "; the file has no transfer functions, 0x2201.. left as they were"
            }
        )?;
        match &self.stamp {
            Some(st) => write!(f, "\n{st}")?,
            None => write!(
                f,
                "\nno calibration stamp: the firmware of {} has no 0x2011 (the calibration \
                 was stored without one)",
                self.node
            )?,
        }
        if self.switched {
            write!(
                f,
                "\nthe node was operational and is pre-operational now: `perpend node … nmt \
                 start` starts it again"
            )?;
        }
        Ok(())
    }
}

fn real(index: u16, sub: u8, label: String, v: f64) -> Result<Value> {
    let x = v as f32;
    let (_, e) = od::find(index, sub).map_err(|_| anyhow!("{index:#06x} sub {sub} unknown"))?;
    if let Limits::Real(lo, hi) = e.limits {
        if !(x.is_finite() && x >= lo && x <= hi) {
            bail!(
                "{label} = {v} is outside what the board accepts ({lo} to {hi}); nothing was \
                 written"
            );
        }
    }
    Ok(Value {
        index,
        sub,
        bytes: x.to_le_bytes().to_vec(),
        label,
        shown: v,
    })
}

/// The values of sub 1..25 (a missing table or spot as zeros: none).
fn calibration_values(s: &SensorParams) -> [f64; CAL_VALUES] {
    let e = &s.ext;
    let t = e.linearity_table.unwrap_or(TableParams {
        knots_mm: [0.0; 5],
        values_mm: [0.0; 3],
    });
    let [k0, k1, k2, k3, k4] = t.knots_mm;
    let [c0, c1, c2] = t.values_mm;
    let [s0, s1] = e.spot_mm.unwrap_or([0.0; 2]);
    [
        s.zero_mm[0],
        s.zero_mm[1],
        s.zero_mm[2],
        s.dir[0],
        s.dir[1],
        s.dir[2],
        e.d_ref_mm,
        e.gain,
        e.nonlinearity[0],
        e.nonlinearity[1],
        e.incidence_mm,
        e.crosstalk,
        e.thermal_mm_per_c,
        e.temp_ref_c,
        e.drift_mm_per_s,
        k0,
        k1,
        k2,
        k3,
        k4,
        c0,
        c1,
        c2,
        s0,
        s1,
    ]
}

/// Refuses a table the board would refuse: active (a coefficient non-zero
/// in `f32`) with knots not strictly ascending in `f32` (knots closer than
/// `f32` resolves collapse).
fn check_table(i: usize, c: &[f64; CAL_VALUES]) -> Result<()> {
    let f = |k: usize| c[k] as f32;
    let active = (COEFF0..SPOT0).any(|k| f(k) != 0.0);
    if active && !(KNOT0..COEFF0 - 1).all(|k| f(k + 1) > f(k)) {
        bail!(
            "sensor {} linearity table: the knots {:?} are not strictly ascending as the board \
             holds them (REAL32); nothing was written",
            i + 1,
            &c[KNOT0..COEFF0]
        );
    }
    Ok(())
}

/// The head's thermal time constant (`thermal_tau_s`).
pub const TAU_INDEX: u16 = 0x2105;

/// Every value of the file, checked against the board's ranges: per
/// sensor its calibration and transfer function, then the head's thermal
/// time constant ([`TAU_INDEX`]).
///
/// # Errors
/// A value the board would refuse, named.
pub fn plan(file: &ParamFile) -> Result<Vec<Value>> {
    let mut out = Vec::new();
    for (i, s) in file.sensors.iter().enumerate() {
        let index = 0x2101 + i as u16;
        let c = calibration_values(s);
        check_table(i, &c)?;
        for (k, v) in c.into_iter().enumerate() {
            let label = format!("sensor {} {}", i + 1, CAL_NAMES[k]);
            out.push(real(index, k as u8 + 1, label, v)?);
        }
        if let Some(t) = &s.transfer {
            let index = 0x2201 + i as u16;
            let kind = u8::from(t.kind == TRANSFER_VOLTAGE);
            out.push(Value {
                index,
                sub: 1,
                bytes: vec![kind],
                label: format!("sensor {} transfer kind", i + 1),
                shown: kind as f64,
            });
            for (k, v) in [t.scale, t.mm_at_low, t.mm_at_high].into_iter().enumerate() {
                let label = format!("sensor {} transfer {}", i + 1, TF_NAMES[k + 1]);
                out.push(real(index, k as u8 + 2, label, v)?);
            }
        }
    }
    let label = "thermal_tau_s (head thermal time constant)".to_string();
    out.push(real(TAU_INDEX, 0, label, file.thermal_tau_s)?);
    Ok(out)
}

/// Drops the thermal time constant from `values` when the board's
/// firmware has no 0x2105 and the file asks for no lag; refuses a lag it
/// cannot hold. The same for the spot coefficients ([`fit_spot`]).
fn fit_to_board(node: &mut Node, file: &ParamFile, values: &mut Vec<Value>) -> Result<()> {
    fit_spot(node, file, values)?;
    match node.client.upload(node.id, TAU_INDEX, 0) {
        Err(e) if e.abort_code() == Some(0x0602_0000) => {
            if file.thermal_tau_s != 0.0 {
                bail!(
                    "the file has thermal_tau_s = {} s, but {} has no thermal time constant \
                     (0x2105: firmware before it); nothing was written",
                    file.thermal_tau_s,
                    node.name()
                );
            }
            values.retain(|v| v.index != TAU_INDEX);
            Ok(())
        }
        r => r.map(|_| ()).map_err(Into::into),
    }
}

/// Drops the spot coefficients (0x2101.. sub 24..25) from `values` when
/// the board's firmware has none (0x2101 sub 0 below 25) and the file has
/// none either; refuses spot terms the board cannot hold (it would keep
/// whatever its stored record has).
fn fit_spot(node: &mut Node, file: &ParamFile, values: &mut Vec<Value>) -> Result<()> {
    let highest = node.client.read_u32(node.id, 0x2101, 0)?;
    if highest > u32::from(CAL_SUB_SPOT) {
        return Ok(());
    }
    if let Some(s) = file.sensors.iter().find(|s| s.ext.spot_mm.is_some()) {
        bail!(
            "sensor {} has ext.spot_mm {:?}, but {} has no spot objects (0x2101 sub 0 = \
             {highest}: firmware before 0x2101..0x2104 sub 24/25) and would keep the spot \
             terms of its stored record; update its firmware or drop the spot terms. Nothing \
             was written",
            s.sensor,
            s.ext.spot_mm.unwrap_or_default(),
            node.name()
        );
    }
    let cal = 0x2101..=0x2104u16;
    values.retain(|v| !(cal.contains(&v.index) && v.sub >= CAL_SUB_SPOT));
    Ok(())
}

/// The calibration stamp object (record hash, UTC seconds, store count).
pub const STAMP_INDEX: u16 = 0x2011;

/// The first 4 bytes, big-endian, of the SHA-256 of `bytes`.
pub fn record_hash(bytes: &[u8]) -> u32 {
    let d = Sha256::digest(bytes);
    u32::from_be_bytes([d[0], d[1], d[2], d[3]])
}

/// [`record_hash`] of a file's bytes.
fn file_hash(path: &Path) -> Result<u32> {
    let bytes = std::fs::read(path)
        .with_context(|| format!("{}: cannot read; nothing was written", path.display()))?;
    Ok(record_hash(&bytes))
}

/// UTC seconds since 1970, now (0 before 1970, `u32::MAX` after 2106).
fn utc_now_s() -> u32 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u32::try_from(d.as_secs()).unwrap_or(u32::MAX))
}

/// The stamp's host-written values: sub 1 the record hash, sub 2 the UTC
/// seconds.
fn stamp_values(hash: u32, utc_s: u32) -> [Value; 2] {
    let v = |sub: u8, x: u32, what: &str| Value {
        index: STAMP_INDEX,
        sub,
        bytes: x.to_le_bytes().to_vec(),
        label: format!("calibration stamp {what}"),
        shown: x.into(),
    };
    [v(1, hash, "record hash"), v(2, utc_s, "UTC seconds")]
}

/// Writes the stamp and reads it back; `false`: the firmware has no
/// 0x2011 (abort 0x06020000 on the first write), nothing written.
fn write_stamp(node: &mut Node, stamp: &[Value], bar: &Progress) -> Result<bool> {
    for (k, v) in stamp.iter().enumerate() {
        match node.client.download(node.id, v.index, v.sub, &v.bytes) {
            Err(e) if k == 0 && e.abort_code() == Some(0x0602_0000) => return Ok(false),
            r => r.with_context(|| format!("writing the {}", v.label))?,
        }
        bar.inc();
    }
    verify(node, stamp, bar, "after writing")?;
    Ok(true)
}

/// The board's calibration stamp (`None`: its firmware has no 0x2011).
///
/// # Errors
/// Client errors.
pub fn read_stamp(node: &mut Node) -> Result<Option<Stamp>> {
    let (c, id) = (&mut node.client, node.id);
    let record_hash = match c.read_u32(id, STAMP_INDEX, 1) {
        Ok(h) => h,
        Err(e) if e.abort_code() == Some(0x0602_0000) => return Ok(None),
        Err(e) => return Err(e.into()),
    };
    Ok(Some(Stamp {
        record_hash,
        utc_s: c.read_u32(id, STAMP_INDEX, 2)?,
        store_count: c.read_u32(id, STAMP_INDEX, 3)?,
    }))
}

/// Makes sure the node is pre-operational; returns whether it was switched.
fn ensure_preop(node: &mut Node, allow: bool) -> Result<bool> {
    let hb = node.heartbeat_ms()?;
    match node.state(hb)? {
        Some(s @ (NodeState::Operational | NodeState::Stopped)) if !allow => bail!(
            "{} is {s}: the board takes calibration only in pre-operational, and the robot \
             controller may be using it now. Nothing was written. Rerun with --preop to switch \
             it to pre-operational for the push (after the push's reset it stays \
             pre-operational; `perpend node … nmt start` starts it again)",
            node.name()
        ),
        Some(NodeState::Operational | NodeState::Stopped) => {
            node.client.nmt(node.id, crate::canopen::Nmt::Preop)?;
            let _ = node
                .client
                .wait_heartbeat(node.id, Duration::from_millis(hb + 200))?;
            Ok(true)
        }
        _ => Ok(false),
    }
}

/// Unlocks calibration writes and checks the board says so.
fn unlock(node: &mut Node, allow: bool) -> Result<()> {
    let id = node.id;
    match node.client.write_u32(id, 0x2010, 0, UNLOCK_SIGNATURE) {
        Ok(()) => {}
        Err(e) if e.abort_code() == Some(0x0800_0022) && !allow => bail!(
            "{} refuses the unlock in its present NMT state (operational, heartbeat off): \
             nothing was written; rerun with --preop to switch it to pre-operational",
            node.name()
        ),
        Err(e) => return Err(e.into()),
    }
    if node.client.read_u32(id, 0x2010, 0)? != 1 {
        bail!(
            "{}: 0x2010 does not read as unlocked after the unlock",
            node.name()
        );
    }
    Ok(())
}

/// Reads each value back; `Err` names the first that differs.
fn verify(node: &mut Node, values: &[Value], bar: &Progress, when: &str) -> Result<()> {
    for v in values {
        let got = node.client.upload(node.id, v.index, v.sub)?;
        bar.inc();
        if got != v.bytes {
            let shown = match <[u8; 4]>::try_from(got.as_slice()) {
                Ok(b) if v.index == STAMP_INDEX => u32::from_le_bytes(b).to_string(),
                Ok(b) => f32::from_le_bytes(b).to_string(),
                Err(_) => format!("{got:02x?}"),
            };
            bail!(
                "{} reads back as {shown} {when}, {} was written ({:#06x} sub {})",
                v.label,
                v.shown,
                v.index,
                v.sub
            );
        }
    }
    Ok(())
}

/// Writes every value (checking `cancel` before each); returns how many
/// differed from what the board held. A sensor's active table whose knots
/// change is switched off first ([`clear_table`]).
fn write_all(
    node: &mut Node,
    values: &[Value],
    cancel: &AtomicBool,
    bar: &Progress,
) -> Result<usize> {
    let before = values
        .iter()
        .map(|v| node.client.upload(node.id, v.index, v.sub))
        .collect::<Result<Vec<_>, _>>()?;
    let changed = values
        .iter()
        .zip(&before)
        .filter(|(v, b)| v.bytes != **b)
        .count();
    for (k, v) in values.iter().enumerate() {
        if cancel.load(Ordering::SeqCst) {
            bail!("interrupted (Ctrl-C) after {k} of {} writes", values.len());
        }
        if v.sub == CAL_SUB_KNOTS && (0x2101..=0x2104).contains(&v.index) {
            clear_table(node, values, &before, v.index)?;
        }
        node.client
            .download(node.id, v.index, v.sub, &v.bytes)
            .with_context(|| format!("writing {}", v.label))?;
        bar.inc();
    }
    Ok(changed)
}

/// Zeroes the coefficients of the table in `index` when the board holds
/// an active one (`before`, as read) and the push changes its knots: the
/// board refuses knots out of order under an active table, and the knots
/// pass through intermediate orders while they are written one by one.
fn clear_table(node: &mut Node, values: &[Value], before: &[Vec<u8>], index: u16) -> Result<()> {
    let zero = 0f32.to_le_bytes();
    let mut knots_change = false;
    let mut active = false;
    for (v, b) in values.iter().zip(before).filter(|(v, _)| v.index == index) {
        if (CAL_SUB_KNOTS..CAL_SUB_COEFFS).contains(&v.sub) {
            knots_change |= v.bytes != *b;
        } else if (CAL_SUB_COEFFS..CAL_SUB_SPOT).contains(&v.sub) {
            active |= <[u8; 4]>::try_from(b.as_slice()).is_ok_and(|x| f32::from_le_bytes(x) != 0.0);
        }
    }
    if knots_change && active {
        for sub in CAL_SUB_COEFFS..CAL_SUB_COEFFS + 3 {
            node.client
                .download(node.id, index, sub, &zero)
                .with_context(|| format!("switching off the linearity table of {index:#06x}"))?;
        }
    }
    Ok(())
}

/// Waits for a sample newer than now and checks the board finds its
/// calibration valid (status bit 21 clear).
fn check_valid(node: &mut Node) -> Result<()> {
    let id = node.id;
    let n0 = node.client.read_u32(id, 0x2007, 0)?;
    let end = Instant::now() + Duration::from_secs(2);
    while node.client.read_u32(id, 0x2007, 0)? == n0 && Instant::now() < end {
        std::thread::sleep(Duration::from_millis(2));
    }
    let st = node.client.read_u32(id, 0x2005, 0)?;
    if st & perpend_can::status::CONFIG_INVALID != 0 {
        bail!(
            "the board finds the written calibration invalid (status bit 21: a combination \
             its checks refuse, e.g. a transfer function outside its front end's range or a \
             linearity table it cannot use)"
        );
    }
    Ok(())
}

/// After a failure before the store: lock, reset, wait for the boot-up.
/// Returns what the board is left with, in words.
fn abandon(node: &mut Node) -> String {
    let id = node.id;
    let _ = node.client.write_u32(id, 0x2010, 0, 0);
    let reset = node
        .client
        .nmt(id, crate::canopen::Nmt::Reset)
        .map_err(anyhow::Error::from)
        .and_then(|()| Ok(node.client.wait_bootup(id, BOOT_TIMEOUT)?));
    match reset {
        Ok(()) => format!(
            "nothing was stored: {} was reset and runs its previous stored calibration again",
            node.name()
        ),
        Err(_) => format!(
            "nothing was stored, but {} did not confirm its reset: reset it (NMT reset or power) \
             before use, its dictionary may hold values that were not stored",
            node.name()
        ),
    }
}

/// `perpend node push`: [`push_with_record`] stamping the hash of
/// `--record`, else of the record beside the file
/// ([`perpend_calib::record::record_path`]) when there is one, else of the
/// file itself. A file `pull` wrote and no record puts its stamp back
/// (`calibration_stamp`, or none): pushing a board's own calibration back
/// (the cell run's revert) restores what it carried.
///
/// # Errors
/// As [`push_with_record`].
pub fn push(node: &mut Node, a: &PushArgs, cancel: &AtomicBool) -> Result<PushReport> {
    let beside = perpend_calib::record::record_path(&a.file);
    let record = match (&a.record, beside.exists()) {
        (Some(r), _) => Some(r.clone()),
        (None, true) => Some(beside),
        (None, false) => write_push_record(node, &a.file)?,
    };
    push_with_record(node, a, record.as_deref(), cancel)
}

/// A file with no record beside it (written by hand or by another tool)
/// gets one before it is pushed: the file as its input, the board it goes
/// to (serial 0x1018 sub 4, software 0x100A), not verified; its hash
/// stamps the board. A file `pull` wrote gets none (it keeps its own
/// stamp).
///
/// # Errors
/// The file or the record cannot be read or written; client errors.
fn write_push_record(node: &mut Node, file: &Path) -> Result<Option<PathBuf>> {
    use perpend_calib::record::{Record, Verification};
    let f = ParamFile::read(file)?;
    if f.method == "board" {
        return Ok(None);
    }
    node.hello()?;
    let serial = format!("{:#010x}", node.client.read_u32(node.id, 0x1018, 4)?);
    let firmware = node.client.read_string(node.id, 0x100A, 0)?;
    let mut r = Record::new(&[file], &f)?
        .with_board(&serial, &firmware)
        .with_verification(Verification::expected_only(
            "pushed by `perpend node push` from a file without a record: not verified",
        ));
    r.push_event(&format!(
        "written for `perpend node push` to {}",
        node.name()
    ));
    let path = r.write_beside(file)?;
    println!(
        "push: calibration record {} written (the file had none)",
        path.display()
    );
    Ok(Some(path))
}

/// A push whose calibration stamp (0x2011) takes the hash of `record`,
/// the calibration record written beside the parameter file (`None`: of
/// the parameter file itself).
///
/// # Errors
/// Every refusal and failure in a sentence that says what the board is
/// left with.
pub fn push_with_record(
    node: &mut Node,
    a: &PushArgs,
    record: Option<&Path>,
    cancel: &AtomicBool,
) -> Result<PushReport> {
    let file = ParamFile::read(&a.file)?;
    node.hello()?;
    let n = node.sensors()?;
    if file.sensors.len() != n {
        bail!(
            "{} has {} sensors, {} has {n} (0x2004 sub 0): the file is for another head; \
             nothing was written",
            a.file.display(),
            file.sensors.len(),
            node.name()
        );
    }
    let mut values = plan(&file).with_context(|| a.file.display().to_string())?;
    // A file `pull` wrote (method "board") and no record: its own stamp
    // back (none stays none), so pushing a board's calibration back
    // restores what the board carried.
    let (hash, utc_s) = match (record, &file.calibration_stamp) {
        (None, Some(st)) => (
            u32::from_str_radix(&st.record_hash, 16)
                .with_context(|| format!("{}: calibration_stamp", a.file.display()))?,
            st.utc_s,
        ),
        (None, None) if file.method == "board" => (0, 0),
        _ => (file_hash(record.unwrap_or(&a.file))?, utc_now_s()),
    };
    fit_to_board(node, &file, &mut values)?;
    let switched = ensure_preop(node, a.preop)?;
    unlock(node, a.preop)?;
    let stamp = stamp_values(hash, utc_s);
    let bar = Progress::new(3 * (values.len() + stamp.len()) as u64, "push");
    let (changed, stamped) = match write_phase(node, &values, &stamp, cancel, &bar) {
        Ok(c) => c,
        Err(e) => {
            let left = abandon(node);
            return Err(e.context(left));
        }
    };
    let n = values.len();
    if stamped {
        values.extend(stamp);
    }
    store_phase(node, &values, &bar)?;
    let stamp = if stamped { read_stamp(node)? } else { None };
    Ok(PushReport {
        node: node.name(),
        values: n,
        changed,
        switched,
        transfer: file.sensors.iter().any(|s| s.transfer.is_some()),
        stamp,
    })
}

/// Steps before the store: write, verify, validity, the stamp, last
/// chance to cancel. Returns the values changed and whether the board
/// took the stamp.
fn write_phase(
    node: &mut Node,
    values: &[Value],
    stamp: &[Value],
    cancel: &AtomicBool,
    bar: &Progress,
) -> Result<(usize, bool)> {
    let changed = write_all(node, values, cancel, bar)?;
    verify(node, values, bar, "after writing")?;
    check_valid(node)?;
    let stamped = write_stamp(node, stamp, bar)?;
    if cancel.load(Ordering::SeqCst) {
        bail!("interrupted (Ctrl-C) after every write, before the store");
    }
    Ok((changed, stamped))
}

/// Stores with 0x1010 sub 3 ("save application parameters": calibration
/// and configuration, not a PDO remap someone left unsaved) where the
/// firmware has it, else sub 1 ("save all").
fn store(node: &mut Node) -> Result<(), crate::canopen::ClientError> {
    let save = SAVE_SIGNATURE.to_le_bytes();
    match node
        .client
        .download_timeout(node.id, 0x1010, 3, &save, STORE_TIMEOUT)
    {
        Err(e) if e.abort_code() == Some(0x0609_0011) => {
            node.client
                .download_timeout(node.id, 0x1010, 1, &save, STORE_TIMEOUT)
        }
        r => r,
    }
}

/// The store, the reset and the second verification; the lock at the end.
fn store_phase(node: &mut Node, values: &[Value], bar: &Progress) -> Result<()> {
    let id = node.id;
    if let Err(e) = store(node) {
        let left = abandon(node);
        return Err(anyhow::Error::from(e).context(format!("the store (0x1010) failed; {left}")));
    }
    node.client.nmt(id, crate::canopen::Nmt::Reset)?;
    node.client
        .wait_bootup(id, BOOT_TIMEOUT)
        .context("the calibration was stored, but the node did not boot up after the reset")?;
    verify(node, values, bar, "after the reset").context(
        "the calibration was stored, but the board reads back other values after its reset",
    )?;
    node.client.write_u32(id, 0x2010, 0, 0)?;
    Ok(())
}

/// The model name of the non-zero extension terms (`base` if none).
fn model_name(sensors: &[SensorParams]) -> String {
    let any = |f: fn(&ExtParams) -> bool| sensors.iter().any(|s| f(&s.ext));
    let mut v = Vec::new();
    if any(|e| e.nonlinearity != [0.0, 0.0]) {
        v.push("nonlinearity");
    } else if any(|e| e.gain != 0.0) {
        v.push("gain");
    }
    if any(|e| e.linearity_table.is_some()) {
        v.push("linearity table");
    }
    for (name, f) in [
        (
            "incidence",
            (|e: &ExtParams| e.incidence_mm != 0.0 || e.spot_mm.is_some())
                as fn(&ExtParams) -> bool,
        ),
        ("crosstalk", |e| e.crosstalk != 0.0),
        ("thermal", |e| e.thermal_mm_per_c != 0.0),
        ("drift", |e| e.drift_mm_per_s != 0.0),
    ] {
        if any(f) {
            v.push(name);
        }
    }
    if v.is_empty() {
        "base".into()
    } else {
        v.join("+")
    }
}

/// One sensor's parameters from its 25 calibration values and transfer
/// (a table only when a coefficient is non-zero: otherwise the board
/// applies none and its knots mean nothing; spot terms only when one is
/// non-zero, as the lab writes them).
fn sensor_params(i: usize, c: &[f64; CAL_VALUES], t: Option<TransferParams>) -> SensorParams {
    let mut dir = [c[3], c[4], c[5]];
    let len = dir.iter().map(|x| x * x).sum::<f64>().sqrt();
    if (len - 1.0).abs() > 1e-6 && len > 0.0 {
        eprintln!(
            "warning: sensor {}: the board's beam direction has length {len:.6}; the file \
             holds it normalised (as the board uses it)",
            i + 1
        );
        dir.iter_mut().for_each(|x| *x /= len);
    }
    SensorParams {
        sensor: i + 1,
        zero_mm: [c[0], c[1], c[2]],
        dir,
        ext: ExtParams {
            d_ref_mm: c[6],
            gain: c[7],
            nonlinearity: [c[8], c[9]],
            incidence_mm: c[10],
            spot_mm: c[SPOT0..]
                .iter()
                .any(|x| *x != 0.0)
                .then(|| [c[SPOT0], c[SPOT0 + 1]]),
            crosstalk: c[11],
            thermal_mm_per_c: c[12],
            temp_ref_c: c[13],
            drift_mm_per_s: c[14],
            linearity_table: c[COEFF0..SPOT0]
                .iter()
                .any(|x| *x != 0.0)
                .then(|| TableParams {
                    knots_mm: [
                        c[KNOT0],
                        c[KNOT0 + 1],
                        c[KNOT0 + 2],
                        c[KNOT0 + 3],
                        c[KNOT0 + 4],
                    ],
                    values_mm: [c[COEFF0], c[COEFF0 + 1], c[COEFF0 + 2]],
                }),
        },
        correction: None,
        sigma: None,
        sigma_ext: Vec::new(),
        residual_rms_mm: None,
        readings: 0,
        identifiability: None,
        transfer: t,
    }
}

/// Reads calibration value `sub` of sensor `i`; a spot coefficient the
/// firmware has no object for (abort 0x06090011, before sub 24/25) reads
/// as 0: no object shows what such a board applies.
fn read_cal(node: &mut Node, i: usize, sub: u8) -> Result<f64> {
    match node.client.read_f32(node.id, 0x2101 + i as u16, sub) {
        Ok(v) => Ok(v as f64),
        Err(e) if sub >= CAL_SUB_SPOT && e.abort_code() == Some(0x0609_0011) => Ok(0.0),
        Err(e) => Err(e.into()),
    }
}

/// Reads the board's calibration into a parameter file.
///
/// # Errors
/// Client errors; a Ctrl-C; a calibration the file format refuses.
pub fn pull(node: &mut Node, cancel: &AtomicBool) -> Result<ParamFile> {
    node.hello()?;
    let n = node.sensors()?;
    let id = node.id;
    let bar = Progress::new((CAL_VALUES + 4) as u64 * n as u64, "pull");
    let mut sensors = Vec::new();
    for i in 0..n {
        let mut c = [0f64; CAL_VALUES];
        for (k, v) in c.iter_mut().enumerate() {
            if cancel.load(Ordering::SeqCst) {
                bail!("interrupted (Ctrl-C): nothing was written");
            }
            *v = read_cal(node, i, k as u8 + 1)?;
            bar.inc();
        }
        let tf = 0x2201 + i as u16;
        let kind = node.client.read_u32(id, tf, 1)?;
        let mut r = [0f64; 3];
        for (k, v) in r.iter_mut().enumerate() {
            *v = node.client.read_f32(id, tf, k as u8 + 2)? as f64;
        }
        (0..4).for_each(|_| bar.inc());
        let t = TransferParams {
            kind: if kind == 1 {
                TRANSFER_VOLTAGE
            } else {
                TRANSFER_CURRENT
            }
            .into(),
            scale: r[0],
            mm_at_low: r[1],
            mm_at_high: r[2],
        };
        sensors.push(sensor_params(i, &c, Some(t)));
    }
    let mut file = ParamFile::new("board", &model_name(&sensors), 0);
    file.sensors = sensors;
    file.thermal_tau_s = match node.client.read_f32(id, TAU_INDEX, 0) {
        Ok(tau) => tau as f64,
        Err(e) if e.abort_code() == Some(0x0602_0000) => 0.0,
        Err(e) => return Err(e.into()),
    };
    file.calibration_stamp = read_stamp(node)?
        .filter(|s| (s.record_hash, s.utc_s, s.store_count) != (0, 0, 0))
        .map(|s| s.to_file());
    file.validate()
        .with_context(|| format!("the calibration of {} as a params.json", node.name()))?;
    Ok(file)
}

/// `perpend node pull`: to `--out` or standard output.
///
/// # Errors
/// As [`pull`], or the file cannot be written.
pub fn pull_to(node: &mut Node, a: &PullArgs, cancel: &AtomicBool) -> Result<()> {
    let file = pull(node, cancel)?;
    match &a.out {
        Some(p) => {
            file.write(p)?;
            eprintln!(
                "pull: {} sensors of {} written to {}",
                file.sensors.len(),
                node.name(),
                p.display()
            );
        }
        None => {
            let text = serde_json::to_string_pretty(&file)? + "\n";
            let mut out = std::io::stdout().lock();
            match std::io::Write::write_all(&mut out, text.as_bytes()) {
                Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => {
                    return Err(e).context("writing to standard output")
                }
                _ => {}
            }
        }
    }
    Ok(())
}

#[cfg(test)]
#[path = "params_tests.rs"]
mod tests;
