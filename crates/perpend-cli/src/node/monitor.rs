//! `perpend node monitor`: the board's measurement live, from its TPDOs.
//!
//! The TPDO parameters are read from the board (0x1800.., 0x1A00..), so a
//! remapped PDO is decoded right. Each SYNC gives one row: θ1, θ2, θ, the
//! pitch/yaw correction the robot applies (0x2003, Chen eq. 22), the
//! normal, the distances, the RMS residual, the status word and the sample
//! counter; what no synchronous TPDO carries (in the default mapping: θ,
//! pitch/yaw and the distances) is read by SDO once per row, after that
//! SYNC's PDOs (so from a slightly later sample).
//!
//! SYNC: for half a second the monitor listens; if another producer (the
//! robot controller) sends SYNC, rows follow its SYNCs, else the monitor
//! sends SYNC itself at `--sync-hz` (0: never; then it waits for one).
//! The board sends TPDOs only in operational: `--start` starts a board
//! that is not, and puts it back into pre-operational at the end.
//!
//! Ends after `--seconds` or at Ctrl-C. Rows are printed at most five times
//! a second; `--csv FILE` logs every row (`t_s`, sample, angles, pitch/yaw,
//! normal, distances, RMS, status).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use perpend_can::Frame;

use super::{words, Node};
use crate::canopen::pdo::Tpdo;
use crate::canopen::{Nmt, NodeState};

/// Options of `monitor`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// SYNC rate [Hz] when no other SYNC producer is heard (0: never send).
    #[arg(long, default_value_t = 10.0)]
    pub sync_hz: f64,
    /// Stop after this many seconds (default: at Ctrl-C).
    #[arg(long)]
    pub seconds: Option<f64>,
    /// Log every row to this CSV file.
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// Start the node if it is not operational (back to pre-operational at
    /// the end).
    #[arg(long)]
    pub start: bool,
}

/// One column: name and object.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Field {
    name: String,
    index: u16,
    sub: u8,
}

fn fields(sensors: usize) -> Vec<Field> {
    let f = |name: &str, index, sub| Field {
        name: name.to_string(),
        index,
        sub,
    };
    let mut v = vec![
        f("sample", 0x2007, 0),
        f("theta1_deg", 0x2002, 1),
        f("theta2_deg", 0x2002, 2),
        f("theta_deg", 0x2002, 3),
        f("pitch_deg", 0x2003, 1),
        f("yaw_deg", 0x2003, 2),
        f("nx", 0x2001, 1),
        f("ny", 0x2001, 2),
        f("nz", 0x2001, 3),
    ];
    v.extend((1..=sensors).map(|i| f(&format!("d{i}_mm"), 0x2004, i as u8)));
    v.push(f("rms_mm", 0x2006, 0));
    v.push(f("status", 0x2005, 0));
    v
}

/// The rows being assembled and what they need.
struct Rows {
    tpdos: Vec<Tpdo>,
    fields: Vec<Field>,
    sensors: usize,
    current: BTreeMap<(u16, u8), f64>,
    seen: Vec<u16>,
    start: Instant,
    csv: Option<csv::Writer<std::fs::File>>,
    printed: Option<Instant>,
    count: u64,
    /// Rows printed (at most five a second, so fewer than `count`).
    shown: u64,
    last_status: Option<u32>,
}

impl Rows {
    /// Takes a PDO frame into the current row; `true` when every TPDO of
    /// this SYNC has come.
    fn take(&mut self, f: &Frame) -> bool {
        let Some(t) = self.tpdos.iter().find(|t| t.cob_id == f.id) else {
            return false;
        };
        for (m, v) in t.decode(f.payload()) {
            self.current.insert((m.index, m.sub), v.as_f64());
        }
        if !self.seen.contains(&f.id) {
            self.seen.push(f.id);
        }
        self.seen.len() == self.tpdos.len()
    }

    /// Completes the current row (SDO reads for what no PDO carried),
    /// prints and logs it.
    fn emit(&mut self, node: &mut Node) -> Result<()> {
        if self.current.is_empty() {
            return Ok(());
        }
        let t_s = self.start.elapsed().as_secs_f64();
        for fl in &self.fields {
            if let std::collections::btree_map::Entry::Vacant(e) =
                self.current.entry((fl.index, fl.sub))
            {
                let b = node.client.upload(node.id, fl.index, fl.sub)?;
                if let Some(v) = crate::canopen::pdo::value_of(fl.index, fl.sub, &b) {
                    e.insert(v.as_f64());
                }
            }
        }
        let vals: Vec<Option<f64>> = self
            .fields
            .iter()
            .map(|fl| self.current.get(&(fl.index, fl.sub)).copied())
            .collect();
        self.log(t_s, &vals)?;
        self.print(t_s, &vals);
        self.count += 1;
        self.current.clear();
        self.seen.clear();
        Ok(())
    }

    fn log(&mut self, t_s: f64, vals: &[Option<f64>]) -> Result<()> {
        let Some(w) = self.csv.as_mut() else {
            return Ok(());
        };
        let mut rec = vec![format!("{t_s:.4}")];
        for (fl, v) in self.fields.iter().zip(vals) {
            rec.push(match (fl.name.as_str(), v) {
                (_, None) => String::new(),
                ("status", Some(x)) => format!("{:#010x}", *x as u32),
                ("sample", Some(x)) => format!("{}", *x as u32),
                (_, Some(x)) => format!("{x}"),
            });
        }
        w.write_record(&rec).context("writing the CSV log")?;
        Ok(())
    }

    fn print(&mut self, t_s: f64, vals: &[Option<f64>]) {
        let get = |name: &str| {
            self.fields
                .iter()
                .position(|f| f.name == name)
                .and_then(|i| vals[i])
        };
        let st = get("status").map(|x| x as u32);
        self.last_status = st.or(self.last_status);
        if self
            .printed
            .is_some_and(|p| p.elapsed() < Duration::from_millis(200))
        {
            return;
        }
        self.printed = Some(Instant::now());
        self.shown += 1;
        let g = |name: &str, p: usize| get(name).map_or("-".into(), |x| format!("{x:.p$}"));
        let d: Vec<String> = (1..=self.sensors)
            .map(|i| g(&format!("d{i}_mm"), 3))
            .collect();
        println!(
            "t {t_s:7.2} s  #{}  θ1 {}°  θ2 {}°  θ {}°  pitch {}°  yaw {}°  n ({}, {}, {})  d {} mm  rms {} mm  {}",
            g("sample", 0),
            g("theta1_deg", 3),
            g("theta2_deg", 3),
            g("theta_deg", 3),
            g("pitch_deg", 3),
            g("yaw_deg", 3),
            g("nx", 4),
            g("ny", 4),
            g("nz", 4),
            d.join(" "),
            g("rms_mm", 4),
            st.map_or("-".into(), |s| words::status_short(s, self.sensors))
        );
    }
}

/// The node operational (started if `--start`); whether it was started.
fn ensure_operational(node: &mut Node, start: bool) -> Result<bool> {
    let hb = node.heartbeat_ms()?;
    match node.state(hb)? {
        Some(NodeState::Operational) => Ok(false),
        s if start => {
            node.client.nmt(node.id, Nmt::Start)?;
            let _ = node
                .client
                .wait_heartbeat(node.id, Duration::from_millis(hb.min(2000) + 200))?;
            if s.is_none() {
                eprintln!(
                    "monitor: NMT start sent to {} (its state is not known)",
                    node.name()
                );
            }
            Ok(true)
        }
        Some(s) => bail!(
            "{} is {s}: it sends TPDOs only in operational. Pass --start to start it for the \
             monitor (it is put back into pre-operational at the end), or `perpend node … nmt \
             start`",
            node.name()
        ),
        None => {
            eprintln!(
                "warning: the NMT state of {} is not known (heartbeat off); TPDOs come only in \
                 operational",
                node.name()
            );
            Ok(false)
        }
    }
}

/// The summary's count: the rows received, and how many of them were
/// printed (at most five a second) and where the others are.
fn rows_words(count: u64, shown: u64, csv: Option<&std::path::Path>) -> String {
    let rest = match csv {
        Some(p) => format!("every row in {}", p.display()),
        None => "--csv FILE logs every row".into(),
    };
    if shown == count {
        format!("{count} rows, all shown")
    } else {
        format!("{count} rows, {shown} shown (at most 5 a second; {rest})")
    }
}

/// The loop: SYNC (own or observed), rows, until `end` or Ctrl-C.
fn run_loop(node: &mut Node, rows: &mut Rows, a: &Args, cancel: &AtomicBool) -> Result<bool> {
    let listen_until = Instant::now() + Duration::from_millis(500);
    while let Some(left) = listen_until.checked_duration_since(Instant::now()) {
        node.client.recv(left)?;
    }
    let own = node.client.sync_seen().is_none() && a.sync_hz > 0.0;
    let period = Duration::from_secs_f64(1.0 / a.sync_hz.max(1e-3));
    let end = a
        .seconds
        .map(|s| Instant::now() + Duration::from_secs_f64(s.max(0.0)));
    let mut next = Instant::now();
    let mut last_pdo = Instant::now();
    let mut warned = false;
    while !cancel.load(Ordering::SeqCst) && end.is_none_or(|e| Instant::now() < e) {
        if own && Instant::now() >= next {
            rows.emit(node)?;
            node.client.sync()?;
            next = (next + period).max(Instant::now());
        }
        let wait = if own {
            next.saturating_duration_since(Instant::now())
        } else {
            Duration::from_millis(100)
        };
        match node.client.recv(wait.min(Duration::from_millis(100)))? {
            Some((_, f)) if f.id == 0x080 && f.len == 0 && !own => rows.emit(node)?,
            Some((_, f)) => {
                if rows.tpdos.iter().any(|t| t.cob_id == f.id) {
                    last_pdo = Instant::now();
                }
                if rows.take(&f) {
                    rows.emit(node)?;
                }
            }
            None => {}
        }
        if !warned && last_pdo.elapsed() > Duration::from_secs(2) {
            eprintln!(
                "warning: no TPDO from {} for 2 s: is it operational, and does a SYNC reach it?",
                node.name()
            );
            warned = true;
        }
    }
    rows.emit(node)?;
    Ok(own)
}

/// Creates the CSV log with its header.
fn open_csv(p: &std::path::Path, fields: &[Field]) -> Result<csv::Writer<std::fs::File>> {
    let mut w =
        csv::Writer::from_path(p).with_context(|| format!("{}: cannot create", p.display()))?;
    let mut h = vec!["t_s".to_string()];
    h.extend(fields.iter().map(|f| f.name.clone()));
    w.write_record(&h)
        .with_context(|| format!("{}: cannot write", p.display()))?;
    Ok(w)
}

/// `perpend node monitor`.
///
/// # Errors
/// A node that is not operational (without `--start`), maps no
/// synchronous TPDO, or stops answering; the CSV file.
pub fn run(node: &mut Node, a: &Args, cancel: &AtomicBool) -> Result<()> {
    node.hello()?;
    let sensors = node.sensors()?;
    let tpdos: Vec<Tpdo> = node
        .client
        .read_tpdos(node.id, perpend_can::od::TPDOS as u8)?
        .into_iter()
        .filter(|t| t.valid && t.synchronous() && !t.mapped.is_empty())
        .collect();
    if tpdos.is_empty() {
        bail!(
            "{} has no valid synchronous TPDO (0x1800..0x1803): nothing to monitor",
            node.name()
        );
    }
    let fields = fields(sensors);
    let csv = a.csv.as_deref().map(|p| open_csv(p, &fields)).transpose()?;
    let started = ensure_operational(node, a.start)?;
    let mut rows = Rows {
        tpdos,
        fields,
        sensors,
        current: BTreeMap::new(),
        seen: Vec::new(),
        start: Instant::now(),
        csv,
        printed: None,
        count: 0,
        shown: 0,
        last_status: None,
    };
    let r = run_loop(node, &mut rows, a, cancel);
    if started {
        node.client.nmt(node.id, Nmt::Preop)?;
    }
    let own = r?;
    if let Some(w) = rows.csv.as_mut() {
        w.flush().context("writing the CSV log")?;
    }
    eprintln!(
        "monitor: {} in {:.1} s ({}){}",
        rows_words(rows.count, rows.shown, a.csv.as_deref()),
        rows.start.elapsed().as_secs_f64(),
        if own {
            format!("SYNC sent by perpend at {} Hz", a.sync_hz)
        } else {
            "SYNC from another producer".into()
        },
        if started {
            "; the node is pre-operational again"
        } else {
            ""
        }
    );
    Ok(())
}
