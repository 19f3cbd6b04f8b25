//! The slcan-over-TCP server of the virtual board: one client at a time
//! (others wait in the listen queue until it disconnects), real-time
//! clock, one sample per acquisition period, or one per SYNC when 0x2301
//! locks acquisition to SYNC (the scan is taken when the SYNC is read).
//!
//! Each loop turn: accept or read the client, parse its slcan lines
//! ([`crate::slcan`]), hand transmitted frames to the board, run the
//! samples that are due, poll the board, and send what it produced while
//! the channel is open (`O`). The board keeps running without a client
//! (frames are then dropped, as on a bus with nobody listening).
//!
//! Latency: for every TPDO 1 (θ1/θ2) handed to the socket the server notes
//! the time since the acquisition of the sample it carries, and prints the
//! distribution (median, 99th percentile, max) when the client disconnects:
//! the acquisition-to-frame latency as far as it can be measured on the
//! host (it includes the wait for the controller's SYNC).
//!
//! Link faults (`perpend board --fault bus:drop:IDX:N`, `bus:reset:IDX:N`,
//! [`LinkFault`]) act on the client's N-th SDO request to one object: the
//! connection is closed before the answer goes out, or an NMT reset node
//! follows the request on the bus; each fires once. Block-tail faults
//! (`bus:block-tail:N:K`, [`super::tail`]) drop the last segments of a
//! block download's sub-block.
//!
//! Limits: the loop sleeps at most 200 µs when idle, so timestamps are
//! accurate to a fraction of a millisecond; if it falls more than 50
//! samples behind (machine overloaded) it skips the missed samples.

use std::io::{ErrorKind, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result};
use perpend_can::Frame;

use super::node::VirtualBoard;
use super::world::World;
use crate::slcan::{self, Command, LineSplitter, BUSY_PREFIX};

/// Largest amount of unsent output kept for a slow client [bytes]; beyond
/// it frames are dropped (a bus does not wait either).
const MAX_BACKLOG: usize = 1 << 20;
/// Most samples run in one loop turn before skipping ahead.
const MAX_CATCH_UP: u32 = 50;
/// Most bytes taken from the client per loop turn (~190 frames): a client
/// that writes faster than the board handles frames is throttled by TCP
/// flow control, as a bus would throttle it, instead of holding the loop
/// in its read (no samples, no SYNC answers, output dropped).
const MAX_READ: usize = 4096;

struct Client {
    stream: TcpStream,
    /// The client's address, told to a second client that is refused.
    peer: String,
    lines: LineSplitter,
    open: bool,
    listen_only: bool,
    out: Vec<u8>,
    /// The bit rate set with `Sn` \[kbit/s\] (`None`: never set, hears
    /// every rate).
    kbps: Option<u16>,
}

/// The slcan `Sn` rates \[kbit/s\] (n = 0..8).
const SLCAN_KBPS: [u16; 9] = [10, 20, 50, 100, 125, 250, 500, 800, 1000];

/// The rate of an `Sn` line, if it is one.
fn slcan_rate(line: &[u8]) -> Option<u16> {
    match line {
        [b'S', d @ b'0'..=b'8'] => SLCAN_KBPS.get((d - b'0') as usize).copied(),
        _ => None,
    }
}

impl Client {
    fn new(stream: TcpStream) -> std::io::Result<Self> {
        stream.set_nonblocking(true)?;
        stream.set_nodelay(true)?;
        let peer = stream
            .peer_addr()
            .map_or_else(|_| "an unknown address".into(), |a| a.to_string());
        Ok(Self {
            stream,
            peer,
            lines: LineSplitter::new(),
            open: false,
            listen_only: false,
            out: Vec::new(),
            kbps: None,
        })
    }

    /// Reads what is available, at most [`MAX_READ`] bytes; returns the
    /// frames to transmit, or `None` when the client has gone.
    fn read(&mut self) -> Option<Vec<Frame>> {
        let mut frames = Vec::new();
        let mut buf = [0u8; MAX_READ];
        loop {
            match self.stream.read(&mut buf) {
                Ok(0) => return None,
                Ok(n) => {
                    let (open, listen_only, out, kbps) = (
                        &mut self.open,
                        &mut self.listen_only,
                        &mut self.out,
                        &mut self.kbps,
                    );
                    self.lines.feed(&buf[..n], |line| {
                        if let Some(k) = line.ok().and_then(slcan_rate) {
                            *kbps = Some(k);
                        }
                        match line.and_then(slcan::parse) {
                            Ok(cmd) => {
                                match cmd {
                                    Command::Open => {
                                        *open = true;
                                        *listen_only = false;
                                    }
                                    Command::ListenOnly => {
                                        *open = true;
                                        *listen_only = true;
                                    }
                                    Command::Close => *open = false,
                                    Command::Transmit(f) if *open && !*listen_only => {
                                        frames.push(f)
                                    }
                                    _ => {}
                                }
                                if out.len() < MAX_BACKLOG {
                                    out.extend_from_slice(slcan::reply(&cmd));
                                }
                            }
                            // python-can's set_bitrate sends an empty
                            // data-bit-rate line: not an error.
                            Err(slcan::SlcanError::Empty) => {}
                            Err(_) if out.len() < MAX_BACKLOG => {
                                out.extend_from_slice(slcan::ERROR)
                            }
                            Err(_) => {}
                        }
                    });
                    return Some(frames);
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => return Some(frames),
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(_) => return None,
            }
        }
    }

    /// Sends as much pending output as the socket takes; `false` when the
    /// client has gone.
    fn flush(&mut self) -> bool {
        while !self.out.is_empty() {
            match self.stream.write(&self.out) {
                Ok(0) => return false,
                Ok(n) => {
                    self.out.drain(..n);
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => return true,
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(_) => return false,
            }
        }
        true
    }
}

/// Acquisition-to-frame latencies [µs] of the TPDO 1 frames sent to one
/// client (at most [`Latency::CAP`] kept).
#[derive(Debug, Default)]
pub struct Latency {
    us: Vec<u64>,
}

impl Latency {
    /// Most latencies kept per client.
    pub const CAP: usize = 1 << 20;

    /// Notes one frame's latency.
    pub fn note(&mut self, us: u64) {
        if self.us.len() < Self::CAP {
            self.us.push(us);
        }
    }

    /// `(count, median, p99, max)` [µs], `None` without frames.
    pub fn summary(&mut self) -> Option<(usize, u64, u64, u64)> {
        if self.us.is_empty() {
            return None;
        }
        self.us.sort_unstable();
        let n = self.us.len();
        let at = |q: f64| self.us[((n - 1) as f64 * q).round() as usize];
        Some((n, at(0.5), at(0.99), self.us[n - 1]))
    }

    /// Prints the summary to stderr and forgets the frames.
    fn report(&mut self) {
        if let Some((n, med, p99, max)) = self.summary() {
            eprintln!(
                "perpend board: acquisition-to-frame latency over {n} TPDO 1 frames: \
                 median {med} µs, p99 {p99} µs, max {max} µs"
            );
        }
        self.us.clear();
    }
}

/// A frame on the virtual bus: its sender (`None`: the client), its rate
/// \[kbit/s\] (`None`: a client that never set one) and the frame.
type Wire = (Option<usize>, Option<u16>, Frame);

/// Most board-to-board deliveries per loop turn (an echo storm between
/// boards cannot hold the loop).
const MAX_BUS_HOPS: usize = 4096;

/// Puts `f` of board `from` (at rate `kbps`) into `wire` unless an
/// identical frame of another board is there already: identical frames
/// sent at the same time are one frame on CAN (LSS answers of several
/// slaves, for instance).
fn push_merged(wire: &mut Vec<Wire>, from: usize, kbps: u16, f: Frame) {
    if !wire
        .iter()
        .any(|&(s, k, g)| s != Some(from) && k == Some(kbps) && g == f)
    {
        wire.push((Some(from), Some(kbps), f));
    }
}

/// Whether a frame sent at `a` is received at `b` (a rate of `None`
/// hears and is heard at every rate).
fn rates_agree(a: Option<u16>, b: Option<u16>) -> bool {
    a.is_none() || b.is_none() || a == b
}

/// What a [`LinkFault`] does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkAction {
    /// Close the client's connection (its answer lost).
    Drop,
    /// Reset the addressed board (NMT reset node) after the request.
    Reset,
}

/// `--fault bus:drop:IDX:N` or `bus:reset:IDX:N`: at the client's N-th
/// SDO request (upload or download initiate) to object IDX.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LinkFault {
    /// What happens.
    pub action: LinkAction,
    /// The object whose requests are counted.
    pub index: u16,
    /// Which request (1 = the first).
    pub nth: u32,
}

impl std::str::FromStr for LinkFault {
    type Err = anyhow::Error;
    /// Parses `drop:IDX:N` or `reset:IDX:N` (IDX decimal or 0x hex).
    fn from_str(s: &str) -> Result<Self> {
        let mut it = s.split(':');
        let action = match it.next() {
            Some("drop") => Some(LinkAction::Drop),
            Some("reset") => Some(LinkAction::Reset),
            _ => None,
        };
        let index = it.next().and_then(|t| {
            let t = t.trim();
            match t.strip_prefix("0x").or_else(|| t.strip_prefix("0X")) {
                Some(h) => u16::from_str_radix(h, 16).ok(),
                None => t.parse().ok(),
            }
        });
        let nth = it.next().and_then(|t| t.trim().parse::<u32>().ok());
        match (action, index, nth, it.next()) {
            (Some(action), Some(index), Some(nth), None) if nth >= 1 => {
                Ok(Self { action, index, nth })
            }
            _ => anyhow::bail!(
                "--fault 'bus:{s}': expected bus:drop:IDX:N or bus:reset:IDX:N (IDX an object, \
                 e.g. 0x2101; N ≥ 1: the N-th SDO request to it)"
            ),
        }
    }
}

/// The link faults of a run with their counts; each fires once.
struct LinkFaults(Vec<(LinkFault, u32, bool)>);

impl LinkFaults {
    /// Looks at the client's `frames` of one turn: inserts the NMT resets
    /// that fire; returns `true` when the connection is to be dropped (the
    /// frames after the one that fired it are discarded).
    fn apply(&mut self, frames: &mut Vec<Frame>) -> bool {
        let mut k = 0;
        while k < frames.len() {
            let f = frames[k];
            k += 1;
            let sdo = (0x601..=0x67F).contains(&f.id) && f.len == 8 && !f.rtr;
            if !(sdo && matches!(f.data[0] >> 5, 1 | 2)) {
                continue;
            }
            let index = u16::from_le_bytes([f.data[1], f.data[2]]);
            for (fault, count, fired) in &mut self.0 {
                if *fired || fault.index != index {
                    continue;
                }
                *count += 1;
                if *count < fault.nth {
                    continue;
                }
                *fired = true;
                match fault.action {
                    LinkAction::Drop => {
                        eprintln!("perpend board: fault: dropping the client at its SDO request {} to {index:#06x}", fault.nth);
                        frames.truncate(k);
                        return true;
                    }
                    LinkAction::Reset => {
                        eprintln!(
                            "perpend board: fault: reset after the SDO request {} to {index:#06x}",
                            fault.nth
                        );
                        let node = (f.id - 0x600) as u8;
                        frames.insert(k, Frame::new(0x000, &[0x81, node]));
                        k += 1;
                    }
                }
            }
        }
        false
    }
}

/// The virtual bus: the boards, one sample clock each.
struct Bus<'a> {
    boards: &'a mut [VirtualBoard],
    next_sample: Vec<u64>,
    last_sample: Vec<u64>,
}

impl Bus<'_> {
    /// Delivers `w` to every board but its sender whose rate agrees; what
    /// they send goes to `out` (merged).
    fn deliver(&mut self, w: Wire, now: u64, out: &mut Vec<Wire>) {
        let (from, kbps, f) = w;
        for (i, b) in self.boards.iter_mut().enumerate() {
            if from == Some(i) || !rates_agree(kbps, Some(b.bit_rate_kbps())) {
                continue;
            }
            let mut sent = Vec::new();
            b.handle(&f, now, &mut |o| sent.push(o));
            // SYNC-locked acquisition (0x2301): the scan of this SYNC, now.
            if b.app_mut().take_sync_scan() {
                b.sample(now);
                self.last_sample[i] = now;
            }
            let k = b.bit_rate_kbps();
            sent.into_iter().for_each(|o| push_merged(out, i, k, o));
        }
    }

    /// Runs the samples that are due and polls every board.
    fn tick(&mut self, now: u64, out: &mut Vec<Wire>) {
        for (i, b) in self.boards.iter_mut().enumerate() {
            let period = b.period_us();
            let next = &mut self.next_sample[i];
            if b.app().sync_locked() {
                *next = now + period;
            }
            let mut k = 0;
            while *next <= now && k < MAX_CATCH_UP {
                b.sample(*next);
                self.last_sample[i] = *next;
                *next += period;
                k += 1;
            }
            if *next <= now {
                *next = now + period;
            }
            let mut sent = Vec::new();
            b.poll(now, &mut |o| sent.push(o));
            let kb = b.bit_rate_kbps();
            sent.into_iter().for_each(|o| push_merged(out, i, kb, o));
        }
    }

    /// The time to the next sample of any board.
    fn next_due(&self) -> u64 {
        self.next_sample.iter().copied().min().unwrap_or(0)
    }
}

/// New connections while a client holds the board: each waits up to
/// [`DOOR_GRACE`] (the holder may just be closing: a `perpend node` command
/// that ended, whose close the loop has not read yet), then is told in one
/// line that the board is in use (by whom) and read until it closes (at
/// most [`REFUSED_KEEP`]), so that closing it never resets what it has not
/// read yet.
#[derive(Default)]
struct Door {
    waiting: Vec<(TcpStream, String, Instant)>,
    refused: Vec<(TcpStream, Instant)>,
}

/// How long a new connection waits for the holder to go (shorter than the
/// host client's one-second set-up timeout, so it reads why).
const DOOR_GRACE: Duration = Duration::from_millis(500);
/// How long a refused connection is kept open for its client to read why.
const REFUSED_KEEP: Duration = Duration::from_secs(2);

impl Door {
    /// Tells waiting connections older than [`DOOR_GRACE`] that the board
    /// is held by `holder` and keeps them until they close.
    fn refuse_stale(&mut self, holder: &str) {
        let (stale, fresh): (Vec<_>, Vec<_>) = std::mem::take(&mut self.waiting)
            .into_iter()
            .partition(|(_, _, at)| at.elapsed() >= DOOR_GRACE);
        self.waiting = fresh;
        for (mut s, peer, _) in stale {
            let _ = s.write_all(format!("{BUSY_PREFIX} {holder}\r").as_bytes());
            eprintln!("perpend board: client {peer} refused: in use by {holder}");
            if s.set_nonblocking(true).is_ok() {
                self.refused.push((s, Instant::now()));
            }
        }
    }

    /// Reads and drops what the refused clients send; closes those that
    /// closed or are older than [`REFUSED_KEEP`].
    fn drain_refused(&mut self) {
        let mut buf = [0u8; 256];
        self.refused.retain_mut(|(s, at)| {
            let open = loop {
                match s.read(&mut buf) {
                    Ok(0) => break false,
                    Ok(_) => {}
                    Err(e) if e.kind() == ErrorKind::WouldBlock => break true,
                    Err(_) => break false,
                }
            };
            open && at.elapsed() < REFUSED_KEEP
        });
    }

    /// One turn: a new connection waits; the oldest waiting one becomes
    /// the client when there is none; the stale ones are refused.
    fn turn(&mut self, listener: &TcpListener, client: &mut Option<Client>) {
        self.drain_refused();
        match listener.accept() {
            Ok((s, peer)) => self.waiting.push((s, peer.to_string(), Instant::now())),
            Err(e) if e.kind() == ErrorKind::WouldBlock => {}
            Err(e) => eprintln!("perpend board: accept: {e}"),
        }
        match client {
            Some(c) => {
                let holder = c.peer.clone();
                self.refuse_stale(&holder);
            }
            None if !self.waiting.is_empty() => {
                let (s, peer, _) = self.waiting.remove(0);
                match Client::new(s) {
                    Ok(c) => {
                        eprintln!("perpend board: client {peer} connected");
                        *client = Some(c);
                    }
                    Err(e) => eprintln!("perpend board: client {peer}: {e}"),
                }
            }
            None => {}
        }
    }
}

/// Serves the boards on `listener` until the process is stopped: one
/// board, or several on one virtual bus (a cell; every frame a board sends
/// reaches the client and the other boards whose bit rate agrees);
/// `world`, if any, moves the plane of the first board ([`super::world`]).
///
/// # Errors
/// Only if the listener cannot be made non-blocking.
pub fn serve(
    listener: TcpListener,
    mut world: Option<World>,
    boards: &mut [VirtualBoard],
    faults: Vec<LinkFault>,
    mut tails: super::tail::BlockTails,
) -> Result<()> {
    let mut faults = LinkFaults(faults.into_iter().map(|f| (f, 0, false)).collect());
    listener
        .set_nonblocking(true)
        .context("making the listener non-blocking")?;
    let start = Instant::now();
    let mut client: Option<Client> = None;
    let n = boards.len();
    let mut bus = Bus {
        boards,
        next_sample: vec![0; n],
        last_sample: vec![0; n],
    };
    let mut latency = Latency::default();
    let mut door = Door::default();
    loop {
        let now = start.elapsed().as_micros() as u64;
        door.turn(&listener, &mut client);
        let mut busy = match (world.as_mut(), bus.boards.first_mut()) {
            (Some(w), Some(b)) => w.poll(b),
            _ => false,
        };
        // The bus of this turn: the client's frames, then what the boards
        // send (handed to the client and to the other boards).
        let mut wire: Vec<Wire> = Vec::new();
        let mut drop_client = false;
        if let Some(c) = client.as_mut() {
            match c.read() {
                Some(mut frames) => {
                    drop_client = faults.apply(&mut frames);
                    tails.apply(&mut frames);
                    busy |= !frames.is_empty();
                    wire.extend(frames.into_iter().map(|f| (None, c.kbps, f)));
                }
                None => {
                    eprintln!("perpend board: client disconnected");
                    latency.report();
                    client = None;
                }
            }
        }
        let mut heard: Vec<Wire> = Vec::new();
        let (mut i, mut polled) = (0, false);
        loop {
            if i < wire.len() && i < MAX_BUS_HOPS {
                let w = wire[i];
                i += 1;
                bus.deliver(w, now, &mut wire);
                if w.0.is_some() {
                    tails.observe(&w.2);
                    heard.push(w);
                }
            } else if polled {
                break;
            } else {
                bus.tick(now, &mut wire);
                polled = true;
            }
        }
        if drop_client {
            eprintln!("perpend board: client dropped (fault)");
            client = None;
        }
        if let Some(c) = client.as_mut() {
            let mut tpdo1 = Vec::new();
            if c.open {
                for &(from, kbps, f) in &heard {
                    if rates_agree(kbps, c.kbps) && c.out.len() < MAX_BACKLOG {
                        slcan::format_frame(&f, &mut c.out);
                        if f.id & 0x780 == 0x180 && f.id != 0x180 {
                            tpdo1.push(bus.last_sample[from.unwrap_or(0)]);
                        }
                    }
                }
            }
            busy |= !c.out.is_empty();
            let ok = c.flush();
            let sent = start.elapsed().as_micros() as u64;
            for t in tpdo1 {
                latency.note(sent.saturating_sub(t));
            }
            if !ok {
                eprintln!("perpend board: client disconnected");
                latency.report();
                client = None;
            }
        }
        if !busy {
            let until_sample = bus
                .next_due()
                .saturating_sub(start.elapsed().as_micros() as u64);
            std::thread::sleep(Duration::from_micros(until_sample.clamp(20, 200)));
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    use super::super::node::BoardConfig;
    use super::super::sim::SimHead;
    use perpend_core::geometry::Plane;

    fn boards(n: usize, node_id: u8) -> Vec<VirtualBoard> {
        (0..n)
            .map(|k| {
                let plane = Plane::from_abcd(0.0, 0.0, 1.0, -40.0).unwrap();
                let head = perpend_core::params::Params::factory().head.cast();
                let sim = SimHead::new(head, plane, 0.002, k as u64).unwrap();
                let cfg = BoardConfig {
                    node_id,
                    head: None,
                    calibration: None,
                    thermal_tau_s: 0.0,
                };
                VirtualBoard::with_serial(&cfg, sim, 0x100 + k as u32).unwrap()
            })
            .collect()
    }

    /// Sends `f` from the client at `kbps` to the bus; what the client hears.
    fn exchange(bus: &mut Bus, f: Frame, kbps: Option<u16>) -> Vec<Frame> {
        let mut wire = Vec::new();
        bus.deliver((None, kbps, f), 1000, &mut wire);
        wire.into_iter()
            .filter(|w| rates_agree(w.1, kbps))
            .map(|w| w.2)
            .collect()
    }

    #[test]
    fn identical_answers_of_several_boards_are_one_frame() {
        let mut b = boards(3, 0x20);
        let mut bus = Bus {
            next_sample: vec![0; b.len()],
            last_sample: vec![0; b.len()],
            boards: &mut b,
        };
        let lss = |c: u8, v: u8| Frame::new(0x7E5, &[c, v, 0, 0, 0, 0, 0, 0]);
        assert!(exchange(&mut bus, lss(0x04, 1), None).is_empty());
        // Same answer from all three: one frame.
        let a = exchange(&mut bus, lss(0x5E, 0), None);
        assert_eq!(a, vec![Frame::new(0x7E4, &[0x5E, 0x20, 0, 0, 0, 0, 0, 0])]);
        // Different answers (serials): three frames.
        assert_eq!(exchange(&mut bus, lss(0x5D, 0), None).len(), 3);
        // A master at another bit rate reaches nobody.
        assert!(exchange(&mut bus, lss(0x5E, 0), Some(500)).is_empty());
        assert_eq!(exchange(&mut bus, lss(0x5E, 0), Some(1000)).len(), 1);
    }

    #[test]
    fn slcan_rates_parse() {
        assert_eq!(slcan_rate(b"S8"), Some(1000));
        assert_eq!(slcan_rate(b"S6"), Some(500));
        assert_eq!(slcan_rate(b"S9"), None);
        assert_eq!(slcan_rate(b"s0014"), None);
    }

    #[test]
    fn latency_summary_quantiles() {
        let mut l = Latency::default();
        assert_eq!(l.summary(), None);
        for us in (1..=100).rev() {
            l.note(us);
        }
        assert_eq!(l.summary(), Some((100, 51, 99, 100)));
    }
    use std::net::TcpListener;

    /// A connected (server-side client, peer) pair on loopback.
    fn pair() -> (Client, TcpStream) {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let peer = TcpStream::connect(l.local_addr().unwrap()).unwrap();
        let (s, _) = l.accept().unwrap();
        (Client::new(s).unwrap(), peer)
    }

    /// One SDO upload request of 0x1000 to node 0x10 (22 bytes).
    const REQ: &[u8] = b"t61084000100000000000\r";

    /// Reads until `n` frames came in; returns the frames of each turn.
    fn read_all(c: &mut Client, n: usize) -> Vec<usize> {
        let mut turns = Vec::new();
        let mut total = 0;
        let t = std::time::Instant::now();
        while total < n {
            assert!(t.elapsed() < Duration::from_secs(10), "{total} of {n}");
            let f = c.read().unwrap();
            total += f.len();
            if f.is_empty() {
                std::thread::sleep(Duration::from_millis(1));
            } else {
                turns.push(f.len());
            }
        }
        turns
    }

    #[test]
    fn a_flooding_client_is_read_in_bounded_turns() {
        // Regression (issue 7 load test): a client writing faster than the
        // board handles frames held the loop in `read` until it ran dry.
        let (mut c, mut peer) = pair();
        let mut msg = b"O\r".to_vec();
        for _ in 0..5000 {
            msg.extend_from_slice(REQ);
        }
        let writer = std::thread::spawn(move || {
            peer.write_all(&msg).unwrap();
            peer
        });
        let turns = read_all(&mut c, 5000);
        let _peer = writer.join().unwrap();
        assert!(turns.iter().all(|&n| n <= MAX_READ / (REQ.len() - 1)));
        assert!(turns.len() >= 5000 * REQ.len() / MAX_READ, "{turns:?}");
    }

    #[test]
    fn replies_to_a_client_that_does_not_read_are_bounded() {
        // Regression: the "z" replies bypassed the backlog limit, so a
        // client that only writes grew the board's memory without bound.
        let (mut c, mut peer) = pair();
        c.out = vec![b'x'; MAX_BACKLOG];
        let mut msg = b"O\r".to_vec();
        for _ in 0..200 {
            msg.extend_from_slice(REQ);
        }
        msg.extend_from_slice(b"?\r"); // an error reply too
        peer.write_all(&msg).unwrap();
        let frames: usize = read_all(&mut c, 200).iter().sum();
        assert_eq!(frames, 200);
        std::thread::sleep(Duration::from_millis(20));
        c.read().unwrap();
        assert_eq!(c.out.len(), MAX_BACKLOG);
    }
}
