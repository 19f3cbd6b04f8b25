//! The world of the virtual board (`perpend board --world HOST:PORT`): a
//! line-based TCP control channel through which a simulated robot moves the
//! datum plane the board's head looks at. One client at a time; loopback
//! only (the board refuses another address).
//!
//! ```text
//! → plane A,B,C,D        the head looks at A·x + B·y + C·z + D = 0 (TCS) from
//!                        the next sample on
//! ← ok
//! ← error: <why>         a bad line; nothing changed
//! ```
//!
//! Limits: the plane jumps (no motion in between); the client should let
//! the board settle (its jump detector holds a sensor for 20 samples) before
//! it measures.

use std::io::{ErrorKind, Read, Write};
use std::net::{TcpListener, TcpStream};

use anyhow::{bail, Context as _, Result};

use super::node::VirtualBoard;
use crate::demo::parse_plane;

/// Longest accepted line [bytes].
const MAX_LINE: usize = 256;

/// The control channel: its listener and the client, if any.
pub struct World {
    listener: TcpListener,
    client: Option<(TcpStream, Vec<u8>)>,
}

impl World {
    /// Listens on `addr`, which must be a loopback address.
    ///
    /// # Errors
    /// A non-loopback address, one that cannot be bound.
    pub fn bind(addr: &str) -> Result<Self> {
        let listener =
            TcpListener::bind(addr).with_context(|| format!("--world {addr}: cannot listen"))?;
        let local = listener.local_addr()?;
        if !local.ip().is_loopback() {
            bail!("--world {addr}: the world channel is for loopback addresses only");
        }
        listener.set_nonblocking(true)?;
        Ok(Self {
            listener,
            client: None,
        })
    }

    /// The bound address.
    ///
    /// # Errors
    /// As [`TcpListener::local_addr`].
    pub fn local_addr(&self) -> Result<std::net::SocketAddr> {
        Ok(self.listener.local_addr()?)
    }

    /// Accepts a client, handles the lines it sent; `true` if anything was
    /// done.
    pub fn poll(&mut self, board: &mut VirtualBoard) -> bool {
        if self.client.is_none() {
            if let Ok((s, _)) = self.listener.accept() {
                if s.set_nonblocking(true).is_ok() {
                    self.client = Some((s, Vec::new()));
                }
            }
        }
        let Some((stream, buf)) = self.client.as_mut() else {
            return false;
        };
        let mut chunk = [0u8; 1024];
        let n = match stream.read(&mut chunk) {
            Ok(0) => {
                self.client = None;
                return false;
            }
            Ok(n) => n,
            Err(e) if e.kind() == ErrorKind::WouldBlock => return false,
            Err(_) => {
                self.client = None;
                return false;
            }
        };
        buf.extend_from_slice(&chunk[..n]);
        let mut replies = Vec::new();
        while let Some(end) = buf.iter().position(|&b| b == b'\n') {
            let line: Vec<u8> = buf.drain(..=end).collect();
            replies.extend_from_slice(handle(&String::from_utf8_lossy(&line), board).as_bytes());
        }
        if buf.len() > MAX_LINE {
            buf.clear();
            replies.extend_from_slice(b"error: line too long\n");
        }
        if stream.write_all(&replies).is_err() {
            self.client = None;
        }
        true
    }
}

/// Handles one line; returns the reply.
fn handle(line: &str, board: &mut VirtualBoard) -> String {
    let line = line.trim();
    match apply(line, board) {
        Ok(()) => "ok\n".into(),
        Err(e) => format!("error: {e:#}\n"),
    }
}

fn apply(line: &str, board: &mut VirtualBoard) -> Result<()> {
    let Some(rest) = line.strip_prefix("plane ") else {
        bail!("'{line}': expected `plane A,B,C,D`");
    };
    let plane = parse_plane(rest.trim())?;
    board.sim_mut().set_plane(plane);
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::board::node::BoardConfig;
    use crate::board::sim::SimHead;
    use perpend_core::geometry::Plane;
    use perpend_core::params::Params;

    #[test]
    fn lines_move_the_plane_or_are_refused() {
        let plane = Plane::from_abcd(0.0, 0.0, 1.0, -30.0).unwrap();
        let sim = SimHead::new(Params::factory().head.cast(), plane, 0.0, 1).unwrap();
        let cfg = BoardConfig {
            node_id: 0x20,
            head: None,
            calibration: None,
            thermal_tau_s: 0.0,
        };
        let mut b = VirtualBoard::new(&cfg, sim).unwrap();
        assert_eq!(handle("plane 0,0,1,-28\n", &mut b), "ok\n");
        assert!((b.sim_mut().plane().d + 28.0).abs() < 1e-12);
        assert!(handle("plane 0,0,0,1", &mut b).starts_with("error:"));
        assert!(handle("move 1", &mut b).starts_with("error:"));
        assert!((b.sim_mut().plane().d + 28.0).abs() < 1e-12);
        assert!(World::bind("0.0.0.0:0").is_err());
    }
}
