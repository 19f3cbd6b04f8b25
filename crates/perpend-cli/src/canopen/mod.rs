//! The CANopen master side of the host tool, on any [`Bus`]: SDO upload and
//! download (expedited and segmented, [`sdo`]), NMT commands, SYNC, the
//! boot-up and heartbeat of each node, EMCY, TPDO decoding through the
//! mapping read from the device ([`pdo`]), and the LSS master (CiA 305,
//! [`lss`]).
//!
//! One [`Client`] owns the bus. Frames that arrive while it waits for
//! something else (an SDO answer, a boot-up) are kept, bounded, for
//! [`Client::recv`]; every frame is looked at on the way: heartbeats and
//! boot-ups give each node's NMT state ([`Client::heard`]), EMCY frames are
//! collected ([`Client::take_emcy`]), a SYNC from another producer is noted
//! ([`Client::sync_seen`]).
//!
//! Every failure is a [`ClientError`] that says which node, which bus, what
//! was asked, and (for an abort) what the code means ([`abort::describe`]).

pub mod abort;
pub mod lss;
pub mod pdo;
pub mod sdo;

use std::collections::{BTreeMap, VecDeque};
use std::fmt;
use std::time::{Duration, Instant};

use perpend_can::Frame;

use crate::bus::{Bus, BusError};

/// Frames kept for [`Client::recv`] at most (the oldest are dropped).
const BACKLOG: usize = 4096;
/// EMCY messages kept at most.
const EMCY_KEPT: usize = 64;

/// A node's NMT state as its heartbeat or boot-up says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NodeState {
    /// The boot-up message (the node has just reset).
    BootUp,
    /// Stopped: only NMT and heartbeat.
    Stopped,
    /// Operational: PDOs; calibration read-only.
    Operational,
    /// Pre-operational: SDO, no PDOs; calibration writable.
    PreOperational,
    /// A state byte CiA 301 does not define.
    Other(u8),
}

impl NodeState {
    /// From the heartbeat's state byte (bit 7, the node-guarding toggle,
    /// ignored).
    pub fn from_byte(b: u8) -> Self {
        match b & 0x7F {
            0x00 => NodeState::BootUp,
            0x04 => NodeState::Stopped,
            0x05 => NodeState::Operational,
            0x7F => NodeState::PreOperational,
            x => NodeState::Other(x),
        }
    }
}

impl fmt::Display for NodeState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            NodeState::BootUp => f.write_str("booting (boot-up message)"),
            NodeState::Stopped => f.write_str("stopped"),
            NodeState::Operational => f.write_str("operational"),
            NodeState::PreOperational => f.write_str("pre-operational"),
            NodeState::Other(x) => write!(f, "unknown state {x:#04x}"),
        }
    }
}

/// NMT commands (CiA 301 §7.2.8.3.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Nmt {
    /// Start remote node → operational.
    Start,
    /// Stop remote node → stopped.
    Stop,
    /// Enter pre-operational.
    Preop,
    /// Reset node: every object back to its stored value, boot-up follows.
    Reset,
    /// Reset communication: the communication objects only.
    ResetComm,
}

impl Nmt {
    /// The command specifier.
    pub const fn code(self) -> u8 {
        match self {
            Nmt::Start => 0x01,
            Nmt::Stop => 0x02,
            Nmt::Preop => 0x80,
            Nmt::Reset => 0x81,
            Nmt::ResetComm => 0x82,
        }
    }
}

/// The last heartbeat or boot-up heard from a node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Heard {
    /// Its state.
    pub state: NodeState,
    /// When.
    pub at: Instant,
}

/// An emergency message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Emcy {
    /// Sending node.
    pub node: u8,
    /// Error code (0 = error reset).
    pub code: u16,
    /// Error register (0x1001).
    pub register: u8,
    /// Manufacturer-specific bytes.
    pub data: [u8; 5],
}

/// What went wrong talking to a node.
#[derive(Debug)]
pub enum ClientError {
    /// The bus failed.
    Bus(BusError),
    /// The node did not answer in time.
    Timeout {
        /// Node-id asked.
        node: u8,
        /// The bus.
        bus: String,
        /// What was asked, in words.
        what: String,
        /// How long the client waited.
        waited: Duration,
        /// What the client heard meanwhile, and what to check.
        hint: String,
    },
    /// The node refused with an SDO abort.
    Abort {
        /// Node-id.
        node: u8,
        /// Object.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Abort code.
        code: u32,
        /// A write (download), else a read.
        write: bool,
    },
    /// The node answered something the protocol does not allow.
    Protocol {
        /// Node-id.
        node: u8,
        /// What, in words.
        what: String,
    },
}

impl ClientError {
    /// The abort code, when the node refused.
    pub fn abort_code(&self) -> Option<u32> {
        match self {
            ClientError::Abort { code, .. } => Some(*code),
            _ => None,
        }
    }
}

impl fmt::Display for ClientError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ClientError::Bus(e) => e.fmt(f),
            ClientError::Timeout {
                node,
                bus,
                what,
                waited,
                hint,
            } => write!(
                f,
                "no answer from node {node} on {bus} within {} ms ({what}): {hint}",
                waited.as_millis()
            ),
            ClientError::Abort {
                node,
                index,
                sub,
                code,
                write,
            } => write!(
                f,
                "node {node} refused {} {index:#06x} sub {sub} with abort {code:#010x}: {}",
                if *write {
                    "the write of"
                } else {
                    "the read of"
                },
                abort::describe(*code)
            ),
            ClientError::Protocol { node, what } => write!(f, "node {node}: {what}"),
        }
    }
}

/// A bus error's sentence is the whole message, so no `source()` (a chain
/// printed with `{:#}` would repeat it).
impl std::error::Error for ClientError {}

impl From<BusError> for ClientError {
    fn from(e: BusError) -> Self {
        ClientError::Bus(e)
    }
}

/// The CANopen master.
pub struct Client {
    bus: Box<dyn Bus>,
    /// How long an SDO answer may take.
    pub timeout: Duration,
    /// How long an LSS request waits for its answers ([`lss`]).
    pub lss_timeout: Duration,
    backlog: VecDeque<(Instant, Frame)>,
    heard: BTreeMap<u8, Heard>,
    emcy: VecDeque<Emcy>,
    sync_seen: Option<Instant>,
}

impl Client {
    /// A client on `bus` with a 500 ms SDO timeout and a 50 ms LSS one.
    pub fn new(bus: Box<dyn Bus>) -> Self {
        Self {
            bus,
            timeout: Duration::from_millis(500),
            lss_timeout: lss::DEFAULT_TIMEOUT,
            backlog: VecDeque::new(),
            heard: BTreeMap::new(),
            emcy: VecDeque::new(),
            sync_seen: None,
        }
    }

    /// The bus's name.
    pub fn bus_name(&self) -> &str {
        self.bus.name()
    }

    /// Sends a frame.
    ///
    /// # Errors
    /// [`ClientError::Bus`].
    pub fn send(&mut self, f: &Frame) -> Result<(), ClientError> {
        Ok(self.bus.send(f)?)
    }

    /// Sends an NMT command to `node` (0: every node).
    ///
    /// # Errors
    /// [`ClientError::Bus`].
    pub fn nmt(&mut self, node: u8, cmd: Nmt) -> Result<(), ClientError> {
        self.send(&Frame::new(0x000, &[cmd.code(), node]))?;
        self.forget_state(node);
        Ok(())
    }

    /// Forgets the state heard from `node` (0: every node): after an NMT
    /// command, only a newer heartbeat tells the state.
    fn forget_state(&mut self, node: u8) {
        if node == 0 {
            self.heard
                .values_mut()
                .for_each(|h| h.state = NodeState::Other(0xFF));
        } else if let Some(h) = self.heard.get_mut(&node) {
            h.state = NodeState::Other(0xFF);
        }
    }

    /// Sends a SYNC.
    ///
    /// # Errors
    /// [`ClientError::Bus`].
    pub fn sync(&mut self) -> Result<(), ClientError> {
        self.send(&Frame::new(0x080, &[]))
    }

    /// The last heartbeat or boot-up of `node`, unless an NMT command for
    /// it was sent or seen since.
    pub fn heard(&self, node: u8) -> Option<Heard> {
        self.heard
            .get(&node)
            .copied()
            .filter(|h| h.state != NodeState::Other(0xFF))
    }

    /// Every node heard so far.
    pub fn heard_nodes(&self) -> Vec<u8> {
        self.heard.keys().copied().collect()
    }

    /// When another producer's SYNC was last seen.
    pub fn sync_seen(&self) -> Option<Instant> {
        self.sync_seen
    }

    /// The EMCY messages received so far (oldest first), forgotten here.
    pub fn take_emcy(&mut self) -> Vec<Emcy> {
        self.emcy.drain(..).collect()
    }

    fn note(&mut self, f: &Frame, at: Instant) {
        let id = f.id;
        if id == 0x080 && f.len == 0 && !f.rtr {
            self.sync_seen = Some(at);
        } else if id == 0x000 && f.len == 2 && !f.rtr {
            // Another master's NMT command.
            self.forget_state(f.data[1]);
        } else if (0x701..=0x77F).contains(&id) && f.len == 1 && !f.rtr {
            let state = NodeState::from_byte(f.data[0]);
            self.heard.insert((id - 0x700) as u8, Heard { state, at });
        } else if (0x081..=0x0FF).contains(&id) && f.len == 8 && !f.rtr {
            if self.emcy.len() == EMCY_KEPT {
                self.emcy.pop_front();
            }
            let d = f.data;
            self.emcy.push_back(Emcy {
                node: (id - 0x080) as u8,
                code: u16::from_le_bytes([d[0], d[1]]),
                register: d[2],
                data: [d[3], d[4], d[5], d[6], d[7]],
            });
        }
    }

    fn keep(&mut self, f: Frame, at: Instant) {
        if self.backlog.len() == BACKLOG {
            self.backlog.pop_front();
        }
        self.backlog.push_back((at, f));
    }

    /// The next frame (kept ones first), waiting at most `timeout`, with
    /// the time it was received.
    ///
    /// # Errors
    /// [`ClientError::Bus`].
    pub fn recv(&mut self, timeout: Duration) -> Result<Option<(Instant, Frame)>, ClientError> {
        if let Some(x) = self.backlog.pop_front() {
            return Ok(Some(x));
        }
        match self.bus.recv(timeout)? {
            Some(f) => {
                let at = Instant::now();
                self.note(&f, at);
                Ok(Some((at, f)))
            }
            None => Ok(None),
        }
    }

    /// Waits at most `timeout` for a frame from the bus that `pred`
    /// accepts; the others are kept for [`Client::recv`].
    ///
    /// # Errors
    /// [`ClientError::Bus`].
    pub fn wait_for(
        &mut self,
        timeout: Duration,
        mut pred: impl FnMut(&Frame) -> bool,
    ) -> Result<Option<Frame>, ClientError> {
        let end = Instant::now() + timeout;
        loop {
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            if let Some(f) = self.bus.recv(left)? {
                let at = Instant::now();
                self.note(&f, at);
                if pred(&f) {
                    return Ok(Some(f));
                }
                self.keep(f, at);
            }
        }
    }

    /// Waits for `node`'s next heartbeat (at most `timeout`) and returns its
    /// state, `None` when none came.
    ///
    /// # Errors
    /// [`ClientError::Bus`].
    pub fn wait_heartbeat(
        &mut self,
        node: u8,
        timeout: Duration,
    ) -> Result<Option<NodeState>, ClientError> {
        let id = 0x700 + node as u16;
        let f = self.wait_for(timeout, |f| f.id == id && f.len == 1 && !f.rtr)?;
        Ok(f.map(|f| NodeState::from_byte(f.data[0])))
    }

    /// Waits for `node`'s boot-up message (at most `timeout`).
    ///
    /// # Errors
    /// [`ClientError::Timeout`] when it does not come.
    pub fn wait_bootup(&mut self, node: u8, timeout: Duration) -> Result<(), ClientError> {
        let id = 0x700 + node as u16;
        match self.wait_for(timeout, |f| f.id == id && f.len == 1 && f.data[0] == 0)? {
            Some(_) => Ok(()),
            None => Err(self.timeout_error(node, "boot-up message after a reset", timeout)),
        }
    }

    /// The timeout error for `node`, with what was heard meanwhile.
    pub fn timeout_error(&self, node: u8, what: &str, waited: Duration) -> ClientError {
        let others: Vec<String> = self
            .heard
            .keys()
            .filter(|&&n| n != node)
            .map(|n| n.to_string())
            .collect();
        let hint = match self.heard(node) {
            Some(h) if h.state == NodeState::Stopped => format!(
                "node {node} is stopped (its heartbeat says so) and a stopped node answers no SDO; \
                 `perpend node … nmt preop` first"
            ),
            Some(_) => format!(
                "its heartbeat is heard but it did not answer: is another master's transfer to \
                 node {node} in progress?"
            ),
            None if !others.is_empty() => format!(
                "heard on the bus: node {}; is --node-id right?",
                others.join(", node ")
            ),
            None => "nothing was heard on the bus: is the board powered and connected, the \
                     node-id right and the bit rate the board's?"
                .to_string(),
        };
        ClientError::Timeout {
            node,
            bus: self.bus.name().to_string(),
            what: what.to_string(),
            waited,
            hint,
        }
    }
}
