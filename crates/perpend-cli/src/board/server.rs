//! The slcan-over-TCP server of the virtual board: one client at a time
//! (others wait in the listen queue until it disconnects), real-time
//! clock, one sample per acquisition period.
//!
//! Each loop turn: accept or read the client, parse its slcan lines
//! ([`crate::slcan`]), hand transmitted frames to the board, run the
//! samples that are due, poll the board, and send what it produced while
//! the channel is open (`O`). The board keeps running without a client
//! (frames are then dropped, as on a bus with nobody listening).
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
use crate::slcan::{self, Command, LineSplitter};

/// Largest amount of unsent output kept for a slow client [bytes]; beyond
/// it frames are dropped (a bus does not wait either).
const MAX_BACKLOG: usize = 1 << 20;
/// Most samples run in one loop turn before skipping ahead.
const MAX_CATCH_UP: u32 = 50;

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

    /// Reads what is available; returns the frames to transmit, or `None`
    /// when the client has gone.
    fn read(&mut self) -> Option<Vec<Frame>> {
        let mut frames = Vec::new();
        let mut buf = [0u8; 4096];
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
                                out.extend_from_slice(slcan::reply(&cmd));
                            }
                            Err(_) => out.extend_from_slice(slcan::ERROR),
                        });
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

/// Serves the board on `listener` until the process is stopped.
///
/// # Errors
/// Only if the listener cannot be made non-blocking.
pub fn serve(listener: TcpListener, board: &mut VirtualBoard) -> Result<()> {
    listener
        .set_nonblocking(true)
        .context("making the listener non-blocking")?;
    let start = Instant::now();
    let mut client: Option<Client> = None;
    let mut next_sample = 0u64;
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
        let mut busy = false;
        if let Some(c) = client.as_mut() {
            match c.read() {
                Some(frames) => {
                    for f in &frames {
                        busy = true;
                        board.handle(f, now, &mut |o| produced.push(o));
                    }
                }
                None => {
                    eprintln!("perpend board: client disconnected");
                    client = None;
                }
            }
        }
        let period = board.period_us();
        let mut k = 0;
        while next_sample <= now && k < MAX_CATCH_UP {
            board.sample(next_sample);
            next_sample += period;
            k += 1;
        }
        if next_sample <= now {
            next_sample = now + period;
        }
        board.poll(now, &mut |o| produced.push(o));
        if let Some(c) = client.as_mut() {
            if c.open {
                for f in &produced {
                    if c.out.len() < MAX_BACKLOG {
                        slcan::format_frame(f, &mut c.out);
                    }
                }
            }
            busy |= !c.out.is_empty();
            if !c.flush() {
                eprintln!("perpend board: client disconnected");
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
