//! `perpend board`: a virtual sensor board on the host. The firmware's
//! application ([`perpend_board::app::App`]: the same pipeline,
//! `perpend-core` math and `perpend-can` device as on the STM32) runs
//! against a simulated head looking at a fixed plane and serves its CAN bus
//! as LAWICEL/slcan over TCP, one client at a time, so that python-can's
//! `slcan` interface with channel `socket://HOST:PORT` (and any CANopen
//! master on top of it) talks to it.
//!
//! ```text
//! perpend board --slcan 127.0.0.1:5555 --node-id 16 --plane 0.035,-0.052,1,-40 \
//!               [--sensors sensors.csv] [--params params.json] [--noise-mm 0.002] \
//!               [--fault 3:open] [--seed 1] [--serial 0x12345678] \
//!               [--truth truth.csv] [--world 127.0.0.1:5556]
//! ```
//!
//! * `--serial`: 0x1018 sub 4 (default: derived from `--seed` as the
//!   firmware derives it from the MCU's unique ID, [`node::serial_for_seed`]).
//!   Repeated (`--serial 0x101 --serial 0x102 ...`): one board per serial on
//!   one virtual bus, a cell of heads behind one slcan port (board k has
//!   seed `--seed` + k; the world channel moves the first); the first
//!   stdout line is then `perpend board: N boards, nodes A,B,.. on HOST:PORT`.
//!   `--serial S:NODEID` gives that board its own node-id instead of
//!   `--node-id` (a cell of configured and non-configured heads:
//!   `--node-id 0xFF --serial 0x101:16 --serial 0x102:17 --serial 0x103`).
//! * `--node-id 0xFF`: the board is not configured (CiA 305): it sends
//!   nothing and waits for an LSS master to give it a node-id
//!   (`perpend_can::lss`, docs/can.md "LSS commissioning").
//! * `--plane A,B,C,D`: the surface `A·x + B·y + C·z + D = 0` in the TCS.
//! * `--sensors`: the head the board is built with (exchange format,
//!   4 sensors): stored on the board and simulated.
//! * `--params`: a calibration (`perpend calibrate --out`): stored on the
//!   board and simulated as the true head (it overrides `--sensors` for
//!   both), its `thermal_tau_s` stored in 0x2105 (the simulated die
//!   temperature is constant, so the lag only shows when 0x200A moves).
//!   Without either flag the board runs the factory head.
//! * `--truth`: the head that is really built (exchange format, 4
//!   sensors): only simulated, never stored, so the board runs its stored
//!   (nominal) head on the readings of this one, as a real board does
//!   before its calibration. It overrides what `--sensors`/`--params`
//!   would simulate.
//! * `--world HOST:PORT` (loopback): a line-based control channel through
//!   which a simulated robot moves the plane (`plane A,B,C,D` → `ok`, see
//!   [`world`]); its address is the second stdout line,
//!   `perpend board: world on HOST:PORT`.
//! * `--tracker-tilt-deg X,Y`, `--tcp-tilt-deg X,Y`, `--tcp-offset-mm X,Y`
//!   (need `--world`): frame errors of the simulated cell (issue 36,
//!   docs/frames.md): the datum plate as the tracker reports it is tilted
//!   by X about the datum's x and Y about its y against the truth (the tilt
//!   turns against the head when the world's `move` turns the last joint);
//!   the true spindle frame is tilted / offset against the taught TCP. The
//!   head sees every plane of the world channel through them.
//! * `--temp-c T`: the die temperature the board measures (0x200A, the
//!   thermal correction, `temp_c` of `perpend node capture`); default none.
//! * `--noise-mm`: reading noise, 1σ (default 2 µm; 0 makes every sensor
//!   look stuck after the stuck detector's 2 s).
//! * `--fault SENSOR:KIND` (repeatable): `open`, `overcurrent`,
//!   `saturated`, `stuck`, `noisy` (see [`sim`]).
//! * `--fault bus:noack:SECONDS`: for the first SECONDS of the run nothing
//!   the board sends is acknowledged (a node alone on the bus): its frames
//!   stay in the transmit queue or are dropped and counted (0x2008, EMCY
//!   0x8110 `[1, count]`), acquisition goes on (0x2007 advances), frames it
//!   receives are handled; afterwards it sends the queue and answers at
//!   once (see [`node`]).
//! * `--fault bus:drop:IDX:N` / `bus:reset:IDX:N` (testing a master's
//!   recovery): at the N-th SDO request (upload or download) to object IDX
//!   the server closes the client's connection, the board's answer lost
//!   (an adapter unplugged), or the board resets as on an NMT reset node
//!   after answering it (a brown-out). Each fires once; the board then
//!   accepts a new client as usual (see [`server::LinkFault`]).
//! * Port 0 picks a free port. The first line on stdout is
//!   `perpend board: node N on HOST:PORT` once the port accepts clients.
//!
//! Parameters stored by 0x1010 live in an in-memory flash: they survive
//! NMT resets (and 0x1011 restores the factory state) for the run.

pub mod node;
pub mod server;
pub mod sim;
pub mod tail;
pub mod update;
pub mod world;

use std::io::Write as _;
use std::net::TcpListener;
use std::path::PathBuf;
use std::str::FromStr;

use anyhow::{anyhow, bail, Context as _, Result};
use perpend_core::head::Head4;
use perpend_core::params::Params;

use crate::demo::parse_plane;
use node::{BoardConfig, VirtualBoard};
use sim::{Fault, SimHead};
use world::World;

/// Arguments of `perpend board`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// TCP address to serve slcan on, e.g. `127.0.0.1:5555` (port 0: any
    /// free port, printed at start).
    #[arg(long)]
    pub slcan: String,
    /// CANopen node-id, 1..127 (decimal or 0x hex), or 0xFF: not
    /// configured, the board waits for LSS (CiA 305).
    #[arg(long, default_value = "0x20", value_parser = parse_node_id)]
    pub node_id: u8,
    /// Plane `A,B,C,D` (`A·x + B·y + C·z + D = 0`, TCS, +z = feed).
    #[arg(long, default_value = "0.035,-0.052,1,-40", allow_hyphen_values = true)]
    pub plane: String,
    /// Head of the board (`sensors.csv`, exchange format, 4 sensors).
    #[arg(long)]
    pub sensors: Option<PathBuf>,
    /// Calibration of the board (`params.json` of `perpend calibrate`).
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// Reading noise [mm, 1σ].
    #[arg(long, default_value_t = 0.002)]
    pub noise_mm: f64,
    /// Die temperature the board measures [°C] (default: none, as a board
    /// without its temperature sensor): published in 0x200A, recorded by
    /// `perpend node capture` in `temp_c`, used by the thermal correction.
    #[arg(long, allow_hyphen_values = true)]
    pub temp_c: Option<f64>,
    /// Fault `SENSOR:KIND` (1-based sensor; open, overcurrent, saturated,
    /// stuck, noisy), `bus:noack:SECONDS` (nothing the board sends is
    /// acknowledged for the first SECONDS), `bus:drop:IDX:N` (the client's
    /// connection is closed at its N-th SDO request to object IDX) or
    /// `bus:reset:IDX:N` (the board resets after answering it),
    /// `bus:block-tail:N:K` (the last K segments of the N-th sub-block of
    /// the next SDO block download are lost), or `update:no-confirm` (an
    /// image from `perpend node update` hangs at start: the board rolls
    /// back to the old one); repeatable.
    #[arg(long)]
    pub fault: Vec<FaultArg>,
    /// Seed of the noise generator.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Serial number of the board (0x1018 sub 4), decimal or 0x hex;
    /// default: derived from --seed the way the firmware folds the MCU's
    /// unique ID (FNV-1a to 32 bits). Repeated: one board per serial, all
    /// on one virtual bus (a cell), each with the other options.
    /// `S:NODEID`: this board's node-id instead of --node-id.
    #[arg(long, value_name = "S[:NODEID]")]
    pub serial: Vec<SerialArg>,
    /// The head really built (sensors.csv): simulated, not stored.
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// Loopback address of the world channel that moves the plane, e.g.
    /// `127.0.0.1:0`.
    #[arg(long)]
    pub world: Option<String>,
    /// Tracker (base) tilt X,Y [deg] about the datum's x and y: the planes
    /// of the world channel are seen tilted by it, turning against the
    /// head with the last joint (issue 36; needs --world).
    #[arg(long, value_parser = world::parse_pair, default_value = "0,0", allow_hyphen_values = true)]
    pub tracker_tilt_deg: world::Pair,
    /// TCP tilt X,Y [deg]: the true spindle frame against the taught one
    /// (fixed to the flange; needs --world).
    #[arg(long, value_parser = world::parse_pair, default_value = "0,0", allow_hyphen_values = true)]
    pub tcp_tilt_deg: world::Pair,
    /// TCP lateral offset X,Y [mm] of the true spindle frame against the
    /// taught one (needs --world).
    #[arg(long, value_parser = world::parse_pair, default_value = "0,0", allow_hyphen_values = true)]
    pub tcp_offset_mm: world::Pair,
}

/// Parses a serial number: decimal or `0x` hex `u32`.
pub fn parse_serial(s: &str) -> Result<u32> {
    perpend_can::config::parse_u32(s.trim().as_bytes())
        .ok_or_else(|| anyhow!("serial '{s}': expected a decimal or 0x hex u32"))
}

/// One `--serial S[:NODEID]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SerialArg {
    /// The serial number (0x1018 sub 4).
    pub serial: u32,
    /// The board's own node-id (1..127 or 0xFF), else `--node-id`.
    pub node_id: Option<u8>,
}

impl FromStr for SerialArg {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        let (serial, node_id) = match s.split_once(':') {
            Some((a, b)) => (a, Some(parse_node_id(b.trim())?)),
            None => (s, None),
        };
        Ok(Self {
            serial: parse_serial(serial)?,
            node_id,
        })
    }
}

/// One `--fault`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FaultArg {
    /// `SENSOR:KIND`: a sensor fault.
    Sensor(Fault),
    /// `bus:noack:SECONDS`: no acknowledge for the first SECONDS.
    BusNoAck(f64),
    /// `update:no-confirm`: a new image hangs at start (rollback).
    UpdateNoConfirm,
    /// `bus:drop:IDX:N` or `bus:reset:IDX:N`: the server's link faults.
    Link(server::LinkFault),
    /// `bus:block-tail:N:K`: the tail of a block download's sub-block lost.
    BlockTail(tail::BlockTail),
}

impl FromStr for FaultArg {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        if s == "update:no-confirm" {
            return Ok(FaultArg::UpdateNoConfirm);
        }
        let Some(rest) = s.strip_prefix("bus:") else {
            return Ok(FaultArg::Sensor(s.parse()?));
        };
        if rest.starts_with("drop:") || rest.starts_with("reset:") {
            return Ok(FaultArg::Link(rest.parse()?));
        }
        if let Some(t) = rest.strip_prefix("block-tail:") {
            return Ok(FaultArg::BlockTail(t.parse()?));
        }
        let secs = rest
            .strip_prefix("noack:")
            .and_then(|t| t.trim().parse::<f64>().ok())
            .filter(|t| t.is_finite() && (0.0..=86_400.0).contains(t));
        match secs {
            Some(t) => Ok(FaultArg::BusNoAck(t)),
            None => bail!(
                "--fault '{s}': expected bus:noack:SECONDS (0..86400), bus:drop:IDX:N, \
                 bus:reset:IDX:N or bus:block-tail:N:K"
            ),
        }
    }
}

/// Parses a node-id: decimal or `0x` hex, 1..=127, or 0xFF (not
/// configured: waits for LSS).
pub fn parse_node_id(s: &str) -> Result<u8> {
    let v = match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(h) => u8::from_str_radix(h, 16),
        None => s.parse::<u8>(),
    }
    .map_err(|_| anyhow!("node-id '{s}': expected 1..127 or 0xFF"))?;
    if !((1..=127).contains(&v) || v == perpend_can::lss::UNCONFIGURED) {
        bail!("node-id '{s}': expected 1..127 or 0xFF");
    }
    Ok(v)
}

fn head4(v: Vec<perpend_core::head::Sensor<f64>>, what: &str) -> Result<Head4<f64>> {
    let n = v.len();
    let arr: [perpend_core::head::Sensor<f64>; 4] = v
        .try_into()
        .map_err(|_| anyhow!("{what}: the board has 4 sensors, the file has {n}"))?;
    Ok(Head4::new(arr))
}

/// Builds the boards of the arguments: one per `--serial` (board k with
/// seed `--seed` + k), or one.
///
/// # Errors
/// As [`build`].
pub fn build_all(a: &Args) -> Result<Vec<VirtualBoard>> {
    if a.serial.len() <= 1 {
        return Ok(vec![build(a)?]);
    }
    a.serial
        .iter()
        .enumerate()
        .map(|(k, &s)| {
            build(&Args {
                serial: vec![s],
                node_id: s.node_id.unwrap_or(a.node_id),
                seed: a.seed.wrapping_add(k as u64),
                slcan: a.slcan.clone(),
                plane: a.plane.clone(),
                sensors: a.sensors.clone(),
                params: a.params.clone(),
                fault: a.fault.clone(),
                truth: a.truth.clone(),
                world: None,
                ..*a
            })
        })
        .collect()
}

/// Builds the board from the arguments (no network; the first `--serial`).
///
/// # Errors
/// Unreadable or invalid files, a bad plane, noise or node-id.
pub fn build(a: &Args) -> Result<VirtualBoard> {
    let plane = parse_plane(&a.plane)?;
    let head = match &a.sensors {
        Some(p) => {
            let t = perpend_formats::exchange::read_sensors(p)?;
            Some(head4(t.sensors()?, &p.display().to_string())?)
        }
        None => None,
    };
    let mut thermal_tau_s = 0.0;
    let calibration = match &a.params {
        Some(p) => {
            let f = perpend_formats::paramfile::ParamFile::read(p)?;
            thermal_tau_s = f.thermal_tau_s;
            Some(head4(f.sensors()?, &p.display().to_string())?)
        }
        None => None,
    };
    let truth = match &a.truth {
        Some(p) => {
            let t = perpend_formats::exchange::read_sensors(p)?;
            head4(t.sensors()?, &p.display().to_string())?
        }
        None => calibration
            .or(head)
            .unwrap_or_else(|| Params::factory().head.cast()),
    };
    let mut sim = SimHead::new(truth, plane, a.noise_mm, a.seed)?;
    if let Some(t) = a.temp_c {
        if !(-40.0..=125.0).contains(&t) {
            bail!("--temp-c {t}: outside the die sensor's -40..125 °C");
        }
    }
    sim.set_temp_c(a.temp_c);
    let mut noack_us = None;
    let mut confirms = true;
    for f in &a.fault {
        match *f {
            FaultArg::Sensor(f) => sim.set_fault(f.sensor, Some(f.kind)),
            FaultArg::BusNoAck(t) => noack_us = Some((t * 1e6) as u64),
            FaultArg::UpdateNoConfirm => confirms = false,
            FaultArg::Link(_) | FaultArg::BlockTail(_) => {}
        }
    }
    let first = a.serial.first().copied();
    let cfg = BoardConfig {
        node_id: first.and_then(|s| s.node_id).unwrap_or(a.node_id),
        head,
        calibration,
        thermal_tau_s,
    };
    let serial = first.map_or_else(|| node::serial_for_seed(a.seed), |s| s.serial);
    let mut board = VirtualBoard::with_serial(&cfg, sim, serial)?;
    board.set_bus_noack(noack_us);
    board.set_update_confirms(confirms);
    Ok(board)
}

/// Runs `perpend board` until killed.
///
/// # Errors
/// As [`build`], or when the address cannot be bound.
pub fn run(a: &Args) -> Result<()> {
    let mut boards = build_all(a)?;
    let listener = TcpListener::bind(&a.slcan)
        .with_context(|| format!("--slcan {}: cannot listen", a.slcan))?;
    let addr = listener.local_addr()?;
    let nodes: Vec<String> = boards
        .iter()
        .map(|b| b.app().device().active_node_id().to_string())
        .collect();
    match nodes.as_slice() {
        [one] => println!("perpend board: node {one} on {addr}"),
        _ => println!(
            "perpend board: {} boards, nodes {} on {addr}",
            nodes.len(),
            nodes.join(",")
        ),
    }
    let frames = world::frames_of(a.tracker_tilt_deg, a.tcp_tilt_deg, a.tcp_offset_mm)?;
    if a.world.is_none() && frames.amax() > 0.0 {
        bail!("--tracker-tilt-deg, --tcp-tilt-deg and --tcp-offset-mm act on the planes of the world channel: add --world 127.0.0.1:0");
    }
    let world = match &a.world {
        Some(w) => {
            let world = World::bind(w)?.with_frames(frames);
            println!("perpend board: world on {}", world.local_addr()?);
            Some(world)
        }
        None => None,
    };
    std::io::stdout().flush()?;
    let faults = a
        .fault
        .iter()
        .filter_map(|f| match f {
            FaultArg::Link(l) => Some(*l),
            _ => None,
        })
        .collect();
    let tails = tail::BlockTails::new(a.fault.iter().filter_map(|f| match f {
        FaultArg::BlockTail(t) => Some(*t),
        _ => None,
    }));
    server::serve(listener, world, &mut boards, faults, tails)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use perpend_formats::exchange::{write_sensors, SensorTable};

    fn args() -> Args {
        Args {
            slcan: "127.0.0.1:0".into(),
            node_id: 0x20,
            plane: "0.01,0.02,1,-40".into(),
            sensors: None,
            params: None,
            noise_mm: 0.0,
            temp_c: None,
            fault: Vec::new(),
            seed: 1,
            serial: Vec::new(),
            truth: None,
            world: None,
            tracker_tilt_deg: world::Pair::default(),
            tcp_tilt_deg: world::Pair::default(),
            tcp_offset_mm: world::Pair::default(),
        }
    }

    #[test]
    fn node_ids_parse_in_decimal_and_hex() {
        assert_eq!(parse_node_id("16").unwrap(), 16);
        assert_eq!(parse_node_id("0x7F").unwrap(), 127);
        assert!(parse_node_id("0").is_err());
        assert!(parse_node_id("128").is_err());
        assert!(parse_node_id("x").is_err());
    }

    #[test]
    fn builds_from_a_sensors_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sensors.csv");
        let head = Head4::<f64>::cone(60.0, 25f64.to_radians(), 0.0, 0.0).unwrap();
        let table = SensorTable::from_sensors(&head.sensors, None);
        let mut f = std::fs::File::create(&path).unwrap();
        write_sensors(&mut f, &table, &[]).unwrap();
        drop(f);
        let mut a = args();
        a.sensors = Some(path);
        let b = build(&a).unwrap();
        let c = b.app().device().calibration(0).unwrap();
        assert!((c.zero[0] - 60.0).abs() < 1e-4);
        // three sensors in a file: refused
        let path3 = dir.path().join("three.csv");
        let t3 = SensorTable::from_sensors(&head.sensors[..3], None);
        let mut f = std::fs::File::create(&path3).unwrap();
        write_sensors(&mut f, &t3, &[]).unwrap();
        drop(f);
        a.sensors = Some(path3);
        let e = build(&a).err().unwrap().to_string();
        assert!(e.contains("4 sensors"), "{e}");
    }

    #[test]
    fn serial_from_flag_or_seed() {
        assert_eq!(parse_serial("0x00C0FFEE").unwrap(), 0x00C0_FFEE);
        assert_eq!(parse_serial("17").unwrap(), 17);
        assert!(parse_serial("0x1_0000_0000").is_err());
        assert!(parse_serial("x").is_err());
        let b = build(&args()).unwrap();
        let seed1 = node::serial_for_seed(1);
        assert_eq!(b.app().device().read_u32(0x1018, 4), Some(seed1));
        assert_ne!(node::serial_for_seed(2), seed1);
        let b = build(&Args {
            serial: vec!["0xABCD".parse().unwrap()],
            ..args()
        })
        .unwrap();
        assert_eq!(b.app().device().read_u32(0x1018, 4), Some(0xABCD));
        assert_eq!(b.app().device().node_id(), 0x20);
        assert_eq!(
            b.app().device().read_u32(0x1018, 1),
            Some(perpend_can::config::VENDOR_ID)
        );
    }

    #[test]
    fn a_cell_mixes_configured_and_non_configured_heads() {
        let mut a = args();
        a.node_id = perpend_can::lss::UNCONFIGURED;
        a.serial = ["0x101:16", "0x102:0x11", "0x103"]
            .iter()
            .map(|s| s.parse().unwrap())
            .collect();
        let ids: Vec<u8> = build_all(&a)
            .unwrap()
            .iter()
            .map(|b| b.app().device().active_node_id())
            .collect();
        assert_eq!(ids, vec![16, 17, 0xFF]);
        for bad in ["0x101:0", "0x101:128", "x:16", "0x101:"] {
            assert!(bad.parse::<SerialArg>().is_err(), "{bad}");
        }
    }

    #[test]
    fn faults_parse() {
        assert_eq!(
            "bus:noack:2.5".parse::<FaultArg>().unwrap(),
            FaultArg::BusNoAck(2.5)
        );
        assert!(matches!(
            "3:open".parse::<FaultArg>().unwrap(),
            FaultArg::Sensor(Fault { sensor: 2, .. })
        ));
        for bad in [
            "bus:noack:",
            "bus:noack:-1",
            "bus:noack:nan",
            "bus:off:1",
            "5:open",
            "bus:drop:0x2101",
            "bus:drop:0x2101:0",
            "bus:reset:zz:1",
        ] {
            assert!(bad.parse::<FaultArg>().is_err(), "{bad}");
        }
        assert!(matches!(
            "bus:block-tail:3:5".parse::<FaultArg>().unwrap(),
            FaultArg::BlockTail(tail::BlockTail {
                sub_block: 3,
                segments: 5
            })
        ));
        assert!("bus:block-tail:0:5".parse::<FaultArg>().is_err());
        assert!(matches!(
            "bus:drop:0x2103:2".parse::<FaultArg>().unwrap(),
            FaultArg::Link(server::LinkFault {
                index: 0x2103,
                nth: 2,
                ..
            })
        ));
        let mut a = args();
        a.fault = vec![FaultArg::BusNoAck(1.0)];
        let mut b = build(&a).unwrap();
        let mut sent = Vec::new();
        b.poll(999_999, &mut |f| sent.push(f));
        assert!(sent.is_empty(), "boot-up held back");
        b.poll(1_000_000, &mut |f| sent.push(f));
        assert_eq!(sent.len(), 1);
    }

    #[test]
    fn bad_plane_and_noise_are_refused() {
        let mut a = args();
        a.plane = "0,0,0,1".into();
        assert!(build(&a).is_err());
        let mut a = args();
        a.noise_mm = f64::NAN;
        assert!(build(&a).is_err());
    }
}
