//! A serial port as an slcan [`Link`] (`--bus slcan:/dev/ttyACM0[@BAUD]`):
//! opened without becoming the controlling terminal, put in raw mode
//! (`cfmakeraw`, receiver on, modem lines ignored, reads return what is
//! there) at the line speed given, flushed; reads wait with `poll`.
//!
//! termios through `nix` (MIT): no system package is needed to build it.
//! USB CDC adapters (CANable, most USBtin clones) ignore the line speed;
//! FTDI-based ones need the speed their firmware expects (often 115200).
//!
//! Limits: Unix only (elsewhere the bus says so); line speeds 9600 to
//! 230400 everywhere, up to 3000000 on Linux.

#[cfg(unix)]
pub use imp::SerialLink;

#[cfg(not(unix))]
pub use other::SerialLink;

#[cfg(unix)]
mod imp {
    use std::fs::{File, OpenOptions};
    use std::io::{Read, Write};
    use std::os::fd::AsFd;
    use std::os::unix::fs::OpenOptionsExt;
    use std::time::Duration;

    use nix::fcntl::{fcntl, FcntlArg, OFlag};
    use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
    use nix::sys::termios::{
        cfmakeraw, cfsetspeed, tcflush, tcgetattr, tcsetattr, BaudRate, ControlFlags, FlushArg,
        SetArg, SpecialCharacterIndices,
    };

    use super::super::slcan::Link;
    use crate::bus::BusError;

    /// An open serial port in raw mode.
    #[derive(Debug)]
    pub struct SerialLink(File);

    fn baud_rate(baud: u32) -> Option<BaudRate> {
        Some(match baud {
            9600 => BaudRate::B9600,
            19_200 => BaudRate::B19200,
            38_400 => BaudRate::B38400,
            57_600 => BaudRate::B57600,
            115_200 => BaudRate::B115200,
            230_400 => BaudRate::B230400,
            #[cfg(target_os = "linux")]
            460_800 => BaudRate::B460800,
            #[cfg(target_os = "linux")]
            921_600 => BaudRate::B921600,
            #[cfg(target_os = "linux")]
            1_000_000 => BaudRate::B1000000,
            #[cfg(target_os = "linux")]
            2_000_000 => BaudRate::B2000000,
            #[cfg(target_os = "linux")]
            3_000_000 => BaudRate::B3000000,
            _ => return None,
        })
    }

    /// Raw mode, receiver on, modem lines ignored, non-blocking reads, the
    /// speed; then both queues flushed.
    fn configure(f: &File, speed: BaudRate) -> nix::Result<()> {
        let mut t = tcgetattr(f.as_fd())?;
        cfmakeraw(&mut t);
        t.control_flags |= ControlFlags::CLOCAL | ControlFlags::CREAD;
        t.control_chars[SpecialCharacterIndices::VMIN as usize] = 0;
        t.control_chars[SpecialCharacterIndices::VTIME as usize] = 0;
        cfsetspeed(&mut t, speed)?;
        tcsetattr(f.as_fd(), SetArg::TCSANOW, &t)?;
        tcflush(f.as_fd(), FlushArg::TCIOFLUSH)?;
        // Opened non-blocking (so that a port waiting for carrier does not
        // hang the open); blocking writes from here on.
        let flags = OFlag::from_bits_truncate(fcntl(f.as_fd(), FcntlArg::F_GETFL)?);
        fcntl(f.as_fd(), FcntlArg::F_SETFL(flags & !OFlag::O_NONBLOCK))?;
        Ok(())
    }

    impl SerialLink {
        /// Opens and configures `path` at `baud`; `name` labels errors.
        ///
        /// # Errors
        /// [`BusError::Open`] with what to check.
        pub fn open(path: &str, baud: u32, name: &str) -> Result<Self, BusError> {
            let open_err = |hint: &str, source: std::io::Error| BusError::Open {
                bus: name.to_string(),
                hint: hint.to_string(),
                source,
            };
            let speed = baud_rate(baud).ok_or_else(|| BusError::Adapter {
                bus: name.to_string(),
                what: format!(
                    "line speed {baud} baud is not supported here (9600, 19200, 38400, 57600, \
                     115200, 230400; on Linux also 460800, 921600, 1000000, 2000000, 3000000)"
                ),
            })?;
            let file = OpenOptions::new()
                .read(true)
                .write(true)
                .custom_flags((OFlag::O_NOCTTY | OFlag::O_NONBLOCK).bits())
                .open(path)
                .map_err(|e| {
                    open_err(
                        "is the adapter plugged in, and may this user open the port \
                         (group dialout)?",
                        e,
                    )
                })?;
            configure(&file, speed).map_err(|e| {
                open_err(
                    "the device is not a serial port, or refused raw mode",
                    std::io::Error::from(e),
                )
            })?;
            Ok(Self(file))
        }
    }

    impl Link for SerialLink {
        fn write_all(&mut self, b: &[u8]) -> std::io::Result<()> {
            self.0.write_all(b)
        }

        fn read_timeout(
            &mut self,
            buf: &mut [u8],
            timeout: Duration,
        ) -> std::io::Result<Option<usize>> {
            let ms = PollTimeout::try_from(timeout).unwrap_or(PollTimeout::MAX);
            let mut fds = [PollFd::new(self.0.as_fd(), PollFlags::POLLIN)];
            match poll(&mut fds, ms) {
                Ok(0) => return Ok(None),
                Ok(_) => {}
                Err(nix::errno::Errno::EINTR) => return Ok(None),
                Err(e) => return Err(e.into()),
            }
            // Readable or hung up: 0 bytes now means the port went away.
            self.0.read(buf).map(Some)
        }
    }
}

#[cfg(not(unix))]
mod other {
    use std::time::Duration;

    use super::super::slcan::Link;
    use crate::bus::BusError;

    /// Serial ports are not supported on this system.
    #[derive(Debug)]
    pub struct SerialLink;

    impl SerialLink {
        /// Always an error: serial slcan is implemented for Unix only.
        ///
        /// # Errors
        /// [`BusError::Unsupported`].
        pub fn open(_path: &str, _baud: u32, name: &str) -> Result<Self, BusError> {
            Err(BusError::Unsupported(format!(
                "{name}: slcan on a serial port is implemented for Unix systems only"
            )))
        }
    }

    impl Link for SerialLink {
        fn write_all(&mut self, _b: &[u8]) -> std::io::Result<()> {
            Err(std::io::ErrorKind::Unsupported.into())
        }
        fn read_timeout(&mut self, _: &mut [u8], _: Duration) -> std::io::Result<Option<usize>> {
            Err(std::io::ErrorKind::Unsupported.into())
        }
    }
}

#[cfg(all(test, unix))]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_port_and_a_non_tty_are_named() {
        let e = SerialLink::open("/dev/does-not-exist-perpend", 115_200, "slcan:/dev/x")
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("slcan:/dev/x") && e.contains("plugged in"),
            "{e}"
        );
        let e = SerialLink::open("/dev/null", 115_200, "slcan:/dev/null")
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("not a serial port"), "{e}");
        let e = SerialLink::open("/dev/null", 12_345, "slcan:/dev/null")
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("12345 baud"), "{e}");
    }

    /// A fake adapter on a pseudo-terminal: the whole serial path (raw
    /// mode, slcan set-up, frames both ways) without hardware.
    #[cfg(target_os = "linux")]
    #[test]
    fn an_slcan_adapter_on_a_pty_carries_frames() {
        use crate::bus::slcan::SlcanBus;
        use crate::bus::Bus;
        use nix::fcntl::OFlag;
        use nix::pty::{grantpt, posix_openpt, ptsname_r, unlockpt};
        use perpend_can::Frame;
        use std::io::{Read, Write};
        use std::time::Duration;

        let mut master = posix_openpt(OFlag::O_RDWR | OFlag::O_NOCTTY).unwrap();
        grantpt(&master).unwrap();
        unlockpt(&master).unwrap();
        let path = ptsname_r(&master).unwrap();
        let adapter = std::thread::spawn(move || {
            let mut buf = [0u8; 256];
            let mut line = Vec::new();
            let mut opened = false;
            while let Ok(n) = master.read(&mut buf) {
                if n == 0 {
                    break;
                }
                for &b in &buf[..n] {
                    if b != b'\r' {
                        line.push(b);
                        continue;
                    }
                    let reply: &[u8] = match line.first() {
                        Some(b'O') => {
                            opened = true;
                            b"\r"
                        }
                        // An SDO request: confirm, then answer it.
                        Some(b't') if opened => b"z\rt59084300100000000000\r",
                        _ => b"\r",
                    };
                    if master.write_all(reply).is_err() {
                        return;
                    }
                    line.clear();
                }
            }
        });
        let link = SerialLink::open(&path, 115_200, "slcan:pty").unwrap();
        let mut bus = SlcanBus::open(link, "slcan:pty".into(), 1000).unwrap();
        bus.send(&Frame::new(0x610, &[0x40, 0, 0x10, 0, 0, 0, 0, 0]))
            .unwrap();
        let f = bus.recv(Duration::from_secs(2)).unwrap().unwrap();
        assert_eq!(f, Frame::new(0x590, &[0x43, 0, 0x10, 0, 0, 0, 0, 0]));
        drop(bus);
        adapter.join().unwrap();
    }
}
