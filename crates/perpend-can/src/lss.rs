//! LSS slave (CiA 305 v3.0, layer setting services): the protocol state
//! machine, without I/O. The device ([`crate::Device`]) feeds it every
//! frame on COB-ID [`MASTER_ID`] 0x7E5 and sends its answers on
//! [`SLAVE_ID`] 0x7E4; what touches the dictionary or storage (the pending
//! node-id in 0x2400 sub 1, the store request, the bit-rate switch) comes
//! back as an [`Outcome`] for the device to carry out.
//!
//! Services (command specifier, CiA 305 §5):
//!
//! | cs | service | state | answer |
//! |---|---|---|---|
//! | 0x04 | switch state global (0 waiting, 1 configuration) | any | none |
//! | 0x40..0x43 | switch state selective: vendor-ID, product code, revision, serial (0x1018 sub 1-4) in this order | waiting | 0x44 when all four match |
//! | 0x11 | configure node-id: 1..127 or 0xFF (non-configured) | configuration | 0x11, error 0 / 1 (out of range) |
//! | 0x13 | configure bit timing: table 0 index | configuration | 0x13, error 0 / 1 (not supported) |
//! | 0x15 | activate bit timing, switch delay \[ms\] | configuration | none |
//! | 0x17 | store configuration (node-id, bit timing) | configuration | 0x17, error 0 / 2 (storage media access error) |
//! | 0x5A..0x5D | inquire vendor-ID, product code, revision, serial | configuration | same cs, value |
//! | 0x5E | inquire node-id (the active one; 0xFF when non-configured) | configuration | 0x5E, node-id |
//! | 0x46..0x4B | identify remote slave: vendor-ID, product code, revision low/high, serial low/high | any | 0x4F when the identity is inside |
//! | 0x4C | identify non-configured remote slave | any | 0x50 when non-configured |
//! | 0x51 | fastscan | waiting, non-configured | 0x4F on a match |
//!
//! Bit timing table 0 ([`TABLE0_KBPS`]): 0 = 1000, 1 = 800, 2 = 500,
//! 3 = 250, 4 = 125, 5 reserved, 6 = 50, 7 = 20, 8 = 10 kbit/s, 9 automatic
//! detection. The board's FDCAN timing (`perpend_board::bittiming`) exists
//! for 1000, 500, 250 and 125 kbit/s ([`crate::config::BIT_RATES_KBPS`]);
//! every other index, and any table selector other than 0, answers error 1
//! "bit timing not supported".
//!
//! Fastscan (CiA 305 §5.4.4): `[0x51, IDNumber u32, BitChecked, LSSSub,
//! LSSNext]`. BitChecked 0x80 resets the scan (every non-configured slave
//! in waiting state answers); otherwise a slave whose position equals
//! LSSSub answers when bits 31..BitChecked of its identity word LSSSub
//! equal IDNumber's, then takes LSSNext as its position; with BitChecked 0
//! and LSSNext < LSSSub the whole 128-bit identity matched and the slave
//! enters configuration state.
//!
//! Limits: one LSS slave per device; table 0 only; no "inquire
//! identity" of several slaves at once (the master selects one first).

/// COB-ID of LSS requests (master → slave).
pub const MASTER_ID: u16 = 0x7E5;
/// COB-ID of LSS answers (slave → master).
pub const SLAVE_ID: u16 = 0x7E4;
/// The node-id of a non-configured node (CiA 305).
pub const UNCONFIGURED: u8 = 0xFF;

/// CiA 305 bit timing table 0 \[kbit/s\] (`None`: reserved; index 9 is
/// automatic bit rate detection, also `None`).
pub const TABLE0_KBPS: [Option<u16>; 10] = [
    Some(1000),
    Some(800),
    Some(500),
    Some(250),
    Some(125),
    None,
    Some(50),
    Some(20),
    Some(10),
    None,
];

/// Command specifiers (CiA 305 table 6 and following).
pub mod cs {
    /// Switch state global.
    pub const SWITCH_GLOBAL: u8 = 0x04;
    /// Configure node-id.
    pub const CONFIGURE_NODE_ID: u8 = 0x11;
    /// Configure bit timing parameters.
    pub const CONFIGURE_BIT_TIMING: u8 = 0x13;
    /// Activate bit timing parameters.
    pub const ACTIVATE_BIT_TIMING: u8 = 0x15;
    /// Store configuration.
    pub const STORE: u8 = 0x17;
    /// Switch state selective, vendor-ID (first of four: 0x40..0x43).
    pub const SELECTIVE_VENDOR: u8 = 0x40;
    /// Switch state selective, serial number (last of four).
    pub const SELECTIVE_SERIAL: u8 = 0x43;
    /// Switch state selective answer.
    pub const SELECTIVE_ANSWER: u8 = 0x44;
    /// Identify remote slave, vendor-ID (first of six: 0x46..0x4B).
    pub const IDENTIFY_VENDOR: u8 = 0x46;
    /// Identify remote slave, serial number high (last of six).
    pub const IDENTIFY_SERIAL_HIGH: u8 = 0x4B;
    /// Identify non-configured remote slave.
    pub const IDENTIFY_NON_CONFIGURED: u8 = 0x4C;
    /// Identify slave (answer to identify remote slave and fastscan).
    pub const IDENTIFY_SLAVE: u8 = 0x4F;
    /// Identify non-configured slave (answer to 0x4C).
    pub const NON_CONFIGURED_SLAVE: u8 = 0x50;
    /// Fastscan.
    pub const FASTSCAN: u8 = 0x51;
    /// Inquire identity vendor-ID (first of four: 0x5A..0x5D).
    pub const INQUIRE_VENDOR: u8 = 0x5A;
    /// Inquire identity serial number (last of four).
    pub const INQUIRE_SERIAL: u8 = 0x5D;
    /// Inquire node-id.
    pub const INQUIRE_NODE_ID: u8 = 0x5E;
}

/// Error code of the configure answers: success.
pub const ERR_NONE: u8 = 0;
/// Configure node-id: node-id out of range; configure bit timing: bit
/// timing not supported.
pub const ERR_NOT_SUPPORTED: u8 = 1;
/// Store configuration: storage media access error.
pub const ERR_STORAGE: u8 = 2;

/// Fastscan BitChecked value that resets the scan.
const FASTSCAN_RESET: u8 = 0x80;

/// LSS state (CiA 305 §4.3): independent of the NMT state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LssState {
    /// Only switch, identify and fastscan services are served.
    #[default]
    Waiting,
    /// Configure, store, activate and inquire services are served too.
    Configuration,
}

/// What the device knows that the protocol needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Context {
    /// The LSS address: 0x1018 sub 1..4 (vendor-ID, product code,
    /// revision, serial).
    pub identity: [u32; 4],
    /// The active node-id ([`UNCONFIGURED`] when non-configured).
    pub active_node_id: u8,
    /// The pending node-id (0x2400 sub 1: active after the next NMT
    /// reset communication).
    pub pending_node_id: u8,
    /// The active bit rate \[kbit/s\].
    pub bit_rate_kbps: u16,
}

impl Context {
    /// Whether the node is non-configured (CiA 305): no valid node-id is
    /// active nor pending.
    pub const fn non_configured(&self) -> bool {
        self.active_node_id == UNCONFIGURED && self.pending_node_id == UNCONFIGURED
    }
}

/// What the device must do after a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// Send this answer on [`SLAVE_ID`].
    Reply([u8; 8]),
    /// Configure node-id accepted: make `id` the pending node-id (0x2400
    /// sub 1), then send [`reply_code`]`(0x11, 0)`.
    NodeId(u8),
    /// Activate bit timing: stop sending, switch to `kbps` after
    /// `delay_ms`, send nothing for another `delay_ms`.
    Activate {
        /// The new bit rate \[kbit/s\].
        kbps: u16,
        /// The switch delay \[ms\].
        delay_ms: u16,
    },
    /// Store configuration: store the pending node-id and `kbps` (the
    /// pending bit rate); answer [`reply_code`]`(0x17, 0 or 2)` with the
    /// outcome.
    Store {
        /// The bit rate to store \[kbit/s\].
        kbps: u16,
    },
    /// The slave left configuration state: a non-configured node given a
    /// valid pending node-id continues its start-up (NMT reset
    /// communication, CiA 305 §4.3).
    Waiting,
}

/// The answer `[cs, code, 0, ...]` of the configure and store services.
pub const fn reply_code(cs: u8, code: u8) -> [u8; 8] {
    [cs, code, 0, 0, 0, 0, 0, 0]
}

fn reply_u32(cs: u8, v: u32) -> [u8; 8] {
    let b = v.to_le_bytes();
    [cs, b[0], b[1], b[2], b[3], 0, 0, 0]
}

/// The protocol state of one LSS slave.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct LssSlave {
    state: LssState,
    /// Switch state selective: number of identity words matched so far.
    selective: u8,
    /// Identify remote slave: requests received in order so far and
    /// whether every one matched.
    remote: u8,
    remote_match: bool,
    remote_low: u32,
    /// Fastscan: the identity word being scanned.
    fastscan_pos: u8,
    /// Configured, not yet activated bit rate \[kbit/s\].
    pending_kbps: Option<u16>,
}

impl LssSlave {
    /// A slave in waiting state.
    pub const fn new() -> Self {
        Self {
            state: LssState::Waiting,
            selective: 0,
            remote: 0,
            remote_match: false,
            remote_low: 0,
            fastscan_pos: 0,
            pending_kbps: None,
        }
    }

    /// The LSS state.
    pub const fn state(&self) -> LssState {
        self.state
    }

    /// The configured bit rate not yet activated \[kbit/s\].
    pub const fn pending_kbps(&self) -> Option<u16> {
        self.pending_kbps
    }

    /// Handles one request (the payload of a frame on [`MASTER_ID`]; not
    /// 8 bytes long: ignored, CiA 305 frames always have 8).
    pub fn handle(&mut self, data: &[u8], ctx: &Context) -> Option<Outcome> {
        let d: &[u8; 8] = data.try_into().ok()?;
        let c = d[0];
        let word = u32::from_le_bytes([d[1], d[2], d[3], d[4]]);
        if !(cs::SELECTIVE_VENDOR..=cs::SELECTIVE_SERIAL).contains(&c) {
            self.selective = 0;
        }
        match c {
            cs::SWITCH_GLOBAL => self.switch_global(d[1]),
            cs::SELECTIVE_VENDOR..=cs::SELECTIVE_SERIAL => self.selective(c, word, ctx),
            cs::IDENTIFY_VENDOR..=cs::IDENTIFY_SERIAL_HIGH => self.identify(c, word, ctx),
            cs::IDENTIFY_NON_CONFIGURED => ctx
                .non_configured()
                .then_some(Outcome::Reply(reply_code(cs::NON_CONFIGURED_SLAVE, 0))),
            cs::FASTSCAN => self.fastscan(word, d[5], d[6], d[7], ctx),
            _ if self.state == LssState::Configuration => self.configure(d, ctx),
            _ => None,
        }
    }

    /// Called when the stored configuration was written (or failed): the
    /// answer to the store request.
    pub const fn store_done(ok: bool) -> [u8; 8] {
        reply_code(cs::STORE, if ok { ERR_NONE } else { ERR_STORAGE })
    }

    /// Forgets a configured bit rate once it is activated.
    pub fn activated(&mut self) {
        self.pending_kbps = None;
    }

    fn switch_global(&mut self, mode: u8) -> Option<Outcome> {
        match (mode, self.state) {
            (0, LssState::Configuration) => {
                self.state = LssState::Waiting;
                self.fastscan_pos = 0;
                Some(Outcome::Waiting)
            }
            (1, _) => {
                self.state = LssState::Configuration;
                None
            }
            _ => None,
        }
    }

    fn selective(&mut self, c: u8, word: u32, ctx: &Context) -> Option<Outcome> {
        let k = c - cs::SELECTIVE_VENDOR;
        if self.state != LssState::Waiting {
            return None;
        }
        if k == 0 || k != self.selective {
            self.selective = 0;
        }
        if k != self.selective || ctx.identity[k as usize] != word {
            self.selective = 0;
            return None;
        }
        self.selective += 1;
        if self.selective < 4 {
            return None;
        }
        self.selective = 0;
        self.state = LssState::Configuration;
        Some(Outcome::Reply(reply_code(cs::SELECTIVE_ANSWER, 0)))
    }

    /// Identify remote slave: vendor and product exact, revision and
    /// serial inside `[low, high]`.
    fn identify(&mut self, c: u8, word: u32, ctx: &Context) -> Option<Outcome> {
        let k = c - cs::IDENTIFY_VENDOR;
        if k == 0 {
            self.remote = 0;
            self.remote_match = true;
        } else if k != self.remote {
            self.remote = 0;
            return None;
        }
        self.remote += 1;
        let [vendor, product, revision, serial] = ctx.identity;
        let ok = match k {
            0 => vendor == word,
            1 => product == word,
            2 | 4 => {
                self.remote_low = word;
                true
            }
            3 => (self.remote_low..=word).contains(&revision),
            _ => (self.remote_low..=word).contains(&serial),
        };
        self.remote_match &= ok;
        if k < 5 {
            return None;
        }
        self.remote = 0;
        self.remote_match
            .then_some(Outcome::Reply(reply_code(cs::IDENTIFY_SLAVE, 0)))
    }

    fn fastscan(&mut self, id: u32, bit: u8, sub: u8, next: u8, ctx: &Context) -> Option<Outcome> {
        if self.state != LssState::Waiting || !ctx.non_configured() {
            return None;
        }
        let ack = Some(Outcome::Reply(reply_code(cs::IDENTIFY_SLAVE, 0)));
        if bit == FASTSCAN_RESET {
            self.fastscan_pos = 0;
            return ack;
        }
        if bit > 31 || sub > 3 || next > 3 || sub != self.fastscan_pos {
            return None;
        }
        let mask = u32::MAX << bit;
        if ctx.identity[sub as usize] & mask != id & mask {
            return None;
        }
        self.fastscan_pos = next;
        if bit == 0 && next < sub {
            self.fastscan_pos = 0;
            self.state = LssState::Configuration;
        }
        ack
    }

    /// The services of configuration state.
    fn configure(&mut self, d: &[u8; 8], ctx: &Context) -> Option<Outcome> {
        let reply = |code| Some(Outcome::Reply(reply_code(d[0], code)));
        match d[0] {
            cs::CONFIGURE_NODE_ID => {
                let id = d[1];
                if (1..=127).contains(&id) || id == UNCONFIGURED {
                    Some(Outcome::NodeId(id))
                } else {
                    reply(ERR_NOT_SUPPORTED)
                }
            }
            cs::CONFIGURE_BIT_TIMING => match supported(d[1], d[2]) {
                Some(kbps) => {
                    self.pending_kbps = Some(kbps);
                    reply(ERR_NONE)
                }
                None => reply(ERR_NOT_SUPPORTED),
            },
            cs::ACTIVATE_BIT_TIMING => Some(Outcome::Activate {
                kbps: self.pending_kbps.unwrap_or(ctx.bit_rate_kbps),
                delay_ms: u16::from_le_bytes([d[1], d[2]]),
            }),
            cs::STORE => Some(Outcome::Store {
                kbps: self.pending_kbps.unwrap_or(ctx.bit_rate_kbps),
            }),
            cs::INQUIRE_VENDOR..=cs::INQUIRE_SERIAL => {
                let v = ctx.identity[(d[0] - cs::INQUIRE_VENDOR) as usize];
                Some(Outcome::Reply(reply_u32(d[0], v)))
            }
            cs::INQUIRE_NODE_ID => Some(Outcome::Reply(reply_code(d[0], ctx.active_node_id))),
            _ => None,
        }
    }
}

/// The bit rate of table `selector`, index `index`, if the board can run
/// it (see the module docs).
pub fn supported(selector: u8, index: u8) -> Option<u16> {
    if selector != 0 {
        return None;
    }
    let kbps = (*TABLE0_KBPS.get(index as usize)?)?;
    crate::config::BIT_RATES_KBPS
        .contains(&kbps)
        .then_some(kbps)
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
#[path = "lss_tests.rs"]
mod tests;
