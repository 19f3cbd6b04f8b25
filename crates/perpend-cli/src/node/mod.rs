//! `perpend node`: a board on a real (or virtual) CAN bus, from the host:
//! what it is, how it is, what it measures, its calibration in and out,
//! calibration poses captured from it, and LSS commissioning of the nodes
//! on a bus.
//!
//! ```text
//! perpend node --bus BUS --node-id N [--bitrate KBPS] [--timeout-ms MS] <command>
//!   info [--json]                   identity, versions, NMT state, configuration
//!   status [--json]                 status word in words, last emergencies (0x1003)
//!   clear-errors [--json]           empty the emergency history (0x1003 sub 0 = 0)
//!   nmt start|stop|preop|reset|reset-comm
//!   monitor [--sync-hz HZ] [--seconds S] [--csv FILE] [--start]
//!   push params.json [--preop]      write, verify, store, reset, verify again, lock
//!   pull [--out params.json]        the board's calibration as a params.json
//!   capture --plane A,B,C,D --pose K --out poses.csv [--samples N]
//!   lss scan|inquire|set-node-id|set-bitrate|activate-bitrate|store
//!                                   LSS (CiA 305, see [`lss`]): --node-id optional
//!   sdo read IDX SUB [--json]       any object, typed by the EDS (--eds FILE)
//!   sdo write IDX SUB VALUE [--force] [--json]   checked, then read back
//!   sdo list [IDX] [--json]         the EDS's entries (no bus needed)
//!   pdo show|map N OBJ… [--type T] [--event-ms MS] [--inhibit-ms MS] [--store]|off N|on N
//!   update FILE                     signed image (cargo xtask fw --sign) onto the board
//! ```
//!
//! BUS is `tcp:HOST:PORT` (the virtual board), `slcan:/dev/ttyACM0[@BAUD]`
//! or `socketcan:can0` (see [`crate::bus`]). Every failure is a sentence
//! naming the node, the bus and what to do; nothing is left half done:
//! Ctrl-C during `push` relocks the board and resets it to its stored
//! calibration (nothing is stored before every value was written and read
//! back), during `capture` appends nothing, during `monitor` ends it
//! (and returns a node it started to pre-operational). A second Ctrl-C
//! quits at once.
//!
//! Limits: the board's dictionary has no temperature object and no
//! stored-parameter stamp, so `capture` and `monitor` write no `temp_c`
//! and `info` shows no stamp.

pub mod capture;
pub mod filetype;
pub mod info;
pub mod lss;
pub mod mapping;
pub mod monitor;
pub mod params;
pub mod pdo;
pub mod sdo;
pub mod sdo_rules;
pub mod update;
pub mod update_record;
pub mod words;

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{bail, Result};

use crate::bus::{self, BusSpec};
use crate::canopen::{Client, ClientError, NodeState};

/// How to reach one board: the bus and the node (`perpend node`,
/// `perpend cell run`). Every option may stand before or after the
/// subcommand (`perpend node --bus B --node-id 5 info` and `perpend node
/// info --bus B --node-id 5` are the same); `--node-id` may be left out only
/// by the commands that address the whole bus (`lss`).
#[derive(clap::Args, Debug, Clone)]
pub struct LinkArgs {
    /// The CAN bus: `tcp:HOST:PORT` (virtual board), `slcan:/dev/ttyACM0[@BAUD]`
    /// (slcan adapter on a serial port), `socketcan:can0` (Linux SocketCAN).
    #[arg(long, global = true)]
    pub bus: Option<String>,
    /// Node-id of the board, 1..127 (decimal or 0x hex).
    #[arg(long, global = true, value_parser = crate::board::parse_node_id)]
    pub node_id: Option<u8>,
    /// CAN bit rate an slcan adapter is set to [kbit/s] (SocketCAN
    /// interfaces keep theirs: `ip link set can0 type can bitrate …`).
    #[arg(long, global = true, default_value_t = 1000)]
    pub bitrate: u32,
    /// How long the board may take to answer one SDO request [ms]
    /// (default 500), and how long an LSS request waits for its answers
    /// (default 50).
    #[arg(long, global = true)]
    pub timeout_ms: Option<u64>,
}

impl Default for LinkArgs {
    /// No bus, no node, 1000 kbit/s, the default timeouts (as parsed from
    /// no option).
    fn default() -> Self {
        Self {
            bus: None,
            node_id: None,
            bitrate: 1000,
            timeout_ms: None,
        }
    }
}

impl LinkArgs {
    /// The bus, or the sentence that says it is missing.
    ///
    /// # Errors
    /// `--bus` not given.
    pub fn bus(&self) -> Result<&str> {
        match &self.bus {
            Some(b) => Ok(b),
            None => bail!(
                "no bus given: add --bus tcp:HOST:PORT (virtual board), \
                 --bus slcan:/dev/ttyACM0 or --bus socketcan:can0"
            ),
        }
    }

    /// The node-id of a configured node, or the sentence that says it is
    /// missing (or is 0xFF, which only LSS can address).
    ///
    /// # Errors
    /// `--node-id` not given, or 0xFF.
    pub fn node_id(&self) -> Result<u8> {
        match self.node_id {
            Some(perpend_can::lss::UNCONFIGURED) => bail!(
                "node-id 0xFF means \"not configured\": such a node answers no SDO, only LSS. \
                 Find it with `perpend node --bus {bus} lss scan` and give it a node-id with \
                 `lss scan --assign FIRST --store` (or `lss set-node-id N --serial S`)",
                bus = self.bus.as_deref().unwrap_or("BUS")
            ),
            Some(n) => Ok(n),
            None => bail!(
                "no node-id given: add --node-id N (1..127; `perpend node lss fastscan` \
                 lists the nodes on a bus that have none)"
            ),
        }
    }

    /// Opens the bus with this link's bit rate and SDO timeout.
    ///
    /// # Errors
    /// A missing or bad `--bus`, a bus that cannot be opened.
    pub fn client(&self) -> Result<Client> {
        let spec: BusSpec = self.bus()?.parse()?;
        let bus = bus::open(&spec, self.bitrate)?;
        let mut client = Client::new(bus);
        client.timeout = Duration::from_millis(self.timeout_ms.unwrap_or(500).max(1));
        if let Some(ms) = self.timeout_ms {
            client.lss_timeout = Duration::from_millis(ms.max(1));
        }
        Ok(client)
    }
}

/// The link options of a parent's [`LinkArgs`] for a subcommand that
/// opens no bus (`perpend cell sim-head`): the same ids and types,
/// hidden and refused with a sentence. Flattened into that subcommand's
/// arguments, it keeps the parent's global options out of its help (clap
/// does not propagate a global option to a subcommand that has an
/// argument of the same id) and refuses them after the subcommand.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct NoLink {
    /// Refused: this command opens no bus.
    #[arg(long, hide = true, value_parser = no_link::<String>)]
    pub bus: Option<String>,
    /// Refused: this command addresses no node.
    #[arg(long, hide = true, value_parser = no_link::<u8>)]
    pub node_id: Option<u8>,
    /// Refused: this command opens no bus.
    #[arg(long, hide = true, value_parser = no_link::<u32>)]
    pub bitrate: Option<u32>,
    /// Refused: this command opens no bus.
    #[arg(long, hide = true, value_parser = no_link::<u64>)]
    pub timeout_ms: Option<u64>,
}

/// The value parser of [`NoLink`]: every value refused.
fn no_link<T>(_: &str) -> Result<T, String> {
    Err("this command opens no bus: leave out --bus, --node-id, --bitrate and --timeout-ms".into())
}

/// Arguments of `perpend node`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The bus and the node.
    #[command(flatten)]
    pub link: LinkArgs,
    /// What to do.
    #[command(subcommand)]
    pub cmd: Cmd,
}

/// The subcommands.
#[derive(clap::Subcommand, Debug)]
pub enum Cmd {
    /// Identity, versions, serial, NMT state (from the heartbeat), configuration.
    Info(info::InfoArgs),
    /// The status word (0x2005) in words and the last emergencies (0x1003).
    Status(info::InfoArgs),
    /// Empty the emergency history (0x1003 sub 0 = 0); active errors stay
    /// in the error register until their cause goes.
    ClearErrors(info::InfoArgs),
    /// Send an NMT command and wait for its effect (boot-up, heartbeat).
    Nmt(info::NmtArgs),
    /// Live θ1/θ2/θ, normal, distances, RMS and status from the TPDOs.
    Monitor(monitor::Args),
    /// Write a params.json into the board, verify, store, reset, verify again.
    Push(params::PushArgs),
    /// Read the board's calibration back into a params.json.
    Pull(params::PullArgs),
    /// Average N samples at one pose and append them to poses.csv.
    Capture(capture::Args),
    /// LSS (CiA 305): find non-configured nodes, set node-ids and bit rates.
    Lss(lss::Args),
    /// Read or write any object by index and sub-index, typed by the EDS; list the EDS.
    Sdo(sdo::Args),
    /// Show the PDOs in words; map objects into a TPDO, set its timing, switch it off or on.
    Pdo(pdo::Args),
    /// Put a signed firmware image on the board (CiA 302-3), check it after the restart.
    Update(update::Args),
}

/// Set by Ctrl-C; long operations look at it between steps.
static CANCEL: AtomicBool = AtomicBool::new(false);

/// Installs the Ctrl-C handler. For a command that `checks` the flag
/// (monitor, push, pull, capture, lss scan), the first Ctrl-C sets it and the second
/// quits at once; for the others (short reads) the first quits (exit code
/// 130, as without a handler).
fn install_ctrlc(checks: bool) {
    let _ = ctrlc::set_handler(move || {
        if !checks || CANCEL.swap(true, Ordering::SeqCst) {
            eprintln!("\nperpend node: Ctrl-C, quitting now");
            std::process::exit(130);
        }
        eprintln!("\nperpend node: Ctrl-C, finishing safely (Ctrl-C again quits at once)");
    });
}

/// A session with one node.
pub struct Node {
    /// The CANopen master.
    pub client: Client,
    /// The node-id.
    pub id: u8,
}

impl Node {
    /// A session with node `id` through `client`.
    pub fn new(client: Client, id: u8) -> Self {
        Self { client, id }
    }

    /// Opens the bus of `a` and addresses its node.
    ///
    /// # Errors
    /// A missing `--bus` or `--node-id`, a bad `--bus`, a bus that cannot be
    /// opened.
    pub fn connect(a: &LinkArgs) -> Result<Self> {
        let id = a.node_id()?;
        Ok(Self::new(a.client()?, id))
    }

    /// `node N on BUS`, for messages.
    pub fn name(&self) -> String {
        format!("node {} on {}", self.id, self.client.bus_name())
    }

    /// The first request of a command: the device type (0x1000). When it
    /// times out, listens for the node's heartbeat a little longer, so that
    /// the error can say whether the node is stopped or another node-id
    /// answers instead.
    ///
    /// # Errors
    /// The timeout with what was heard, or any other client error.
    pub fn hello(&mut self) -> Result<u32> {
        match self.client.read_u32(self.id, 0x1000, 0) {
            Ok(v) => Ok(v),
            Err(ClientError::Timeout { waited, what, .. }) => {
                let listen = Duration::from_millis(1600);
                let _ = self.client.wait_heartbeat(self.id, listen)?;
                Err(self.client.timeout_error(self.id, &what, waited).into())
            }
            Err(e) => Err(e.into()),
        }
    }

    /// The number of sensors the board has (0x2004 sub 0).
    ///
    /// # Errors
    /// Client errors.
    pub fn sensors(&mut self) -> Result<usize> {
        let n = self.client.read_u32(self.id, 0x2004, 0)? as usize;
        if n == 0 || n > 16 {
            bail!("{}: 0x2004 sub 0 says {n} sensors", self.name());
        }
        Ok(n)
    }

    /// The heartbeat period (0x1017) [ms].
    ///
    /// # Errors
    /// Client errors.
    pub fn heartbeat_ms(&mut self) -> Result<u64> {
        Ok(self.client.read_u32(self.id, 0x1017, 0)? as u64)
    }

    /// The NMT state from the heartbeat (one heard within 1.5 periods, else
    /// the next one); `None` when the heartbeat is off or does not come. A
    /// boot-up counts as pre-operational (where a node goes after it).
    ///
    /// # Errors
    /// Client errors.
    pub fn state(&mut self, heartbeat_ms: u64) -> Result<Option<NodeState>> {
        if heartbeat_ms == 0 {
            return Ok(None);
        }
        let fresh = Duration::from_millis(heartbeat_ms * 3 / 2);
        let s = match self.client.heard(self.id) {
            Some(h) if h.at.elapsed() < fresh => Some(h.state),
            _ => {
                let wait = Duration::from_millis((heartbeat_ms * 3 / 2 + 200).min(10_000));
                self.client.wait_heartbeat(self.id, wait)?
            }
        };
        Ok(s.map(|s| match s {
            NodeState::BootUp => NodeState::PreOperational,
            s => s,
        }))
    }
}

/// Runs `perpend node`.
///
/// # Errors
/// Everything that went wrong, in sentences.
pub fn run(a: &Args) -> Result<()> {
    install_ctrlc(matches!(
        a.cmd,
        Cmd::Monitor(_)
            | Cmd::Push(_)
            | Cmd::Pull(_)
            | Cmd::Capture(_)
            | Cmd::Lss(lss::Args {
                cmd: lss::Cmd::Scan(_)
            })
    ));
    if let Cmd::Sdo(x) = &a.cmd {
        if x.offline() {
            return sdo::list(&a.link, x);
        }
    }
    let cancel = &CANCEL;
    // LSS addresses the bus (non-configured nodes have no node-id).
    if let Cmd::Lss(x) = &a.cmd {
        return lss::run(&a.link, x, cancel);
    }
    // A file that is not a params.json, or not a signed image, is named
    // before the bus is opened.
    if let Cmd::Push(x) = &a.cmd {
        filetype::check_params(&x.file)?;
    }
    if let Cmd::Update(x) = &a.cmd {
        update::check_file(&x.file)?;
    }
    let mut node = Node::connect(&a.link)?;
    match &a.cmd {
        Cmd::Info(x) => info::info(&mut node, x),
        Cmd::Status(x) => info::status(&mut node, x),
        Cmd::ClearErrors(x) => info::clear_errors(&mut node, x),
        Cmd::Nmt(x) => info::nmt(&mut node, x),
        Cmd::Monitor(x) => monitor::run(&mut node, x, cancel),
        Cmd::Push(x) => params::push(&mut node, x, cancel).map(|r| println!("{r}")),
        Cmd::Pull(x) => params::pull_to(&mut node, x, cancel),
        Cmd::Capture(x) => {
            capture::check_plane(&mut node, x, cancel)?;
            capture::run(&mut node, x, cancel)
        }
        Cmd::Lss(_) => Ok(()),
        Cmd::Sdo(x) => sdo::run(&mut node, x),
        Cmd::Pdo(x) => pdo::run(&mut node, x),
        Cmd::Update(x) => update::run(&mut node, x),
    }
}
