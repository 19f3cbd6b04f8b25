//! The world of the virtual board (`perpend board --world HOST:PORT`): a
//! line-based TCP control channel through which a simulated robot moves the
//! datum plane the board's head looks at. One client at a time; loopback
//! only (the board refuses another address).
//!
//! ```text
//! → plane A,B,C,D        the head looks at A·x + B·y + C·z + D = 0 (TCS) from
//!                        the next sample on
//! ← ok
//! → move A,B,C,D J       the robot presents the plane A,B,C,D (TCS, last
//!                        joint at 0) with its last joint turned by J degrees
//!                        about the spindle axis: the head sees the plane
//!                        turned by −J about TCS z
//! ← ok A',B',C',D'       the turned plane in the (taught) TCS, as the cell
//!                        computes it from its kinematics
//! → seen                 (simulation only) the plane the head really sees
//! ← ok A,B,C,D
//! ← error: <why>         a bad line; nothing changed
//! ```
//!
//! Frame errors (`perpend board --tracker-tilt-deg`, `--tcp-tilt-deg`,
//! `--tcp-offset-mm`, issue 36): the planes of both commands are what the
//! cell computes through its nominal frames; the head sees them through the
//! true ones ([`perpend_calib::frames::true_plane`]: the tracker tilt turns
//! against the head with the joint, the TCP error is fixed to the flange).
//!
//! Limits: the plane jumps (no motion in between); the client should let
//! the board settle (its jump detector holds a sensor for 20 samples) before
//! it measures.

use std::io::{ErrorKind, Read, Write};
use std::net::{TcpListener, TcpStream};

use anyhow::{anyhow, bail, Context as _, Result};
use perpend_calib::frames::{true_plane, FramePose, Frames};

use super::node::VirtualBoard;
use crate::demo::parse_plane;
use perpend_core::geometry::Plane;

/// Longest accepted line [bytes].
const MAX_LINE: usize = 256;

/// The control channel: its listener and the client, if any.
pub struct World {
    listener: TcpListener,
    client: Option<(TcpStream, Vec<u8>)>,
    frames: Frames,
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
            frames: Frames::zeros(),
        })
    }

    /// The cell's frame errors the head sees the planes through.
    pub fn with_frames(mut self, frames: Frames) -> Self {
        self.frames = frames;
        self
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
            let line = String::from_utf8_lossy(&line);
            replies.extend_from_slice(handle(&line, board, &self.frames).as_bytes());
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
fn handle(line: &str, board: &mut VirtualBoard, frames: &Frames) -> String {
    let line = line.trim();
    match apply(line, board, frames) {
        Ok(None) => "ok\n".into(),
        Ok(Some(p)) => format!("ok {},{},{},{}\n", p.n.x, p.n.y, p.n.z, p.d),
        Err(e) => format!("error: {e:#}\n"),
    }
}

/// Applies one line; `Some(plane)` for a `move` (the turned plane).
fn apply(line: &str, board: &mut VirtualBoard, frames: &Frames) -> Result<Option<Plane<f64>>> {
    if line == "seen" {
        return Ok(Some(*board.sim_mut().plane()));
    }
    if let Some(rest) = line.strip_prefix("plane ") {
        let plane = parse_plane(rest.trim())?;
        board
            .sim_mut()
            .set_plane(true_plane(&FramePose::turned(&plane, 0.0), frames));
        return Ok(None);
    }
    let Some(rest) = line.strip_prefix("move ") else {
        bail!("'{line}': expected `plane A,B,C,D`, `move A,B,C,D JOINT_DEG` or `seen`");
    };
    let (abcd, joint) = rest
        .trim()
        .rsplit_once(char::is_whitespace)
        .ok_or_else(|| anyhow!("'{line}': expected `move A,B,C,D JOINT_DEG`"))?;
    let joint: f64 = joint
        .trim()
        .parse()
        .ok()
        .filter(|j: &f64| j.is_finite())
        .ok_or_else(|| anyhow!("'{joint}': the joint angle must be a number of degrees"))?;
    let pose = FramePose::turned(&parse_plane(abcd.trim())?, joint.to_radians());
    board.sim_mut().set_plane(true_plane(&pose, frames));
    Ok(Some(pose.plane))
}

/// A pair `X,Y` (or `X`: `X,0`) of an option such as `--tracker-tilt-deg`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Pair(pub [f64; 2]);

/// Parses a [`Pair`].
///
/// # Errors
/// Not one or two finite numbers.
pub fn parse_pair(s: &str) -> Result<Pair> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>().ok().filter(|x| x.is_finite()))
        .collect::<Option<_>>()
        .ok_or_else(|| anyhow!("'{s}': expected X,Y (two numbers, e.g. 0.05,0)"))?;
    match v.as_slice() {
        [x] => Ok(Pair([*x, 0.0])),
        [x, y] => Ok(Pair([*x, *y])),
        _ => bail!("'{s}': expected X,Y (two numbers, e.g. 0.05,0)"),
    }
}

/// The frame errors of `perpend board`'s options, checked to be small
/// (the model is first order in them).
///
/// # Errors
/// A tilt above 1° or an offset above 5 mm.
pub fn frames_of(tracker_deg: Pair, tcp_deg: Pair, offset_mm: Pair) -> Result<Frames> {
    for (name, p, max) in [
        ("--tracker-tilt-deg", tracker_deg, 1.0),
        ("--tcp-tilt-deg", tcp_deg, 1.0),
        ("--tcp-offset-mm", offset_mm, 5.0),
    ] {
        if p.0.iter().any(|x| x.abs() > max) {
            bail!(
                "{name} {},{}: frame errors are modelled up to {max} (a larger one is a wrong setup, not a calibration error)",
                p.0[0],
                p.0[1]
            );
        }
    }
    Ok(perpend_calib::frames::frames_deg(
        tracker_deg.0,
        tcp_deg.0,
        offset_mm.0,
    ))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::board::node::BoardConfig;
    use crate::board::sim::SimHead;
    use perpend_core::geometry::Plane;
    use perpend_core::params::Params;

    /// A factory board looking at z = 30.
    fn board() -> VirtualBoard {
        let plane = Plane::from_abcd(0.0, 0.0, 1.0, -30.0).unwrap();
        let sim = SimHead::new(Params::factory().head.cast(), plane, 0.0, 1).unwrap();
        let cfg = BoardConfig {
            node_id: 0x20,
            head: None,
            calibration: None,
            thermal_tau_s: 0.0,
        };
        VirtualBoard::new(&cfg, sim).unwrap()
    }

    #[test]
    fn lines_move_the_plane_or_are_refused() {
        let mut b = board();
        let none = Frames::zeros();
        assert_eq!(handle("plane 0,0,1,-28\n", &mut b, &none), "ok\n");
        assert!((b.sim_mut().plane().d + 28.0).abs() < 1e-12);
        assert!(handle("plane 0,0,0,1", &mut b, &none).starts_with("error:"));
        assert!(handle("move 1", &mut b, &none).starts_with("error:"));
        assert!(handle("move 0,0,1,-28 x", &mut b, &none).starts_with("error:"));
        assert!(handle("turn 0,0,1,-28", &mut b, &none).starts_with("error:"));
        assert!((b.sim_mut().plane().d + 28.0).abs() < 1e-12);
        assert!(World::bind("0.0.0.0:0").is_err());
    }

    #[test]
    fn move_turns_the_head_and_the_frames_tilt_what_it_sees() {
        let mut b = board();
        let none = Frames::zeros();
        // a plane tilted about TCS x, head turned by 180°: tilted the other way
        let r = handle("move 0,-0.1,-1,30 180", &mut b, &none);
        assert!(r.starts_with("ok "), "{r}");
        let seen = *b.sim_mut().plane();
        let n = if seen.n.z < 0.0 { seen.n } else { -seen.n };
        assert!((n.y - 0.1 / 1.01f64.sqrt()).abs() < 1e-9, "{seen:?}");
        // a tracker tilted 0.05° about x: the level plate looks tilted by it
        let tilt = frames_of(
            parse_pair("0.05").unwrap(),
            Pair::default(),
            Pair::default(),
        )
        .unwrap();
        assert_eq!(handle("plane 0,0,-1,30", &mut b, &tilt), "ok\n");
        let seen = b.sim_mut().plane().n;
        let deg = seen.x.hypot(seen.y).atan2(seen.z.abs()).to_degrees();
        assert!((deg - 0.05).abs() < 1e-9, "{deg}");
        assert!(handle("seen", &mut b, &tilt).starts_with("ok "));
        assert!(parse_pair("1,2,3").is_err() && parse_pair("a").is_err());
        assert!(frames_of(Pair([2.0, 0.0]), Pair::default(), Pair::default()).is_err());
    }
}
