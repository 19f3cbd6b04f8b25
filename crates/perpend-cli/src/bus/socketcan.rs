//! Linux SocketCAN (`--bus socketcan:can0`) through the `socketcan` crate
//! (MIT, pure Rust over libc; built without its netlink part): a raw CAN
//! socket bound to the interface. The interface must be up with its bit
//! rate set beforehand (`ip link set can0 up type can bitrate 1000000`);
//! `--bitrate` does not apply. Error frames and extended frames are
//! dropped.
//!
//! Built with the cargo feature `socketcan` (default) on Linux; elsewhere
//! [`open`] says that this build cannot open such a bus.

use super::{Bus, BusError};

/// Opens the SocketCAN interface `iface`; `name` labels errors.
///
/// # Errors
/// [`BusError::Open`] (no such interface, interface down) or
/// [`BusError::Unsupported`].
#[cfg(all(target_os = "linux", feature = "socketcan"))]
pub fn open(iface: &str, name: String) -> Result<Box<dyn Bus>, BusError> {
    use socketcan::Socket as _;
    let sock = socketcan::CanSocket::open(iface).map_err(|source| BusError::Open {
        bus: name.clone(),
        hint: format!(
            "does the interface exist and is it up? `ip link set {iface} up type can bitrate \
             1000000`"
        ),
        source,
    })?;
    Ok(Box::new(imp::SocketCanBus { sock, name }))
}

/// Opens the SocketCAN interface `iface`: not in this build.
///
/// # Errors
/// Always [`BusError::Unsupported`].
#[cfg(not(all(target_os = "linux", feature = "socketcan")))]
pub fn open(_iface: &str, name: String) -> Result<Box<dyn Bus>, BusError> {
    Err(BusError::Unsupported(format!(
        "{name}: this build has no SocketCAN support (Linux only, cargo feature `socketcan`)"
    )))
}

#[cfg(all(target_os = "linux", feature = "socketcan"))]
mod imp {
    use std::io::ErrorKind;
    use std::time::{Duration, Instant};

    use perpend_can::Frame;
    use socketcan::{CanFrame, EmbeddedFrame as _, Id, Socket as _, StandardId};

    use crate::bus::{Bus, BusError};

    /// A raw CAN socket.
    pub struct SocketCanBus {
        pub(super) sock: socketcan::CanSocket,
        pub(super) name: String,
    }

    /// Our frame from a socket frame; `None` for extended and error frames.
    pub(super) fn from_socket(f: &CanFrame) -> Option<Frame> {
        let Id::Standard(id) = f.id() else {
            return None;
        };
        match f {
            CanFrame::Data(_) => Some(Frame::new(id.as_raw(), f.data())),
            CanFrame::Remote(_) => Some(Frame::remote(id.as_raw(), f.dlc() as u8)),
            CanFrame::Error(_) => None,
        }
    }

    /// The socket frame of ours; `None` for an invalid id or length.
    pub(super) fn to_socket(f: &Frame) -> Option<CanFrame> {
        let id = StandardId::new(f.id)?;
        if f.rtr {
            CanFrame::new_remote(id, f.len as usize)
        } else {
            CanFrame::new(id, f.payload())
        }
    }

    impl Bus for SocketCanBus {
        fn send(&mut self, f: &Frame) -> Result<(), BusError> {
            let frame = to_socket(f).ok_or_else(|| BusError::Io {
                bus: self.name.clone(),
                source: std::io::Error::new(ErrorKind::InvalidInput, "not a classic CAN frame"),
            })?;
            self.sock
                .write_frame_insist(&frame)
                .map_err(|source| BusError::Io {
                    bus: self.name.clone(),
                    source,
                })
        }

        fn recv(&mut self, timeout: Duration) -> Result<Option<Frame>, BusError> {
            let end = Instant::now() + timeout;
            loop {
                let left = end.saturating_duration_since(Instant::now());
                if left.is_zero() {
                    return Ok(None);
                }
                match self.sock.read_frame_timeout(left) {
                    Ok(f) => {
                        if let Some(f) = from_socket(&f) {
                            return Ok(Some(f));
                        }
                    }
                    Err(e)
                        if matches!(
                            e.kind(),
                            ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                        ) => {}
                    Err(source) => {
                        return Err(BusError::Io {
                            bus: self.name.clone(),
                            source,
                        })
                    }
                }
            }
        }

        fn name(&self) -> &str {
            &self.name
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    #[test]
    fn a_missing_interface_is_named() {
        let e = super::open("perpendnone0", "socketcan:perpendnone0".into())
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("socketcan:perpendnone0"), "{e}");
    }

    #[cfg(all(target_os = "linux", feature = "socketcan"))]
    #[test]
    fn frames_convert_both_ways() {
        use perpend_can::Frame;
        for f in [
            Frame::new(0x601, &[0x40, 0x18, 0x10, 1, 0, 0, 0, 0]),
            Frame::new(0x080, &[]),
            Frame::remote(0x710, 1),
        ] {
            let s = super::imp::to_socket(&f).unwrap();
            assert_eq!(super::imp::from_socket(&s), Some(f));
        }
        assert!(super::imp::to_socket(&Frame::new(0x800, &[1])).is_none());
    }
}
