//! CAN buses of the host tool: one [`Bus`] trait (send a frame, receive
//! with a timeout) and the transports behind the `--bus` option.
//!
//! ```text
//! tcp:HOST:PORT              slcan over TCP (the virtual board, `perpend board`)
//! slcan:/dev/ttyACM0[@BAUD]  slcan on a serial port (CANable, USBtin and the like);
//!                            BAUD is the serial line speed (default 115200, ignored
//!                            by USB CDC adapters); the CAN bit rate is `--bitrate`
//! socketcan:can0             Linux SocketCAN (cargo feature `socketcan`, on by default);
//!                            the bit rate is the interface's (`ip link set can0 type
//!                            can bitrate 1000000`)
//! ```
//!
//! [`fake::FakeBus`] is the in-memory bus of the tests. Frames are
//! [`perpend_can::Frame`]s (11-bit identifiers); extended frames received
//! from a transport are dropped (CANopen CiA 301 does not use them).

pub mod fake;
pub mod serial;
pub mod slcan;
pub mod socketcan;

use std::fmt;
use std::time::Duration;

use perpend_can::Frame;

/// A CAN bus as the CANopen client sees it.
pub trait Bus: Send {
    /// Sends one frame.
    ///
    /// # Errors
    /// [`BusError`] when the transport fails.
    fn send(&mut self, f: &Frame) -> Result<(), BusError>;

    /// The next received frame, waiting at most `timeout`; `Ok(None)` when
    /// none came in that time.
    ///
    /// # Errors
    /// [`BusError`] when the transport fails or closes.
    fn recv(&mut self, timeout: Duration) -> Result<Option<Frame>, BusError>;

    /// The bus as the user named it (`tcp:127.0.0.1:5555`), for messages.
    fn name(&self) -> &str;
}

/// Why a bus cannot be opened or used.
#[derive(Debug)]
pub enum BusError {
    /// The `--bus` text is not one of the three forms.
    Syntax(String),
    /// The transport could not be opened.
    Open {
        /// The bus as named.
        bus: String,
        /// What was tried, in words.
        hint: String,
        /// The system's error.
        source: std::io::Error,
    },
    /// Reading or writing failed after the bus was open.
    Io {
        /// The bus as named.
        bus: String,
        /// The system's error.
        source: std::io::Error,
    },
    /// The other end closed the connection.
    Closed {
        /// The bus as named.
        bus: String,
    },
    /// An slcan adapter refused a set-up command or did not answer it.
    Adapter {
        /// The bus as named.
        bus: String,
        /// What went wrong, in words.
        what: String,
    },
    /// This build cannot open this kind of bus.
    Unsupported(String),
}

impl fmt::Display for BusError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            BusError::Syntax(s) => write!(
                f,
                "--bus '{s}': expected tcp:HOST:PORT (virtual board), slcan:/dev/TTY[@BAUD] \
                 (slcan adapter on a serial port) or socketcan:IFACE (Linux SocketCAN)"
            ),
            BusError::Open { bus, hint, source } => {
                write!(f, "cannot open {bus}: {source}; {hint}")
            }
            BusError::Io { bus, source } => write!(f, "{bus}: the transport failed: {source}"),
            BusError::Closed { bus } => {
                write!(f, "{bus}: the other end closed the connection")
            }
            BusError::Adapter { bus, what } => write!(f, "{bus}: {what}"),
            BusError::Unsupported(s) => f.write_str(s),
        }
    }
}

/// The system's error is part of each sentence, so no `source()`: a
/// chain printed with `{:#}` would repeat it.
impl std::error::Error for BusError {}

/// A parsed `--bus` value.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BusSpec {
    /// slcan over TCP to `HOST:PORT`.
    Tcp(String),
    /// slcan on the serial port `path` at line speed `baud`.
    Slcan {
        /// Device path, e.g. `/dev/ttyACM0`.
        path: String,
        /// Serial line speed [baud].
        baud: u32,
    },
    /// SocketCAN interface.
    SocketCan(String),
}

/// Default serial line speed of slcan adapters [baud].
pub const DEFAULT_BAUD: u32 = 115_200;

impl std::str::FromStr for BusSpec {
    type Err = BusError;

    fn from_str(s: &str) -> Result<Self, BusError> {
        let bad = || BusError::Syntax(s.to_string());
        let (kind, rest) = s.split_once(':').ok_or_else(bad)?;
        if rest.is_empty() {
            return Err(bad());
        }
        match kind {
            "tcp" => {
                let (host, port) = rest.rsplit_once(':').ok_or_else(bad)?;
                if host.is_empty() || port.parse::<u16>().is_err() {
                    return Err(bad());
                }
                Ok(BusSpec::Tcp(rest.to_string()))
            }
            "slcan" => {
                let (path, baud) = match rest.rsplit_once('@') {
                    Some((p, b)) => (p, b.parse::<u32>().map_err(|_| bad())?),
                    None => (rest, DEFAULT_BAUD),
                };
                if path.is_empty() || baud == 0 {
                    return Err(bad());
                }
                Ok(BusSpec::Slcan {
                    path: path.to_string(),
                    baud,
                })
            }
            "socketcan" => Ok(BusSpec::SocketCan(rest.to_string())),
            _ => Err(bad()),
        }
    }
}

impl fmt::Display for BusSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            BusSpec::Tcp(a) => write!(f, "tcp:{a}"),
            BusSpec::Slcan { path, baud } if *baud == DEFAULT_BAUD => write!(f, "slcan:{path}"),
            BusSpec::Slcan { path, baud } => write!(f, "slcan:{path}@{baud}"),
            BusSpec::SocketCan(i) => write!(f, "socketcan:{i}"),
        }
    }
}

/// Opens the bus; `bitrate_kbps` is the CAN bit rate an slcan adapter is
/// set to (SocketCAN interfaces keep theirs; the virtual board ignores it).
///
/// # Errors
/// [`BusError`] naming the bus and what to check.
pub fn open(spec: &BusSpec, bitrate_kbps: u32) -> Result<Box<dyn Bus>, BusError> {
    let name = spec.to_string();
    match spec {
        BusSpec::Tcp(addr) => {
            let link = slcan::TcpLink::connect(addr, &name)?;
            Ok(Box::new(slcan::SlcanBus::open(link, name, bitrate_kbps)?))
        }
        BusSpec::Slcan { path, baud } => {
            let link = serial::SerialLink::open(path, *baud, &name)?;
            Ok(Box::new(slcan::SlcanBus::open(link, name, bitrate_kbps)?))
        }
        BusSpec::SocketCan(iface) => socketcan::open(iface, name),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn bus_specs_parse_and_print() {
        let t: BusSpec = "tcp:127.0.0.1:5555".parse().unwrap();
        assert_eq!(t, BusSpec::Tcp("127.0.0.1:5555".into()));
        assert_eq!(t.to_string(), "tcp:127.0.0.1:5555");
        let s: BusSpec = "slcan:/dev/ttyACM0".parse().unwrap();
        assert_eq!(
            s,
            BusSpec::Slcan {
                path: "/dev/ttyACM0".into(),
                baud: DEFAULT_BAUD
            }
        );
        assert_eq!(s.to_string(), "slcan:/dev/ttyACM0");
        let s: BusSpec = "slcan:/dev/ttyUSB0@921600".parse().unwrap();
        assert_eq!(s.to_string(), "slcan:/dev/ttyUSB0@921600");
        let c: BusSpec = "socketcan:can0".parse().unwrap();
        assert_eq!(c, BusSpec::SocketCan("can0".into()));
        for bad in [
            "can0",
            "tcp:5555",
            "tcp:host:port",
            "slcan:",
            "slcan:/dev/x@fast",
            "usb:x",
        ] {
            let e = bad.parse::<BusSpec>().unwrap_err().to_string();
            assert!(e.contains("expected tcp:HOST:PORT"), "{bad}: {e}");
        }
    }

    #[test]
    fn a_closed_port_is_named_in_the_error() {
        // Bind then drop: the port is (almost surely) closed now.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let spec: BusSpec = format!("tcp:127.0.0.1:{port}").parse().unwrap();
        let e = open(&spec, 1000).err().unwrap().to_string();
        assert!(e.contains(&format!("tcp:127.0.0.1:{port}")), "{e}");
        assert!(e.contains("perpend board"), "{e}");
    }
}
