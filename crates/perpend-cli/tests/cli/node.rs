//! `perpend node` end to end against the virtual board over slcan/TCP on
//! loopback: info, status, push → reset → pull, capture (also with a
//! faulted sensor), monitor, and the refusals (wrong node-id, a board in
//! operational, a file for another head). Each test starts its own board
//! on a free port (`--slcan 127.0.0.1:0`, the port is on its first stdout
//! line) and kills it when it ends, also on failure.
#![allow(clippy::unwrap_used, clippy::panic)]

use std::path::Path;
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use crate::support;

use perpend_cli::node::params::record_hash;
use perpend_core::params::Params;
use perpend_formats::paramfile::{ParamFile, TransferParams, TRANSFER_CURRENT};
use support::{failed, ok, text, VirtualBus};

const NODE: &str = "16";
const PLANE: &str = "0.035,-0.052,1,-40";

/// A running virtual board; killed on drop.
struct Board {
    _vb: VirtualBus,
    bus: String,
}

impl Board {
    fn start(extra: &[&str]) -> Self {
        let vb = VirtualBus::start(&[&["--node-id", NODE, "--plane", PLANE], extra].concat());
        let bus = vb.bus.clone();
        Board { _vb: vb, bus }
    }

    /// Runs `perpend node --bus … --node-id 16 <args>` (bounded in time).
    fn node(&self, args: &[&str]) -> Output {
        self.node_as(NODE, args)
    }

    fn node_as(&self, id: &str, args: &[&str]) -> Output {
        let t = Instant::now();
        let out = Command::new(env!("CARGO_BIN_EXE_perpend"))
            .args(["--quiet", "node", "--bus", &self.bus, "--node-id", id])
            .args(args)
            .output()
            .unwrap();
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "{args:?} took too long"
        );
        out
    }
}

/// The factory head moved a little, a gain, transfer functions; `n` sensors.
fn params_file(path: &Path, n: usize) -> ParamFile {
    let nominal: Vec<_> = Params::factory().head.cast::<f64>().sensors.to_vec();
    let mut truth = nominal.clone();
    for (i, s) in truth.iter_mut().enumerate() {
        s.zero.y -= 0.05 * (i as f64 + 1.0);
        s.ext.gain = -0.002 * i as f64;
    }
    let mut f = ParamFile::truth(&truth[..n], &nominal);
    f.method = "lsq".into();
    f.thermal_tau_s = 725.5;
    for s in &mut f.sensors {
        s.transfer = Some(TransferParams {
            kind: TRANSFER_CURRENT.into(),
            scale: 120.0,
            mm_at_low: 30.0,
            mm_at_high: 70.0,
        });
    }
    f.write(path).unwrap();
    f
}

#[test]
fn info_and_status_describe_the_board() {
    let b = Board::start(&[]);
    let out = ok(&b.node(&["info", "--json"]));
    let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["node_id"], 16);
    assert_eq!(v["sensors"], 4);
    assert_eq!(v["nmt_state"], "pre-operational");
    assert_eq!(v["calibration_unlocked"], false);
    assert!(!v["device_name"].as_str().unwrap().is_empty());
    let out = ok(&b.node(&["info"]));
    assert!(out.contains("NMT state     pre-operational"), "{out}");
    let out = ok(&b.node(&["status"]));
    assert!(out.contains("sensor 1: valid"), "{out}");
    assert!(out.contains("error register"), "{out}");
}

#[test]
fn info_names_the_pdo_mappings_temperature_and_error_register() {
    let b = Board::start(&["--temp-c", "31.5"]);
    let v: serde_json::Value =
        serde_json::from_str(ok(&b.node(&["info", "--json"])).trim()).unwrap();
    assert_eq!(v["die_temp_c"], 31.5);
    assert_eq!(v["error_register"], 0);
    assert_eq!(v["error_register_words"], "no error");
    let pdos = v["pdos"].as_array().unwrap();
    let names: Vec<&str> = pdos.iter().map(|p| p["pdo"].as_str().unwrap()).collect();
    assert_eq!(names, ["TPDO1", "TPDO2", "TPDO3", "TPDO4", "RPDO1"]);
    // TPDO 1 at its default: 0x180 + node-id, every SYNC, θ1 and θ2 in °.
    let t1 = &pdos[0];
    assert_eq!(t1["cob_id"], 0x180 + 16);
    assert_eq!(t1["transmission_words"], "every SYNC");
    assert_eq!(t1["mapped"][0]["name"], "Theta1");
    assert_eq!(t1["mapped"][0]["unit"], "°");
    assert_eq!(pdos[4]["mapped"][0]["index"], 0x2500);
    let out = ok(&b.node(&["info"]));
    assert!(out.contains("die temp      31.5 °C"), "{out}");
    assert!(out.contains("Theta1 [°] (0x2002 sub 1)"), "{out}");
    assert!(
        out.contains("Plane RMS residual [mm] (0x2006 sub 0)"),
        "{out}"
    );
}

#[test]
fn status_gives_each_emergency_its_age() {
    let b = Board::start(&["--fault", "2:open"]);
    std::thread::sleep(Duration::from_millis(1500));
    let v: serde_json::Value =
        serde_json::from_str(ok(&b.node(&["status", "--json"])).trim()).unwrap();
    let up = v["uptime_s"].as_u64().unwrap();
    assert!(up >= 1, "{v}");
    let errors = v["errors"].as_array().unwrap();
    assert!(!errors.is_empty(), "{v}");
    for e in errors {
        let (at, age) = (e["at_s"].as_u64().unwrap(), e["age_s"].as_u64().unwrap());
        assert_eq!(at + age, up, "{e}");
    }
    let out = ok(&b.node(&["status"]));
    assert!(out.contains(" ago "), "{out}");
    assert!(out.contains("`clear-errors` empties the list"), "{out}");
}

#[test]
fn pdo_map_in_cia_order_and_a_refused_step_puts_the_pdo_back() {
    let b = Board::start(&[]);
    let out = ok(&b.node(&["pdo", "map", "3", "0x2003:1", "0x2003:2", "--type", "2"]));
    assert!(out.contains("Pitch [°] (0x2003 sub 1)"), "{out}");
    let mapped = |b: &Board| -> serde_json::Value {
        let v: serde_json::Value =
            serde_json::from_str(ok(&b.node(&["pdo", "show", "--json"])).trim()).unwrap();
        v["pdos"][2].clone()
    };
    let t3 = mapped(&b);
    assert_eq!(t3["transmission"], 2);
    assert_eq!(t3["valid"], true);
    assert_eq!(t3["mapped"][1]["name"], "Yaw");
    // The SYNC start value 250 is refused by the board (0..240) after the
    // mapping was written: the PDO is put back as it was.
    let err = failed(&b.node(&["pdo", "map", "3", "0x2002:3", "--sync-start", "250"]));
    assert!(
        err.contains("its previous parameters were written back"),
        "{err}"
    );
    assert!(err.contains("0x06090031"), "{err}");
    assert_eq!(mapped(&b), t3);
    // Refused before anything is sent: not mappable, too long.
    assert!(failed(&b.node(&["pdo", "map", "3", "0x1017:0"])).contains("cannot be mapped"));
    let err = failed(&b.node(&["pdo", "map", "3", "0x2001:1", "0x2001:2", "0x2001:3"]));
    assert!(err.contains("96 bits"), "{err}");
    // Off, stored, survives a reset; on again.
    ok(&b.node(&["pdo", "off", "3", "--store"]));
    ok(&b.node(&["nmt", "reset"]));
    assert_eq!(mapped(&b)["valid"], false);
    ok(&b.node(&["pdo", "on", "3"]));
    assert_eq!(mapped(&b)["valid"], true);
}

#[test]
fn options_may_follow_the_subcommand() {
    let b = Board::start(&[]);
    let out = Command::new(env!("CARGO_BIN_EXE_perpend"))
        .args(["node", "info", "--json", "--bus", &b.bus, "--node-id", NODE])
        .output()
        .unwrap();
    let v: serde_json::Value = serde_json::from_str(ok(&out).trim()).unwrap();
    assert_eq!(v["node_id"], 16);
    let out = Command::new(env!("CARGO_BIN_EXE_perpend"))
        .args(["node", "info", "--bus", &b.bus])
        .output()
        .unwrap();
    assert!(failed(&out).contains("no node-id given: add --node-id N"));
}

#[test]
fn a_board_held_by_another_client_says_so() {
    let b = Board::start(&[]);
    let addr = b.bus.trim_start_matches("tcp:");
    // The first connection holds the board (as a python session would).
    let holder = std::net::TcpStream::connect(addr).unwrap();
    let port = holder.local_addr().unwrap().port();
    std::thread::sleep(Duration::from_millis(200));
    let t = Instant::now();
    let err = failed(&b.node(&["info"]));
    assert!(
        err.contains("the port answers but is in use by another client"),
        "{err}"
    );
    assert!(err.contains(&format!("127.0.0.1:{port}")), "{err}");
    assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
    drop(holder);
    std::thread::sleep(Duration::from_millis(200));
    ok(&b.node(&["info"]));
}

#[test]
fn push_reset_pull_round_trip() {
    let b = Board::start(&[]);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("params.json");
    let mut file = params_file(&p, 4);
    // spot terms on one sensor (exact in REAL32): 0x2101.. sub 24/25
    file.sensors[1].ext.spot_mm = Some([0.375, -1.25]);
    file.write(&p).unwrap();
    let info = ok(&b.node(&["info"]));
    assert!(info.contains("stamp         none stored"), "{info}");
    let out = ok(&b.node(&["push", p.to_str().unwrap()]));
    assert!(out.contains("117 values written"), "{out}");
    assert!(
        out.contains("read back identical after the boot-up"),
        "{out}"
    );
    // a file without a record gets one beside it (the board's serial, not
    // verified); the calibration stamp is its hash, store #1
    let rec_path = dir.path().join("params.record.json");
    assert!(out.contains("calibration record"), "{out}");
    let rec: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&rec_path).unwrap()).unwrap();
    assert!(
        rec["head_serial"].as_str().unwrap().starts_with("0x"),
        "{rec}"
    );
    assert_eq!(rec["verification"]["kind"], "expected only", "{rec}");
    let hash = format!("{:08x}", record_hash(&std::fs::read(&rec_path).unwrap()));
    assert!(out.contains(&format!("stamp {hash} stored 20")), "{out}");
    assert!(out.contains("Z, store #1"), "{out}");
    let info = ok(&b.node(&["info"]));
    assert!(
        info.contains(&format!("stamp         record {hash} stored")),
        "{info}"
    );
    assert!(info.contains("(store #1)"), "{info}");
    let back = dir.path().join("back.json");
    ok(&b.node(&["pull", "--out", back.to_str().unwrap()]));
    let got = ParamFile::read(&back).unwrap();
    assert_eq!(got.thermal_tau_s, 725.5);
    let st = got.calibration_stamp.clone().unwrap();
    assert_eq!(
        (st.record_hash.as_str(), st.store_count),
        (hash.as_str(), 1)
    );
    let f = |x: f64| x as f32 as f64;
    for (a, g) in file.sensors.iter().zip(&got.sensors) {
        assert_eq!(g.zero_mm, a.zero_mm.map(f));
        assert_eq!(g.dir, a.dir.map(f));
        assert_eq!(g.ext.gain, f(a.ext.gain));
        assert_eq!(g.ext.spot_mm, a.ext.spot_mm);
        assert_eq!(g.transfer, a.transfer);
    }
    assert_eq!(got.sensors[1].ext.spot_mm, Some([0.375, -1.25]));
    assert!(
        got.model.split('+').any(|m| m == "incidence"),
        "{}",
        got.model
    );
    // The pulled file is accepted by push and changes nothing.
    let out = ok(&b.node(&["push", back.to_str().unwrap()]));
    assert!(out.contains("(0 changed"), "{out}");
    let v: serde_json::Value =
        serde_json::from_str(ok(&b.node(&["info", "--json"])).trim()).unwrap();
    assert_eq!(v["calibration_unlocked"], false);
    // the pulled file's own stamp put back (the board carries the same
    // calibration and record), the count one higher
    let st2 = &v["calibration_stamp"];
    assert_eq!(st2["record_hash"], st.record_hash.as_str(), "{v}");
    assert_eq!(st2["utc_s"], st.utc_s, "{v}");
    assert_eq!(st2["store_count"], 2, "{v}");
}

#[test]
fn capture_appends_rows_in_the_exchange_format() {
    let b = Board::start(&[]);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("poses.csv");
    let ps = p.to_str().unwrap();
    for pose in ["1", "2"] {
        let args = [
            "capture",
            "--plane",
            PLANE,
            "--pose",
            pose,
            "--out",
            ps,
            "--samples",
            "8",
        ];
        let out = ok(&b.node(&args));
        assert!(out.contains("4 of 4 readings"), "{out}");
    }
    let t = perpend_formats::exchange::read_poses(&p, Some(4)).unwrap();
    assert_eq!(t.rows.len(), 2);
    let r = &t.rows[1];
    assert!(r.readings.iter().all(|x| x.is_some_and(|d| d > 0.0)));
    assert_eq!(r.noise.n_samples, Some(8));
    assert!(r.noise.sd_mm.iter().all(|s| s.is_some()));
    assert!(r.t_s.unwrap() >= t.rows[0].t_s.unwrap());
    // The same pose again is refused, the file unchanged.
    let before = std::fs::read_to_string(&p).unwrap();
    let err = failed(&b.node(&["capture", "--plane", PLANE, "--pose", "2", "--out", ps]));
    assert!(err.contains("pose 2 is already there"), "{err}");
    assert_eq!(std::fs::read_to_string(&p).unwrap(), before);
}

/// Issue 11 item 7: a log taken over CAN records the temperature the
/// board measures (0x200A, the temperature its thermal correction uses).
#[test]
fn capture_records_the_board_temperature() {
    let b = Board::start(&["--temp-c", "31.5"]);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("poses.csv");
    let ps = p.to_str().unwrap();
    ok(&b.node(&[
        "capture",
        "--plane",
        PLANE,
        "--pose",
        "1",
        "--out",
        ps,
        "--samples",
        "4",
    ]));
    let t = perpend_formats::exchange::read_poses(&p, Some(4)).unwrap();
    let temp = t.rows[0].temp_c.unwrap();
    assert!((temp - 31.5).abs() < 1e-3, "{temp}");
}

#[test]
fn capture_with_a_faulted_sensor_keeps_the_row_and_warns() {
    let b = Board::start(&["--fault", "2:open"]);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("poses.csv");
    let args = [
        "capture",
        "--plane",
        PLANE,
        "--pose",
        "7",
        "--out",
        p.to_str().unwrap(),
        "--samples",
        "5",
    ];
    let o = b.node(&args);
    ok(&o);
    let (_, err) = text(&o);
    assert!(
        err.contains("warning: sensor 2: 5 of 5 samples not valid (open loop"),
        "{err}"
    );
    let t = perpend_formats::exchange::read_poses(&p, Some(4)).unwrap();
    assert_eq!(t.rows[0].readings[1], None);
    assert!(t.rows[0].readings[0].is_some());
}

#[test]
fn a_wrong_node_id_names_node_bus_and_who_answers() {
    let b = Board::start(&[]);
    let err = failed(&b.node_as("17", &["--timeout-ms", "300", "info"]));
    assert!(
        err.contains(&format!("no answer from node 17 on {}", b.bus)),
        "{err}"
    );
    assert!(
        err.contains("heard on the bus: node 16; is --node-id right?"),
        "{err}"
    );
}

#[test]
fn an_operational_board_and_a_foreign_file_are_refused() {
    let b = Board::start(&[]);
    let dir = tempfile::tempdir().unwrap();
    let p3 = dir.path().join("three.json");
    params_file(&p3, 3);
    let err = failed(&b.node(&["push", p3.to_str().unwrap()]));
    assert!(
        err.contains("has 3 sensors") && err.contains("another head"),
        "{err}"
    );
    let p = dir.path().join("params.json");
    params_file(&p, 4);
    ok(&b.node(&["nmt", "start"]));
    let err = failed(&b.node(&["push", p.to_str().unwrap()]));
    assert!(
        err.contains("is operational") && err.contains("--preop"),
        "{err}"
    );
    let out = ok(&b.node(&["push", p.to_str().unwrap(), "--preop"]));
    assert!(out.contains("nmt start"), "{out}");
}

#[test]
fn monitor_logs_rows_and_returns_the_board_to_pre_operational() {
    let b = Board::start(&[]);
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("live.csv");
    let args = [
        "monitor",
        "--start",
        "--seconds",
        "1.5",
        "--sync-hz",
        "20",
        "--csv",
        csv.to_str().unwrap(),
    ];
    let out = ok(&b.node(&args));
    assert!(out.contains("θ1"), "{out}");
    let log = std::fs::read_to_string(&csv).unwrap();
    let mut lines = log.lines();
    let head = lines.next().unwrap();
    assert!(
        head.starts_with(
            "t_s,sample,theta1_deg,theta2_deg,theta_deg,pitch_deg,yaw_deg,nx,ny,nz,d1_mm"
        ),
        "{head}"
    );
    let rows: Vec<&str> = lines.collect();
    assert!(rows.len() >= 10, "{} rows", rows.len());
    // θ1 of the plane within 0.01° (Tian eq. 1-3: atan2(n_y, -n_z)).
    let th1: f64 = rows[rows.len() - 1]
        .split(',')
        .nth(2)
        .unwrap()
        .parse()
        .unwrap();
    let k = (0.035f64 * 0.035 + 0.052 * 0.052 + 1.0).sqrt();
    let want = (0.052 / k).atan2(1.0 / k).to_degrees();
    assert!((th1 - want).abs() < 0.01, "{th1} vs {want}");
    // Pitch/yaw (Chen eq. 22: Rot(y, yaw)·Rot(x, pitch)·e_z = -n, with
    // -n = (a, b, c)/|(a, b, c)| for this plane): sin(pitch) = -(-n)_y,
    // tan(yaw) = (-n)_x / (-n)_z.
    let col = |k: usize| -> f64 {
        rows[rows.len() - 1]
            .split(',')
            .nth(k)
            .unwrap()
            .parse()
            .unwrap()
    };
    let (pitch, yaw) = (col(5), col(6));
    let want_pitch = (0.052 / k).asin().to_degrees();
    let want_yaw = 0.035f64.atan2(1.0).to_degrees();
    assert!(
        (pitch - want_pitch).abs() < 0.01,
        "pitch {pitch} vs {want_pitch}"
    );
    assert!((yaw - want_yaw).abs() < 0.01, "yaw {yaw} vs {want_yaw}");
    let v: serde_json::Value =
        serde_json::from_str(ok(&b.node(&["info", "--json"])).trim()).unwrap();
    assert_eq!(v["nmt_state"], "pre-operational");
}

/// A running `perpend node` process; killed on drop unless taken.
struct Proc(Option<Child>);

impl Drop for Proc {
    fn drop(&mut self) {
        if let Some(c) = self.0.as_mut() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Board {
    fn spawn_node(&self, args: &[&str]) -> Proc {
        let c = Command::new(env!("CARGO_BIN_EXE_perpend"))
            .args(["--quiet", "node", "--bus", &self.bus, "--node-id", NODE])
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        Proc(Some(c))
    }
}

/// Sends SIGINT after `after` and waits (at most 10 s) for the exit.
#[cfg(unix)]
fn interrupt(mut p: Proc, after: Duration) -> Output {
    use nix::sys::signal::{kill, Signal};
    use nix::unistd::Pid;
    std::thread::sleep(after);
    let pid = p.0.as_ref().unwrap().id();
    kill(Pid::from_raw(pid as i32), Signal::SIGINT).unwrap();
    let end = Instant::now() + Duration::from_secs(10);
    while p.0.as_mut().unwrap().try_wait().unwrap().is_none() {
        assert!(Instant::now() < end, "no exit within 10 s of Ctrl-C");
        std::thread::sleep(Duration::from_millis(20));
    }
    p.0.take().unwrap().wait_with_output().unwrap()
}

#[cfg(unix)]
#[test]
fn ctrl_c_appends_nothing_and_leaves_the_board_as_found() {
    let b = Board::start(&[]);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("poses.csv");
    let args = [
        "capture",
        "--plane",
        PLANE,
        "--pose",
        "1",
        "--out",
        p.to_str().unwrap(),
        "--samples",
        "100000",
    ];
    let o = interrupt(b.spawn_node(&args), Duration::from_millis(800));
    let err = failed(&o);
    assert!(
        err.contains("interrupted (Ctrl-C): nothing was appended"),
        "{err}"
    );
    assert!(!p.exists());
    // A monitor that started the node ends at Ctrl-C with the node
    // pre-operational again.
    let o = interrupt(
        b.spawn_node(&["monitor", "--start"]),
        Duration::from_millis(2500),
    );
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}\n{err}");
    assert!(err.contains("the node is pre-operational again"), "{err}");
    let v: serde_json::Value =
        serde_json::from_str(ok(&b.node(&["info", "--json"])).trim()).unwrap();
    assert_eq!(v["nmt_state"], "pre-operational");
}

/// Issue 47 point 6: the summary counts the rows it printed apart from
/// the rows it received (printing is limited to five a second), and each
/// count is true: the printed lines, the CSV's rows.
#[test]
fn monitor_summary_counts_what_it_printed_and_what_it_logged() {
    let b = Board::start(&[]);
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("live.csv");
    let args = ["monitor", "--start", "--seconds", "2", "--sync-hz", "10"];
    let out = b.node(&[&args[..], &["--csv", csv.to_str().unwrap()]].concat());
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    let printed = stdout.lines().filter(|l| l.starts_with("t ")).count();
    let logged = std::fs::read_to_string(&csv).unwrap().lines().count() - 1;
    let summary = stderr
        .lines()
        .find(|l| l.starts_with("monitor: "))
        .unwrap_or_else(|| panic!("no summary: {stderr}"));
    let want = if printed == logged {
        format!("monitor: {logged} rows, all shown")
    } else {
        format!("monitor: {logged} rows, {printed} shown (at most 5 a second; every row in")
    };
    assert!(summary.starts_with(&want), "{summary} vs {want}");
    assert!(
        printed < logged,
        "10 Hz rows, 5 printed a second: {summary}"
    );
}

/// Issue 47 point 5: node-id 0xFF (not configured) is refused at once,
/// with the way to a configured node (LSS), before the bus is opened.
#[test]
fn node_id_ff_is_refused_with_the_way_to_lss() {
    let t = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_perpend"))
        .args([
            "node",
            "--bus",
            "tcp:127.0.0.1:9",
            "--node-id",
            "0xFF",
            "info",
        ])
        .output()
        .unwrap();
    let err = failed(&out);
    assert!(t.elapsed() < Duration::from_secs(1), "{err}");
    assert!(
        err.contains("not configured") && err.contains("lss scan") && err.contains("--assign"),
        "{err}"
    );
}

/// Issue 47, a newcomer's pass: a mistake of the command line (a
/// --node-id the command refuses, a file that is not there) is named
/// before the bus is opened, not hidden behind an unreachable bus.
#[test]
fn command_line_mistakes_come_before_the_bus() {
    let run = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_perpend"))
            .args(["node", "--bus", "tcp:127.0.0.1:9", "--node-id", "3"])
            .args(args)
            .output()
            .unwrap();
        failed(&out)
    };
    let e = run(&["lss", "scan"]);
    assert!(
        e.contains("leave out --node-id 3") && !e.contains("cannot open"),
        "{e}"
    );
    let e = run(&["update", "/nonexistent/fw.signed.bin"]);
    assert!(
        e.contains("cannot read /nonexistent/fw.signed.bin") && !e.contains("cannot open"),
        "{e}"
    );
}
