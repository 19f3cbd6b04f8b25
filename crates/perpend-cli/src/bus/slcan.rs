//! slcan (LAWICEL) on the host side: the client of an slcan adapter, over
//! any byte link with a read timeout ([`Link`]): a TCP connection to the
//! virtual board ([`TcpLink`]) or a serial port ([`super::serial`]).
//!
//! Opening sends `CR CR CR` (flushes a half-typed command), `C` (closes a
//! channel left open), `Sn` (bit rate) and `O` (open); the adapter answers
//! CR to each accepted command and BEL to a refused one. A refused `S` or
//! `O`, or no answer within a second, is an error that says so. Received
//! frames come as `tIIIL…` / `rIIIL` lines, with or without the 4-digit
//! timestamp some adapters append; `z`/`Z` transmit confirmations and
//! extended frames are skipped. Frames are sent as `tIIIL…` lines without
//! waiting for the confirmation.

use std::collections::VecDeque;
use std::io::{ErrorKind, Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

use perpend_can::Frame;

use super::{Bus, BusError};
use crate::slcan::{self as proto, Command, LineSplitter, BUSY_PREFIX};

/// How long the adapter has to answer each set-up command.
const SETUP_TIMEOUT: Duration = Duration::from_secs(1);

/// A byte link to an slcan adapter.
pub trait Link: Send {
    /// Writes all of `b`.
    ///
    /// # Errors
    /// The system's error.
    fn write_all(&mut self, b: &[u8]) -> std::io::Result<()>;

    /// Reads what is available into `buf`, waiting at most `timeout`:
    /// `Ok(None)` when nothing came, `Ok(Some(0))` when the link closed.
    ///
    /// # Errors
    /// The system's error.
    fn read_timeout(&mut self, buf: &mut [u8], timeout: Duration)
        -> std::io::Result<Option<usize>>;
}

/// slcan over TCP (the virtual board).
#[derive(Debug)]
pub struct TcpLink(TcpStream);

impl TcpLink {
    /// Connects to `addr` (`HOST:PORT`) within two seconds; `name` labels
    /// errors.
    ///
    /// # Errors
    /// [`BusError::Open`] with a hint.
    pub fn connect(addr: &str, name: &str) -> Result<Self, BusError> {
        let open_err = |source: std::io::Error| BusError::Open {
            bus: name.to_string(),
            hint: "is `perpend board --slcan HOST:PORT` running there?".into(),
            source,
        };
        let mut last = std::io::Error::new(ErrorKind::NotFound, "the address resolves to nothing");
        for sa in addr.to_socket_addrs().map_err(open_err)? {
            match TcpStream::connect_timeout(&sa, Duration::from_secs(2)) {
                Ok(s) => {
                    s.set_nodelay(true).map_err(open_err)?;
                    return Ok(Self(s));
                }
                Err(e) => last = e,
            }
        }
        Err(open_err(last))
    }
}

impl Link for TcpLink {
    fn write_all(&mut self, b: &[u8]) -> std::io::Result<()> {
        self.0.write_all(b)
    }

    fn read_timeout(
        &mut self,
        buf: &mut [u8],
        timeout: Duration,
    ) -> std::io::Result<Option<usize>> {
        self.0
            .set_read_timeout(Some(timeout.max(Duration::from_micros(100))))?;
        match self.0.read(buf) {
            Ok(n) => Ok(Some(n)),
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => Ok(None),
            Err(e) if e.kind() == ErrorKind::Interrupted => Ok(None),
            Err(e) => Err(e),
        }
    }
}

/// What one received line was.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Line {
    /// A received standard frame.
    Frame(Frame),
    /// A command accepted (empty line: a bare CR).
    Ok,
    /// Anything else (transmit confirmations, extended frames, replies).
    Other,
}

/// Parses one line the adapter sent (without its CR).
pub fn parse_line(line: &[u8]) -> Line {
    if line.is_empty() {
        return Line::Ok;
    }
    match proto::parse(line) {
        Ok(Command::Transmit(f)) => Line::Frame(f),
        // A frame with a 4-digit timestamp after its data.
        Err(_) if matches!(line[0], b't' | b'r') && line.len() > 4 => {
            match proto::parse(&line[..line.len() - 4]) {
                Ok(Command::Transmit(f)) => Line::Frame(f),
                _ => Line::Other,
            }
        }
        _ => Line::Other,
    }
}

/// A CAN bus through an slcan adapter.
pub struct SlcanBus<L: Link> {
    link: L,
    name: String,
    lines: LineSplitter,
    frames: VecDeque<Frame>,
    /// Command replies seen: (accepted, refused).
    replies: (usize, usize),
    /// A line of text the other end sent instead of slcan (the virtual
    /// board's "in use by another client"), kept for the error message.
    said: Option<String>,
}

/// The `Sn` code of a bit rate [kbit/s].
///
/// # Errors
/// [`BusError::Adapter`] for a rate slcan has no code for.
fn bitrate_code(kbps: u32, bus: &str) -> Result<u8, BusError> {
    const RATES: [u32; 9] = [10, 20, 50, 100, 125, 250, 500, 800, 1000];
    RATES
        .iter()
        .position(|&r| r == kbps)
        .map(|i| i as u8)
        .ok_or_else(|| BusError::Adapter {
            bus: bus.to_string(),
            what: format!(
                "--bitrate {kbps}: slcan adapters know 10, 20, 50, 100, 125, 250, 500, 800 \
                 and 1000 kbit/s"
            ),
        })
}

impl<L: Link> SlcanBus<L> {
    /// Sets the adapter up (close, bit rate, open) and returns the bus.
    ///
    /// # Errors
    /// [`BusError::Adapter`] when the adapter refuses or does not answer.
    pub fn open(link: L, name: String, bitrate_kbps: u32) -> Result<Self, BusError> {
        let code = bitrate_code(bitrate_kbps, &name)?;
        let mut bus = Self {
            link,
            name,
            lines: LineSplitter::new(),
            frames: VecDeque::new(),
            replies: (0, 0),
            said: None,
        };
        bus.write(b"\r\r\r")?;
        // Whatever the flush provokes (CR or BEL per adapter) is not an
        // answer to the commands below.
        let end = Instant::now() + Duration::from_millis(50);
        while let Some(left) = end.checked_duration_since(Instant::now()) {
            bus.fill(left)?;
        }
        bus.setup(code, bitrate_kbps).map_err(|e| bus.explain(e))?;
        bus.frames.clear();
        Ok(bus)
    }

    /// The set-up commands: close, bit rate, open.
    fn setup(&mut self, code: u8, bitrate_kbps: u32) -> Result<(), BusError> {
        self.command(b"C\r", "close the channel", false)?;
        let s = format!("S{code}\r");
        self.command(s.as_bytes(), &format!("set {bitrate_kbps} kbit/s"), true)?;
        self.command(b"O\r", "open the channel", true)
    }

    /// A set-up failure said as what was found: an endpoint that told us
    /// it is in use, or one that closed the connection or kept silent
    /// although it accepted it (a TCP port held by another client).
    fn explain(&self, e: BusError) -> BusError {
        let tcp = self.name.starts_with("tcp:");
        let what = match (&self.said, &e) {
            (Some(line), _) if line.starts_with(BUSY_PREFIX) => format!(
                "the port answers but is in use by another client ({}): close that \
                 `perpend node`/python session first; the virtual board serves one client",
                line[BUSY_PREFIX.len()..].trim()
            ),
            (Some(line), _) => format!("the port answers but not in slcan: it said {line:?}"),
            (None, BusError::Closed { .. }) => "the port answers but closed the connection \
                 during set-up: is it in use by another client?"
                .into(),
            (None, BusError::Adapter { what, .. }) if tcp && what.contains("did not answer") => {
                "the port answers (the connection was accepted) but nothing answered the \
                 slcan set-up: it is in use by another client, or not an slcan endpoint"
                    .into()
            }
            _ => return e,
        };
        BusError::Adapter {
            bus: self.name.clone(),
            what,
        }
    }

    fn write(&mut self, b: &[u8]) -> Result<(), BusError> {
        self.link.write_all(b).map_err(|source| BusError::Io {
            bus: self.name.clone(),
            source,
        })
    }

    /// Sends a set-up command and waits for its CR (or BEL). A refusal is
    /// an error when `must` (a `C` on a closed channel may be refused).
    fn command(&mut self, cmd: &[u8], what: &str, must: bool) -> Result<(), BusError> {
        // Replies to the flush CRs may still be on their way: count from now.
        self.replies = (0, 0);
        self.write(cmd)?;
        let end = Instant::now() + SETUP_TIMEOUT;
        while self.replies == (0, 0) {
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(BusError::Adapter {
                    bus: self.name.clone(),
                    what: format!(
                        "the adapter did not answer the command to {what}: is it an slcan \
                         (LAWICEL) adapter, and is the port right?"
                    ),
                });
            }
            self.fill(left)?;
        }
        if self.replies.1 > 0 && self.replies.0 == 0 && must {
            return Err(BusError::Adapter {
                bus: self.name.clone(),
                what: format!("the adapter refused the command to {what}"),
            });
        }
        Ok(())
    }

    /// Reads once (waiting at most `timeout`) and parses what came.
    fn fill(&mut self, timeout: Duration) -> Result<(), BusError> {
        let mut buf = [0u8; 1024];
        let n = match self.link.read_timeout(&mut buf, timeout) {
            Ok(None) => return Ok(()),
            Ok(Some(0)) => {
                return Err(BusError::Closed {
                    bus: self.name.clone(),
                })
            }
            Ok(Some(n)) => n,
            Err(source) => {
                return Err(BusError::Io {
                    bus: self.name.clone(),
                    source,
                })
            }
        };
        // BEL (refused) is not followed by CR: take it out of the stream.
        let bells = buf[..n].iter().filter(|&&b| b == 0x07).count();
        self.replies.1 += bells;
        let bytes: Vec<u8> = buf[..n].iter().copied().filter(|&b| b != 0x07).collect();
        let (frames, replies, said) = (&mut self.frames, &mut self.replies, &mut self.said);
        self.lines
            .feed(&bytes, |line| match line.map(|l| (l, parse_line(l))) {
                Ok((_, Line::Frame(f))) => frames.push_back(f),
                Ok((_, Line::Ok)) => replies.0 += 1,
                Ok((l, Line::Other))
                    if l.len() > 8 && l.iter().all(|b| (0x20..0x7F).contains(b)) =>
                {
                    *said = Some(String::from_utf8_lossy(l).into_owned());
                }
                _ => {}
            });
        Ok(())
    }
}

impl<L: Link> Bus for SlcanBus<L> {
    fn send(&mut self, f: &Frame) -> Result<(), BusError> {
        let mut line = Vec::with_capacity(32);
        proto::format_frame(f, &mut line);
        self.write(&line)
    }

    fn recv(&mut self, timeout: Duration) -> Result<Option<Frame>, BusError> {
        let end = Instant::now() + timeout;
        loop {
            if let Some(f) = self.frames.pop_front() {
                return Ok(Some(f));
            }
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            self.fill(left)?;
        }
    }

    fn name(&self) -> &str {
        &self.name
    }
}

impl<L: Link> Drop for SlcanBus<L> {
    /// Closes the adapter's channel (best effort): a real adapter left
    /// open keeps acknowledging frames on the bus for nobody.
    fn drop(&mut self) {
        let _ = self.link.write_all(b"C\r");
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A scripted adapter: answers each command line with `answer(line)`.
    struct Script {
        input: VecDeque<u8>,
        sent: Vec<u8>,
        answer: fn(&[u8]) -> &'static [u8],
    }

    impl Link for Script {
        fn write_all(&mut self, b: &[u8]) -> std::io::Result<()> {
            self.sent.extend_from_slice(b);
            for line in b.split(|&c| c == b'\r') {
                if !line.is_empty() {
                    self.input.extend((self.answer)(line));
                }
            }
            Ok(())
        }
        fn read_timeout(&mut self, buf: &mut [u8], _: Duration) -> std::io::Result<Option<usize>> {
            if self.input.is_empty() {
                return Ok(None);
            }
            let n = buf.len().min(self.input.len());
            for b in buf.iter_mut().take(n) {
                *b = self.input.pop_front().unwrap();
            }
            Ok(Some(n))
        }
    }

    fn script(answer: fn(&[u8]) -> &'static [u8]) -> Script {
        Script {
            input: VecDeque::new(),
            sent: Vec::new(),
            answer,
        }
    }

    #[test]
    fn opens_sends_and_receives() {
        let mut s = script(|l| match l {
            b"O" => b"\rt7101AB\rt12340000\rz\r",
            _ => b"\r",
        });
        s.input.extend(b"\r\r\r"); // answers to the flush
        let mut bus = SlcanBus::open(s, "test".into(), 500).unwrap();
        assert!(bus.link.sent.starts_with(b"\r\r\rC\rS6\rO\r"));
        bus.send(&Frame::new(0x601, &[0x40, 0x18, 0x10, 1, 0, 0, 0, 0]))
            .unwrap();
        assert!(bus.link.sent.ends_with(b"t60184018100100000000\r"));
        // The frames that came after `O` are delivered; the timestamped one too.
        bus.frames.clear();
        bus.link.input.extend(b"t7101AB\rt0800ABCD\rT123456780\r");
        let f = bus.recv(Duration::from_millis(10)).unwrap().unwrap();
        assert_eq!(f, Frame::new(0x710, &[0xAB]));
        let f = bus.recv(Duration::from_millis(10)).unwrap().unwrap();
        assert_eq!(f, Frame::new(0x080, &[]));
        assert_eq!(bus.recv(Duration::from_millis(1)).unwrap(), None);
    }

    #[test]
    fn a_refused_bitrate_is_an_error_in_words() {
        let s = script(|l| if l.starts_with(b"S") { b"\x07" } else { b"\r" });
        let e = SlcanBus::open(s, "slcan:/dev/x".into(), 1000)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("refused the command to set 1000 kbit/s"), "{e}");
        let s = script(|_| b"");
        let e = SlcanBus::open(s, "slcan:/dev/x".into(), 1000)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("did not answer"), "{e}");
        let s = script(|_| b"\r");
        let e = SlcanBus::open(s, "x".into(), 333)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("--bitrate 333"), "{e}");
    }
}
