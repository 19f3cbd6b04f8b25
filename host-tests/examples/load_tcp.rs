//! Load measurement of the real virtual-board process (issue 7 item 5):
//! starts `perpend board` on a loopback port, connects as an slcan client
//! and drives it with SYNC at a fixed rate and SDO requests at a target
//! rate (or as fast as the socket takes them), optionally issues a 0x1010
//! store in the middle, then reports missed SYNC responses, achieved frame
//! rates and whether the stored values read back after an NMT reset node.
//!
//! ```text
//! cargo run -p host-tests --example load_tcp -- [--bin PATH] [--seconds 5]
//!     [--sync-hz 1000] [--sdo-per-s 8000 | --sdo-per-s 0 (unlimited)] [--store-at 2.5]
//! ```
//!
//! A measurement, not a test: the virtual board runs on a general-purpose
//! OS with a 200 µs idle sleep, so figures depend on the machine. Output:
//! one `key=value` line per figure and a final JSON line.
#![allow(missing_docs, clippy::unwrap_used, clippy::panic)]

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const NODE: u16 = 0x10;
const UNLOCK: u32 = 0x6C61_6375;
const SAVE: u32 = 0x6576_6173;

struct Args {
    bin: String,
    seconds: f64,
    sync_hz: f64,
    sdo_per_s: f64,
    store_at: Option<f64>,
}

fn parse_args() -> Args {
    let target = std::env::var("CARGO_TARGET_DIR")
        .unwrap_or_else(|_| concat!(env!("CARGO_MANIFEST_DIR"), "/../target").to_string());
    let mut a = Args {
        bin: format!("{target}/debug/perpend"),
        seconds: 5.0,
        sync_hz: 1000.0,
        sdo_per_s: 8000.0,
        store_at: Some(2.5),
    };
    let v: Vec<String> = std::env::args().skip(1).collect();
    let mut i = 0;
    while i < v.len() {
        let val = v.get(i + 1).cloned().unwrap_or_default();
        match v[i].as_str() {
            "--bin" => a.bin = val,
            "--seconds" => a.seconds = val.parse().unwrap(),
            "--sync-hz" => a.sync_hz = val.parse().unwrap(),
            "--sdo-per-s" => a.sdo_per_s = val.parse().unwrap(),
            "--store-at" => a.store_at = val.parse().ok().filter(|x: &f64| *x > 0.0),
            other => panic!("unknown argument {other}"),
        }
        i += 2;
    }
    a
}

fn frame_line(id: u16, data: &[u8]) -> String {
    let mut s = format!("t{id:03X}{}", data.len());
    for b in data {
        s.push_str(&format!("{b:02X}"));
    }
    s.push('\r');
    s
}

fn sdo_req(cmd: u8, index: u16, sub: u8, v: u32) -> String {
    let i = index.to_le_bytes();
    let d = v.to_le_bytes();
    frame_line(
        0x600 + NODE,
        &[cmd, i[0], i[1], sub, d[0], d[1], d[2], d[3]],
    )
}

/// The requests of the flood (all answered by one frame in operational).
fn flood_requests() -> Vec<String> {
    vec![
        sdo_req(0x40, 0x1018, 1, 0),
        sdo_req(0x40, 0x2002, 1, 0),
        sdo_req(0x40, 0x2005, 0, 0),
        sdo_req(0x23, 0x2300, 1, 2000), // refused in operational
        sdo_req(0x40, 0x3000, 0, 0),    // no such object
        sdo_req(0xA0, 0x1008, 0, 0),    // block upload: refused
        sdo_req(0x40, 0x2007, 0, 0),
    ]
}

#[derive(Default)]
struct Rx {
    lines: AtomicU64,
    tpdo: [AtomicU64; 4],
    sdo: AtomicU64,
    acks: AtomicU64,
    errors: AtomicU64,
    bootups: AtomicU64,
    stale: AtomicU64,
    last_counter: AtomicU64,
    /// The last SDO responses (for the read-back phase).
    responses: Mutex<Vec<[u8; 8]>>,
}

fn parse_frame(line: &str) -> Option<(u16, Vec<u8>)> {
    let b = line.as_bytes();
    if b.first() != Some(&b't') || b.len() < 5 {
        return None;
    }
    let id = u16::from_str_radix(&line[1..4], 16).ok()?;
    let n = (b[4] - b'0') as usize;
    let data = (0..n)
        .map(|k| u8::from_str_radix(&line[5 + 2 * k..7 + 2 * k], 16).ok())
        .collect::<Option<Vec<u8>>>()?;
    Some((id, data))
}

fn reader(stream: TcpStream, rx: Arc<Rx>, stop: Arc<AtomicBool>) {
    let mut stream = stream;
    stream
        .set_read_timeout(Some(Duration::from_millis(50)))
        .unwrap();
    let mut buf = vec![0u8; 1 << 16];
    let mut line = Vec::new();
    while !stop.load(Ordering::Relaxed) {
        let n = match stream.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(_) => continue,
        };
        for &c in &buf[..n] {
            match c {
                b'\r' => {
                    let l = String::from_utf8_lossy(&line).to_string();
                    line.clear();
                    rx.lines.fetch_add(1, Ordering::Relaxed);
                    if l == "z" || l.is_empty() {
                        rx.acks.fetch_add(1, Ordering::Relaxed);
                        continue;
                    }
                    let Some((id, data)) = parse_frame(&l) else {
                        continue;
                    };
                    match id {
                        x if x == 0x180 + NODE => {
                            rx.tpdo[0].fetch_add(1, Ordering::Relaxed);
                        }
                        x if x == 0x280 + NODE => {
                            rx.tpdo[1].fetch_add(1, Ordering::Relaxed);
                            let c = u32::from_le_bytes([data[4], data[5], data[6], data[7]]) as u64;
                            if rx.last_counter.swap(c, Ordering::Relaxed) == c {
                                rx.stale.fetch_add(1, Ordering::Relaxed);
                            }
                        }
                        x if x == 0x380 + NODE => {
                            rx.tpdo[2].fetch_add(1, Ordering::Relaxed);
                        }
                        x if x == 0x480 + NODE => {
                            rx.tpdo[3].fetch_add(1, Ordering::Relaxed);
                        }
                        x if x == 0x580 + NODE => {
                            rx.sdo.fetch_add(1, Ordering::Relaxed);
                            let mut d = [0u8; 8];
                            d.copy_from_slice(&data[..8]);
                            rx.responses.lock().unwrap().push(d);
                        }
                        x if x == 0x700 + NODE && data == [0] => {
                            rx.bootups.fetch_add(1, Ordering::Relaxed);
                        }
                        _ => {}
                    }
                }
                0x07 => {
                    rx.errors.fetch_add(1, Ordering::Relaxed);
                }
                b'\n' => {}
                c => line.push(c),
            }
        }
    }
}

fn start_board(bin: &str) -> (Child, u16) {
    let mut child = Command::new(bin)
        .args([
            "board",
            "--slcan",
            "127.0.0.1:0",
            "--node-id",
            &NODE.to_string(),
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {bin}: {e}"));
    let mut first = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut first)
        .unwrap();
    let port = first.trim().rsplit(':').next().unwrap().parse().unwrap();
    (child, port)
}

/// One expedited request and its answer (phase without load).
fn request(w: &mut TcpStream, rx: &Rx, line: &str) -> [u8; 8] {
    let before = rx.sdo.load(Ordering::SeqCst);
    w.write_all(line.as_bytes()).unwrap();
    let t = Instant::now();
    while rx.sdo.load(Ordering::SeqCst) == before {
        assert!(t.elapsed() < Duration::from_secs(5), "no answer to {line}");
        std::thread::sleep(Duration::from_millis(1));
    }
    *rx.responses.lock().unwrap().last().unwrap()
}

fn main() {
    let a = parse_args();
    let (mut child, port) = start_board(&a.bin);
    let mut w = TcpStream::connect(("127.0.0.1", port)).unwrap();
    w.set_nodelay(true).unwrap();
    let rx = Arc::new(Rx::default());
    let stop = Arc::new(AtomicBool::new(false));
    let reader_thread = {
        let (s, rx, stop) = (w.try_clone().unwrap(), rx.clone(), stop.clone());
        std::thread::spawn(move || reader(s, rx, stop))
    };
    w.write_all(b"O\r").unwrap();
    std::thread::sleep(Duration::from_millis(100));

    // Pre-operational: unlock, write the values the store must keep.
    let values: [(u16, u8, u32); 3] = [
        (0x2101, 8, 0.0025f32.to_bits()),
        (0x2202, 4, 79.5f32.to_bits()),
        (0x2300, 4, 0.07f32.to_bits()),
    ];
    assert_eq!(
        request(&mut w, &rx, &sdo_req(0x23, 0x2010, 0, UNLOCK))[0],
        0x60
    );
    for (i, s, v) in values {
        assert_eq!(request(&mut w, &rx, &sdo_req(0x23, i, s, v))[0], 0x60);
    }
    w.write_all(frame_line(0, &[0x01, NODE as u8]).as_bytes())
        .unwrap();
    std::thread::sleep(Duration::from_millis(50));

    // The flood.
    let reqs = flood_requests();
    let sync = frame_line(0x080, &[]);
    let store = sdo_req(0x23, 0x1010, 1, SAVE);
    let t0 = Instant::now();
    let sync_period = 1.0 / a.sync_hz;
    let (mut syncs, mut sdos, mut k) = (0u64, 0u64, 0usize);
    let mut store_pending = a.store_at;
    let tpdo_before = rx.tpdo[0].load(Ordering::SeqCst);
    let mut out = String::new();
    loop {
        let t = t0.elapsed().as_secs_f64();
        if t >= a.seconds {
            break;
        }
        out.clear();
        let due_syncs = (t / sync_period) as u64 + 1;
        while syncs < due_syncs {
            out.push_str(&sync);
            syncs += 1;
        }
        if store_pending.is_some_and(|s| t >= s) {
            store_pending = None;
            out.push_str(&store);
            sdos += 1;
        }
        let due_sdos = if a.sdo_per_s > 0.0 {
            (t * a.sdo_per_s) as u64
        } else {
            sdos + 64
        };
        while sdos < due_sdos {
            out.push_str(&reqs[k % reqs.len()]);
            k += 1;
            sdos += 1;
        }
        if !out.is_empty() {
            w.write_all(out.as_bytes()).unwrap();
        } else {
            std::thread::sleep(Duration::from_micros(100));
        }
    }
    let elapsed = t0.elapsed().as_secs_f64();
    // Let the board drain what it has received: until nothing arrives for
    // 500 ms (at most 60 s).
    let drain = Instant::now();
    let mut last = (rx.lines.load(Ordering::SeqCst), Instant::now());
    while last.1.elapsed() < Duration::from_millis(500) && drain.elapsed() < Duration::from_secs(60)
    {
        std::thread::sleep(Duration::from_millis(20));
        let n = rx.lines.load(Ordering::SeqCst);
        if n != last.0 {
            last = (n, Instant::now());
        }
    }
    let drain_s = drain.elapsed().as_secs_f64() - 0.5;
    let tpdo1 = rx.tpdo[0].load(Ordering::SeqCst) - tpdo_before;
    let tpdo_all: u64 = rx
        .tpdo
        .iter()
        .map(|x| x.load(Ordering::SeqCst))
        .sum::<u64>();
    let answered = rx.sdo.load(Ordering::SeqCst);
    let missed = syncs.saturating_sub(tpdo1);
    let stale = rx.stale.load(Ordering::SeqCst);
    let store_ok = rx
        .responses
        .lock()
        .unwrap()
        .iter()
        .any(|r| r[0] == 0x60 && r[1..4] == [0x10, 0x10, 1]);

    // Read back after NMT pre-operational + reset node.
    w.write_all(frame_line(0, &[0x80, NODE as u8]).as_bytes())
        .unwrap();
    let boots = rx.bootups.load(Ordering::SeqCst);
    w.write_all(frame_line(0, &[0x81, NODE as u8]).as_bytes())
        .unwrap();
    let t = Instant::now();
    while rx.bootups.load(Ordering::SeqCst) == boots {
        assert!(
            t.elapsed() < Duration::from_secs(5),
            "no boot-up after reset node"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    let mut read_back_ok = true;
    for (i, s, v) in values {
        let r = request(&mut w, &rx, &sdo_req(0x40, i, s, 0));
        let got = u32::from_le_bytes([r[4], r[5], r[6], r[7]]);
        if got != v || r[0] != 0x43 {
            read_back_ok = false;
            println!("read_back {i:#06x}/{s}: {got:#010x}, want {v:#010x}");
        }
    }
    stop.store(true, Ordering::SeqCst);
    let _ = reader_thread.join();
    let _ = child.kill();
    let _ = child.wait();

    let sent = syncs + sdos;
    println!("seconds={elapsed:.2} (then {drain_s:.2} s until the board's output stopped)");
    println!("sync_sent={syncs} ({:.0}/s)", syncs as f64 / elapsed);
    println!("sdo_sent={sdos} ({:.0}/s)", sdos as f64 / elapsed);
    println!("frames_sent_per_s={:.0}", sent as f64 / elapsed);
    println!("tpdo_received={tpdo_all} tpdo1={tpdo1}");
    println!("missed_sync_responses={missed}");
    println!("stale_tpdo2_counters={stale}");
    println!("sdo_answered={answered}");
    println!(
        "frames_received_per_s={:.0}",
        (tpdo_all + answered) as f64 / elapsed
    );
    println!("slcan_errors={}", rx.errors.load(Ordering::SeqCst));
    println!("store_confirmed={store_ok} read_back_after_reset_node={read_back_ok}");
    println!(
        "{{\"seconds\":{elapsed:.2},\"drain_s\":{drain_s:.2},\"sync_hz\":{},\"sync_sent\":{syncs},\"sdo_sent\":{sdos},\"frames_sent_per_s\":{:.0},\"missed_sync_responses\":{missed},\"stale\":{stale},\"sdo_answered\":{answered},\"store_confirmed\":{store_ok},\"read_back_ok\":{read_back_ok}}}",
        a.sync_hz,
        sent as f64 / elapsed
    );
}
