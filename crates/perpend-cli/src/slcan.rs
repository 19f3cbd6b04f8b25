//! LAWICEL / slcan ASCII protocol, adapter side: what the virtual board
//! speaks over TCP so that python-can's `slcan` interface (channel
//! `socket://127.0.0.1:PORT`) and any slcan tool can talk to it.
//!
//! Commands (each terminated by CR; LF is tolerated and ignored):
//!
//! ```text
//! O / L / C           open / open listen-only / close the channel   -> CR
//! Sn, sXXYY           bit rate (accepted, the virtual bus has none)  -> CR
//! tIIILDD..           transmit 11-bit data frame                     -> z CR
//! rIIIL               transmit 11-bit remote frame                   -> z CR
//! TIIIIIIIILDD.. / R… 29-bit frames (parsed; CANopen does not use them) -> Z CR
//! V, v, N, F, Zn, Mx, mx, Y…   version, serial, flags, timestamps, filters -> reply
//! anything else       BEL (0x07)
//! ```
//!
//! The adapter sends received frames as `tIIILDD..CR` / `rIIILCR` (no
//! timestamps). [`parse`] is a pure function over one line (the fuzz target
//! of the slcan parser); [`LineSplitter`] cuts a byte stream into lines with
//! a bounded buffer.
//!
//! Limits: CAN FD frames (`d`, `D`, `b`, `B`) are refused with BEL.

use perpend_can::Frame;

/// Longest line accepted \[bytes\] (an extended frame with 8 data bytes is
/// 1 + 8 + 1 + 16 = 26); longer lines are discarded as a whole.
pub const MAX_LINE: usize = 64;

/// The line the virtual board sends a second client before it closes that
/// connection, followed by the address of the client that holds the board
/// (short enough for [`MAX_LINE`] with an IPv4 address and port).
pub const BUSY_PREFIX: &str = "perpend board: in use by";

/// One parsed command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// `O`: open the channel (normal mode).
    Open,
    /// `L`: open listen-only.
    ListenOnly,
    /// `C`: close the channel.
    Close,
    /// `Sn` (0..=8 standard rates) or `sXXYY` (BTR registers): accepted and
    /// ignored.
    Bitrate,
    /// `t…`/`r…`: a standard frame to transmit.
    Transmit(Frame),
    /// `T…`/`R…`: an extended-id frame (id, remote, len, data); CANopen
    /// CiA 301 does not use them, the board drops them.
    TransmitExtended {
        /// 29-bit identifier.
        id: u32,
        /// Remote frame.
        rtr: bool,
        /// Data length.
        len: u8,
        /// Payload.
        data: [u8; 8],
    },
    /// `V`: hardware/firmware version.
    Version,
    /// `N`: serial number.
    Serial,
    /// `F`: status flags.
    Flags,
    /// `Zn`, `Mxxxxxxxx`, `mxxxxxxxx`, `Yn`, `Q…`: timestamp / filter /
    /// FD / auto-start settings, accepted and ignored.
    Setting,
}

/// Why a line was refused (answered with BEL).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SlcanError {
    /// Empty line.
    Empty,
    /// Unknown command letter.
    Unknown(u8),
    /// A hex digit was expected.
    BadHex,
    /// Wrong number of characters for the command.
    BadLength,
    /// Data length code above 8 or identifier out of range.
    OutOfRange,
    /// CAN FD frames are not supported.
    Fd,
}

impl core::fmt::Display for SlcanError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            SlcanError::Empty => write!(f, "empty command"),
            SlcanError::Unknown(c) => write!(f, "unknown command {:?}", *c as char),
            SlcanError::BadHex => write!(f, "hex digit expected"),
            SlcanError::BadLength => write!(f, "wrong command length"),
            SlcanError::OutOfRange => write!(f, "identifier or length out of range"),
            SlcanError::Fd => write!(f, "CAN FD frames are not supported"),
        }
    }
}

impl std::error::Error for SlcanError {}

fn hex(c: u8) -> Result<u8, SlcanError> {
    match c {
        b'0'..=b'9' => Ok(c - b'0'),
        b'a'..=b'f' => Ok(c - b'a' + 10),
        b'A'..=b'F' => Ok(c - b'A' + 10),
        _ => Err(SlcanError::BadHex),
    }
}

fn hex_num(s: &[u8]) -> Result<u32, SlcanError> {
    s.iter()
        .try_fold(0u32, |a, &c| Ok((a << 4) | hex(c)? as u32))
}

/// Parses the frame part after the command letter: `id` of `id_digits`
/// hex digits, one DLC digit, then `2·len` data digits unless `rtr`.
fn frame_parts(body: &[u8], id_digits: usize, rtr: bool) -> Result<(u32, u8, [u8; 8]), SlcanError> {
    if body.len() < id_digits + 1 {
        return Err(SlcanError::BadLength);
    }
    let id = hex_num(&body[..id_digits])?;
    let len = hex(body[id_digits])?;
    if len > 8 {
        return Err(SlcanError::OutOfRange);
    }
    let rest = &body[id_digits + 1..];
    let mut data = [0u8; 8];
    if rtr {
        if !rest.is_empty() {
            return Err(SlcanError::BadLength);
        }
    } else {
        if rest.len() != 2 * len as usize {
            return Err(SlcanError::BadLength);
        }
        for (k, d) in data.iter_mut().take(len as usize).enumerate() {
            *d = (hex(rest[2 * k])? << 4) | hex(rest[2 * k + 1])?;
        }
    }
    Ok((id, len, data))
}

/// Parses one command line (without its CR).
///
/// # Errors
/// [`SlcanError`] for anything that is not a valid command.
pub fn parse(line: &[u8]) -> Result<Command, SlcanError> {
    let (&c, body) = line.split_first().ok_or(SlcanError::Empty)?;
    let only = |cmd: Command| {
        if body.is_empty() {
            Ok(cmd)
        } else {
            Err(SlcanError::BadLength)
        }
    };
    match c {
        b'O' => only(Command::Open),
        b'L' => only(Command::ListenOnly),
        b'C' => only(Command::Close),
        b'V' | b'v' => only(Command::Version),
        b'N' => only(Command::Serial),
        b'F' => only(Command::Flags),
        b'S' => match body {
            [d] if hex(*d)? <= 8 => Ok(Command::Bitrate),
            [_] => Err(SlcanError::OutOfRange),
            _ => Err(SlcanError::BadLength),
        },
        b's' => {
            if body.len() != 4 {
                return Err(SlcanError::BadLength);
            }
            hex_num(body)?;
            Ok(Command::Bitrate)
        }
        b'Z' | b'Y' | b'Q' => {
            if body.len() != 1 {
                return Err(SlcanError::BadLength);
            }
            hex(body[0])?;
            Ok(Command::Setting)
        }
        b'M' | b'm' => {
            if body.len() != 8 {
                return Err(SlcanError::BadLength);
            }
            hex_num(body)?;
            Ok(Command::Setting)
        }
        b't' | b'r' => {
            let rtr = c == b'r';
            let (id, len, data) = frame_parts(body, 3, rtr)?;
            if id > 0x7FF {
                return Err(SlcanError::OutOfRange);
            }
            Ok(Command::Transmit(Frame {
                id: id as u16,
                rtr,
                len,
                data,
            }))
        }
        b'T' | b'R' => {
            let rtr = c == b'R';
            let (id, len, data) = frame_parts(body, 8, rtr)?;
            if id > 0x1FFF_FFFF {
                return Err(SlcanError::OutOfRange);
            }
            Ok(Command::TransmitExtended { id, rtr, len, data })
        }
        b'd' | b'D' | b'b' | b'B' => Err(SlcanError::Fd),
        other => Err(SlcanError::Unknown(other)),
    }
}

/// The reply to a successfully parsed command (bytes to send back).
pub fn reply(cmd: &Command) -> &'static [u8] {
    match cmd {
        Command::Transmit(_) => b"z\r",
        Command::TransmitExtended { .. } => b"Z\r",
        Command::Version => b"V1013\r",
        Command::Serial => b"NPPND\r",
        Command::Flags => b"F00\r",
        _ => b"\r",
    }
}

/// The error reply (BEL).
pub const ERROR: &[u8] = b"\x07";

/// Appends the slcan line of a received standard frame to `out`:
/// `tIIILDD..\r` or `rIIIL\r`. Frames with an invalid id or length are
/// clamped (id & 0x7FF, len ≤ 8).
pub fn format_frame(f: &Frame, out: &mut Vec<u8>) {
    const H: &[u8; 16] = b"0123456789ABCDEF";
    let id = f.id & 0x7FF;
    let len = f.len.min(8);
    out.push(if f.rtr { b'r' } else { b't' });
    out.push(H[(id >> 8) as usize & 0xF]);
    out.push(H[(id >> 4) as usize & 0xF]);
    out.push(H[id as usize & 0xF]);
    out.push(H[len as usize]);
    if !f.rtr {
        for &b in &f.data[..len as usize] {
            out.push(H[(b >> 4) as usize]);
            out.push(H[(b & 0xF) as usize]);
        }
    }
    out.push(b'\r');
}

/// Cuts a byte stream into CR-terminated lines (LF ignored), with a
/// bounded buffer: a line longer than [`MAX_LINE`] is dropped whole and
/// reported as `Err(BadLength)` when its CR arrives.
#[derive(Debug, Default)]
pub struct LineSplitter {
    buf: Vec<u8>,
    overflow: bool,
}

impl LineSplitter {
    /// An empty splitter.
    pub fn new() -> Self {
        Self::default()
    }

    /// Feeds bytes; calls `line` for every complete line (without CR).
    pub fn feed(&mut self, bytes: &[u8], mut line: impl FnMut(Result<&[u8], SlcanError>)) {
        for &b in bytes {
            match b {
                b'\r' => {
                    if self.overflow {
                        line(Err(SlcanError::BadLength));
                    } else {
                        line(Ok(&self.buf));
                    }
                    self.buf.clear();
                    self.overflow = false;
                }
                b'\n' => {}
                _ => {
                    if self.buf.len() < MAX_LINE {
                        self.buf.push(b);
                    } else {
                        self.overflow = true;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn parses_the_python_can_session() {
        assert_eq!(parse(b"C"), Ok(Command::Close));
        assert_eq!(parse(b"S6"), Ok(Command::Bitrate));
        assert_eq!(parse(b"O"), Ok(Command::Open));
        assert_eq!(
            parse(b"t61084000100100000000"),
            Ok(Command::Transmit(Frame::new(
                0x610,
                &[0x40, 0x00, 0x10, 0x01, 0, 0, 0, 0]
            )))
        );
        assert_eq!(
            parse(b"t0002010A"),
            Ok(Command::Transmit(Frame::new(0, &[0x01, 0x0A])))
        );
        assert_eq!(
            parse(b"t0800"),
            Ok(Command::Transmit(Frame::new(0x80, &[])))
        );
        assert_eq!(
            parse(b"r7101"),
            Ok(Command::Transmit(Frame::remote(0x710, 1)))
        );
        assert_eq!(
            parse(b"T123456782aBcD"),
            Ok(Command::TransmitExtended {
                id: 0x1234_5678,
                rtr: false,
                len: 2,
                data: [0xAB, 0xCD, 0, 0, 0, 0, 0, 0]
            })
        );
    }

    #[test]
    fn refuses_malformed_lines() {
        assert_eq!(parse(b""), Err(SlcanError::Empty));
        assert_eq!(parse(b"X"), Err(SlcanError::Unknown(b'X')));
        assert_eq!(parse(b"t12"), Err(SlcanError::BadLength));
        assert_eq!(parse(b"t1239"), Err(SlcanError::OutOfRange));
        assert_eq!(parse(b"t123200"), Err(SlcanError::BadLength));
        assert_eq!(parse(b"t1231001"), Err(SlcanError::BadLength));
        assert_eq!(parse(b"t1231G0"), Err(SlcanError::BadHex));
        assert_eq!(parse(b"t8001AA"), Err(SlcanError::OutOfRange));
        assert_eq!(parse(b"r12310"), Err(SlcanError::BadLength));
        assert_eq!(parse(b"S9"), Err(SlcanError::OutOfRange));
        assert_eq!(parse(b"Ox"), Err(SlcanError::BadLength));
        assert_eq!(parse(b"d1231AA"), Err(SlcanError::Fd));
        assert_eq!(parse(b"T300000000"), Err(SlcanError::OutOfRange));
    }

    #[test]
    fn formats_frames() {
        let mut v = Vec::new();
        format_frame(&Frame::new(0x190, &[1, 0xAB]), &mut v);
        format_frame(&Frame::new(0x710, &[]), &mut v);
        format_frame(&Frame::remote(0x123, 8), &mut v);
        assert_eq!(v, b"t190201AB\rt7100\rr1238\r");
    }

    #[test]
    fn splits_lines_and_bounds_them() {
        let mut s = LineSplitter::new();
        let mut got: Vec<Result<Vec<u8>, SlcanError>> = Vec::new();
        s.feed(b"O\r\nt0800", |l| got.push(l.map(|x| x.to_vec())));
        s.feed(b"\r", |l| got.push(l.map(|x| x.to_vec())));
        let long = vec![b'a'; MAX_LINE + 10];
        s.feed(&long, |l| got.push(l.map(|x| x.to_vec())));
        s.feed(b"\rC\r", |l| got.push(l.map(|x| x.to_vec())));
        assert_eq!(
            got,
            vec![
                Ok(b"O".to_vec()),
                Ok(b"t0800".to_vec()),
                Err(SlcanError::BadLength),
                Ok(b"C".to_vec())
            ]
        );
    }

    proptest! {
        /// Any bytes: no panic; every accepted standard frame formats back
        /// to a line that parses to the same frame.
        #[test]
        fn parse_never_panics_and_round_trips(line in prop::collection::vec(any::<u8>(), 0..40)) {
            if let Ok(Command::Transmit(f)) = parse(&line) {
                let mut v = Vec::new();
                format_frame(&f, &mut v);
                prop_assert_eq!(v.last(), Some(&b'\r'));
                prop_assert_eq!(parse(&v[..v.len() - 1]), Ok(Command::Transmit(f)));
            }
        }

        /// Generated frames round-trip exactly.
        #[test]
        fn frames_round_trip(id in 0u16..0x800, rtr: bool, len in 0u8..=8, data: [u8; 8]) {
            let mut f = Frame { id, rtr, len, data };
            if rtr { f.data = [0; 8]; } else { for b in &mut f.data[len as usize..] { *b = 0; } }
            let mut v = Vec::new();
            format_frame(&f, &mut v);
            prop_assert_eq!(parse(&v[..v.len() - 1]), Ok(Command::Transmit(f)));
        }
    }
}
