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
use crate::slcan::{self, Command, LineSplitter};

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
    lines: LineSplitter,
    open: bool,
    listen_only: bool,
    out: Vec<u8>,
}

impl Client {
    fn new(stream: TcpStream) -> std::io::Result<Self> {
        stream.set_nonblocking(true)?;
        stream.set_nodelay(true)?;
        Ok(Self {
            stream,
            lines: LineSplitter::new(),
            open: false,
            listen_only: false,
            out: Vec::new(),
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
                    let (open, listen_only, out) =
                        (&mut self.open, &mut self.listen_only, &mut self.out);
                    self.lines
                        .feed(&buf[..n], |line| match line.and_then(slcan::parse) {
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
                            Err(_) if out.len() < MAX_BACKLOG => {
                                out.extend_from_slice(slcan::ERROR)
                            }
                            Err(_) => {}
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

/// Serves the board on `listener` until the process is stopped; `world`,
/// if any, moves its plane ([`super::world`]).
///
/// # Errors
/// Only if the listener cannot be made non-blocking.
pub fn serve(
    listener: TcpListener,
    mut world: Option<World>,
    board: &mut VirtualBoard,
) -> Result<()> {
    listener
        .set_nonblocking(true)
        .context("making the listener non-blocking")?;
    let start = Instant::now();
    let mut client: Option<Client> = None;
    let mut next_sample = 0u64;
    let mut last_sample = 0u64;
    let mut latency = Latency::default();
    let mut produced: Vec<Frame> = Vec::new();
    loop {
        let now = start.elapsed().as_micros() as u64;
        if client.is_none() {
            match listener.accept() {
                Ok((s, peer)) => match Client::new(s) {
                    Ok(c) => {
                        eprintln!("perpend board: client {peer} connected");
                        client = Some(c);
                    }
                    Err(e) => eprintln!("perpend board: client {peer}: {e}"),
                },
                Err(e) if e.kind() == ErrorKind::WouldBlock => {}
                Err(e) => eprintln!("perpend board: accept: {e}"),
            }
        }
        let mut busy = world.as_mut().is_some_and(|w| w.poll(board));
        if let Some(c) = client.as_mut() {
            match c.read() {
                Some(frames) => {
                    for f in &frames {
                        busy = true;
                        board.handle(f, now, &mut |o| produced.push(o));
                        // SYNC-locked acquisition (0x2301): the scan of
                        // this SYNC, now.
                        if board.app_mut().take_sync_scan() {
                            board.sample(now);
                            last_sample = now;
                        }
                    }
                }
                None => {
                    eprintln!("perpend board: client disconnected");
                    latency.report();
                    client = None;
                }
            }
        }
        let period = board.period_us();
        let mut k = 0;
        if board.app().sync_locked() {
            next_sample = now + period;
        }
        while next_sample <= now && k < MAX_CATCH_UP {
            board.sample(next_sample);
            last_sample = next_sample;
            next_sample += period;
            k += 1;
        }
        if next_sample <= now {
            next_sample = now + period;
        }
        board.poll(now, &mut |o| produced.push(o));
        if let Some(c) = client.as_mut() {
            let mut tpdo1 = 0usize;
            if c.open {
                for f in &produced {
                    if c.out.len() < MAX_BACKLOG {
                        slcan::format_frame(f, &mut c.out);
                        tpdo1 += usize::from(f.id & 0x780 == 0x180 && f.id != 0x180);
                    }
                }
            }
            busy |= !c.out.is_empty();
            let ok = c.flush();
            let sent = start.elapsed().as_micros() as u64;
            for _ in 0..tpdo1 {
                latency.note(sent.saturating_sub(last_sample));
            }
            if !ok {
                eprintln!("perpend board: client disconnected");
                latency.report();
                client = None;
            }
        }
        produced.clear();
        if !busy {
            let until_sample = next_sample.saturating_sub(start.elapsed().as_micros() as u64);
            std::thread::sleep(Duration::from_micros(until_sample.clamp(20, 200)));
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

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
