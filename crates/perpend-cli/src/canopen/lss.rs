//! The LSS master (CiA 305 v3.0, layer setting services) on a [`Client`]:
//! requests on COB-ID 0x7E5, answers on 0x7E4, always 8 bytes (the
//! command specifiers are [`perpend_can::lss::cs`], the board's slave is
//! `perpend_can::lss`).
//!
//! | service | cs | answer |
//! |---|---|---|
//! | switch state global | 0x04 | none |
//! | switch state selective (vendor, product, revision, serial) | 0x40..0x43 | 0x44 |
//! | configure node-id / bit timing | 0x11 / 0x13 | same cs, error code |
//! | activate bit timing (switch delay) | 0x15 | none |
//! | store configuration | 0x17 | 0x17, error code |
//! | inquire vendor, product, revision, serial / node-id | 0x5A..0x5D / 0x5E | same cs, value |
//! | identify remote slave / non-configured remote slave | 0x46..0x4B / 0x4C | 0x4F / 0x50 from each |
//! | fastscan | 0x51 | 0x4F from each matching slave |
//!
//! Timing: CiA 305 fixes no timeout. Every request waits at most
//! [`Client::lss_timeout`] (50 ms unless `--timeout-ms` is given); a
//! confirmed service returns at its first answer, the services several
//! slaves may answer (fastscan, identify, the "exactly one node?" check)
//! wait the whole window, as CANopenNode's `CO_LSSmaster.c` does for
//! fastscan. Store configuration waits at least [`STORE_TIMEOUT`] (the
//! board writes flash before it answers).
//!
//! Fastscan ([`Client::lss_fastscan`]) follows CANopenNode's
//! `CO_LSSmaster_IdentifyFastscan` and python-canopen's `fast_scan`: a
//! reset (BitChecked 0x80) asks whether any non-configured slave waits;
//! then for each identity word, bits 31..0 one by one (a bit stays 0 when
//! some slave answers, else it is 1: the smallest identity is found
//! first), then a confirmation (BitChecked 0, LSSNext = next word; after
//! the serial, LSSNext 0 puts the one slave found into configuration
//! state). A word the caller expects (vendor, product, revision) is tried
//! first with one confirmation (CANopenNode's `CO_LSSmaster_FS_MATCH`)
//! and scanned only when no slave confirms it. Answers of a fastscan step
//! all look alike, so one arriving after its window would count for the
//! next step: the slave found is checked by inquiring its identity, and a
//! scan that does not check out is repeated ([`FASTSCAN_TRIES`]).
//!
//! Limits: table 0 bit rates only; answers that arrive after their window
//! are dropped before the next request.

use std::fmt;
use std::time::{Duration, Instant};

use perpend_can::lss::{cs, LssState, MASTER_ID, SLAVE_ID, TABLE0_KBPS, UNCONFIGURED};
use perpend_can::Frame;

use super::Client;
use crate::bus::BusError;

/// The LSS window of a request unless `--timeout-ms` is given.
pub const DEFAULT_TIMEOUT: Duration = Duration::from_millis(50);
/// The least time a store configuration may take.
pub const STORE_TIMEOUT: Duration = Duration::from_secs(1);
/// Fastscan BitChecked value that resets the scan.
const FASTSCAN_RESET: u8 = 0x80;
/// How often a fastscan that does not check out is tried.
pub const FASTSCAN_TRIES: u32 = 3;

/// An LSS address: object 0x1018 sub 1..4.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct Identity {
    /// Vendor-ID (sub 1).
    pub vendor: u32,
    /// Product code (sub 2).
    pub product: u32,
    /// Revision number (sub 3).
    pub revision: u32,
    /// Serial number (sub 4).
    pub serial: u32,
}

impl Identity {
    /// The four words in LSS order.
    pub const fn words(&self) -> [u32; 4] {
        [self.vendor, self.product, self.revision, self.serial]
    }

    /// From the four words in LSS order.
    pub const fn from_words(w: [u32; 4]) -> Self {
        Self {
            vendor: w[0],
            product: w[1],
            revision: w[2],
            serial: w[3],
        }
    }
}

impl fmt::Display for Identity {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "vendor {:#010x}, product {:#010x}, revision {:#010x}, serial {:#010x}",
            self.vendor, self.product, self.revision, self.serial
        )
    }
}

/// What went wrong in an LSS exchange.
#[derive(Debug)]
pub enum LssError {
    /// The bus failed.
    Bus(BusError),
    /// No slave answered in time.
    NoAnswer {
        /// The bus.
        bus: String,
        /// What was asked, in words.
        what: String,
        /// How long the master waited.
        waited: Duration,
        /// What to check.
        hint: String,
    },
    /// The slave answered with an error code.
    Refused {
        /// The bus.
        bus: String,
        /// The request's command specifier.
        cs: u8,
        /// The error code (byte 1).
        code: u8,
        /// The manufacturer-specific error (byte 2, for code 0xFF).
        spec: u8,
    },
    /// More slaves answered than the service allows.
    Several {
        /// The bus.
        bus: String,
        /// What was asked, in words.
        what: String,
        /// How many answered.
        count: usize,
        /// What to do.
        hint: String,
    },
    /// A value LSS cannot carry.
    Invalid(String),
}

/// The service of a command specifier, in words.
fn service(c: u8) -> &'static str {
    match c {
        cs::CONFIGURE_NODE_ID => "configure node-id",
        cs::CONFIGURE_BIT_TIMING => "configure bit timing",
        cs::STORE => "store configuration",
        _ => "the request",
    }
}

/// What an error code of a configure or store answer means (CiA 305
/// §5.3: 0 success, 0xFF manufacturer-specific with the code in byte 2).
pub fn refusal_words(c: u8, code: u8, spec: u8) -> String {
    match (c, code) {
        (_, 0xFF) => format!("manufacturer-specific error {spec:#04x}"),
        (cs::CONFIGURE_NODE_ID, 1) => "node-id out of range (1..127, or 0xFF: none)".into(),
        (cs::CONFIGURE_BIT_TIMING, 1) => {
            "bit timing not supported (perpend boards run 1000, 500, 250 and 125 kbit/s)".into()
        }
        (cs::STORE, 1) => "store configuration not supported".into(),
        (cs::STORE, 2) => "storage media access error (the flash write failed or \
                           another store is in progress: try again, then check the board)"
            .into(),
        _ => format!("error code {code} (reserved by CiA 305)"),
    }
}

impl fmt::Display for LssError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LssError::Bus(e) => e.fmt(f),
            LssError::NoAnswer {
                bus,
                what,
                waited,
                hint,
            } => write!(
                f,
                "no LSS answer on {bus} within {} ms ({what}): {hint}",
                waited.as_millis()
            ),
            LssError::Refused {
                bus,
                cs,
                code,
                spec,
            } => write!(
                f,
                "the node in LSS configuration state on {bus} refused {}: {}",
                service(*cs),
                refusal_words(*cs, *code, *spec)
            ),
            LssError::Several {
                bus,
                what,
                count,
                hint,
            } => write!(f, "{count} nodes on {bus} answered {what}: {hint}"),
            LssError::Invalid(s) => f.write_str(s),
        }
    }
}

/// The sentence is the whole message (no `source()`), as for
/// [`super::ClientError`].
impl std::error::Error for LssError {}

impl From<BusError> for LssError {
    fn from(e: BusError) -> Self {
        LssError::Bus(e)
    }
}

impl From<super::ClientError> for LssError {
    fn from(e: super::ClientError) -> Self {
        match e {
            super::ClientError::Bus(b) => LssError::Bus(b),
            e => LssError::Invalid(e.to_string()),
        }
    }
}

/// The table 0 index of `kbps` (CiA 305 Table 1).
///
/// # Errors
/// [`LssError::Invalid`] for a rate table 0 does not have.
pub fn table0_index(kbps: u16) -> Result<u8, LssError> {
    TABLE0_KBPS
        .iter()
        .position(|&r| r == Some(kbps))
        .map(|i| i as u8)
        .ok_or_else(|| {
            LssError::Invalid(format!(
                "{kbps} kbit/s is not in the CiA 305 bit timing table: use 1000, 800, 500, \
                 250, 125, 50, 20 or 10 (perpend boards run 1000, 500, 250 and 125)"
            ))
        })
}

/// A request: `cs`, then `bytes` from byte 1 on.
fn request(c: u8, bytes: &[u8]) -> [u8; 8] {
    let mut d = [0u8; 8];
    d[0] = c;
    for (i, b) in bytes.iter().take(7).enumerate() {
        d[1 + i] = *b;
    }
    d
}

/// A fastscan request.
fn fastscan_request(id: u32, bit: u8, sub: u8, next: u8) -> [u8; 8] {
    let b = id.to_le_bytes();
    [cs::FASTSCAN, b[0], b[1], b[2], b[3], bit, sub, next]
}

impl Client {
    /// Sends one LSS request (8 bytes on 0x7E5), after dropping the LSS
    /// answers still kept from earlier requests.
    ///
    /// # Errors
    /// [`LssError::Bus`].
    pub fn lss_send(&mut self, d: [u8; 8]) -> Result<(), LssError> {
        self.backlog.retain(|(_, f)| f.id != SLAVE_ID);
        Ok(self.bus.send(&Frame::new(MASTER_ID, &d))?)
    }

    /// Sends `d` and collects the answers whose first byte is `answer`:
    /// the first one only (`all` false), or every one within the window.
    ///
    /// # Errors
    /// [`LssError::Bus`].
    fn lss_exchange(
        &mut self,
        d: [u8; 8],
        answer: u8,
        all: bool,
        window: Duration,
    ) -> Result<Vec<[u8; 8]>, LssError> {
        self.lss_send(d)?;
        let end = Instant::now() + window;
        let mut got = Vec::new();
        loop {
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(got);
            }
            let f = self.wait_for(left, |f| {
                f.id == SLAVE_ID && f.len == 8 && !f.rtr && f.data[0] == answer
            })?;
            match f {
                Some(f) => got.push(f.data),
                None => return Ok(got),
            }
            if !all {
                return Ok(got);
            }
        }
    }

    /// The error for a request nobody answered.
    fn lss_silent(&self, what: &str, waited: Duration, hint: &str) -> LssError {
        LssError::NoAnswer {
            bus: self.bus_name().to_string(),
            what: what.to_string(),
            waited,
            hint: hint.to_string(),
        }
    }

    /// A confirmed request answered by one slave: its answer.
    fn lss_confirmed(&mut self, d: [u8; 8], what: &str) -> Result<[u8; 8], LssError> {
        let window = if d[0] == cs::STORE {
            self.lss_timeout.max(STORE_TIMEOUT)
        } else {
            self.lss_timeout
        };
        match self.lss_exchange(d, d[0], false, window)?.first() {
            Some(a) => Ok(*a),
            None => Err(self.lss_silent(
                what,
                window,
                "no node is in LSS configuration state (select one: --serial, or scan), \
                 or the bus or bit rate is wrong; a slow adapter needs a larger --timeout-ms",
            )),
        }
    }

    /// A configure or store request: `Ok` on error code 0.
    fn lss_configure(&mut self, d: [u8; 8]) -> Result<(), LssError> {
        let a = self.lss_confirmed(d, service(d[0]))?;
        if a[1] == 0 {
            return Ok(());
        }
        Err(LssError::Refused {
            bus: self.bus_name().to_string(),
            cs: d[0],
            code: a[1],
            spec: a[2],
        })
    }

    /// Switch state global: every slave to `state`.
    ///
    /// # Errors
    /// [`LssError::Bus`].
    pub fn lss_switch_global(&mut self, state: LssState) -> Result<(), LssError> {
        let mode = u8::from(state == LssState::Configuration);
        self.lss_send(request(cs::SWITCH_GLOBAL, &[mode]))
    }

    /// Switch state selective: the slave with identity `id` (all four
    /// words equal) enters configuration state; the others keep theirs.
    ///
    /// # Errors
    /// [`LssError::NoAnswer`] when no slave has that identity (or it is
    /// already in configuration state), bus errors.
    pub fn lss_switch_selective(&mut self, id: &Identity) -> Result<(), LssError> {
        let w = id.words();
        for (k, word) in w.iter().take(3).enumerate() {
            self.lss_send(request(cs::SELECTIVE_VENDOR + k as u8, &word.to_le_bytes()))?;
        }
        let d = request(cs::SELECTIVE_SERIAL, &w[3].to_le_bytes());
        let window = self.lss_timeout;
        if self
            .lss_exchange(d, cs::SELECTIVE_ANSWER, false, window)?
            .is_empty()
        {
            let hint = format!(
                "no node in LSS waiting state has {id}: check the serial (the board's label) \
                 and vendor/product/revision (`perpend node lss scan` lists non-configured \
                 nodes, `perpend node --node-id N info` shows a configured one's)"
            );
            return Err(self.lss_silent("switch state selective", window, &hint));
        }
        Ok(())
    }

    /// Configure node-id (1..127, or 0xFF: non-configured) of the slave(s)
    /// in configuration state; it becomes active at the next NMT reset
    /// (communication), or at once for a non-configured node switched back
    /// to waiting state.
    ///
    /// # Errors
    /// [`LssError::Refused`] with the slave's error code, no answer.
    pub fn lss_configure_node_id(&mut self, id: u8) -> Result<(), LssError> {
        self.lss_configure(request(cs::CONFIGURE_NODE_ID, &[id]))
    }

    /// Configure bit timing: `kbps` from CiA 305 table 0.
    ///
    /// # Errors
    /// [`LssError::Invalid`] for a rate not in table 0, the slave's
    /// refusal (the board: error 1 for 800, 50, 20 and 10 kbit/s).
    pub fn lss_configure_bit_timing(&mut self, kbps: u16) -> Result<(), LssError> {
        let index = table0_index(kbps)?;
        self.lss_configure(request(cs::CONFIGURE_BIT_TIMING, &[0, index]))
    }

    /// Activate bit timing: every slave in configuration state switches
    /// to its configured bit rate after `delay_ms` and stays silent for
    /// another `delay_ms` (CiA 305 §5.3.3). No answer.
    ///
    /// # Errors
    /// [`LssError::Bus`].
    pub fn lss_activate_bit_timing(&mut self, delay_ms: u16) -> Result<(), LssError> {
        self.lss_send(request(cs::ACTIVATE_BIT_TIMING, &delay_ms.to_le_bytes()))
    }

    /// Store configuration (node-id and bit timing) of the slave in
    /// configuration state.
    ///
    /// # Errors
    /// [`LssError::Refused`] (1 not supported, 2 storage media error).
    pub fn lss_store(&mut self) -> Result<(), LssError> {
        self.lss_configure(request(cs::STORE, &[]))
    }

    /// A configure or store request to every slave in configuration
    /// state, answers collected for the window (at least [`STORE_TIMEOUT`]
    /// for a store): the first refusal is the error. Identical answers of
    /// several slaves are one frame on a CAN bus (the virtual board's bus
    /// merges them too), so the answers do not count the slaves.
    fn lss_configure_all(&mut self, d: [u8; 8]) -> Result<(), LssError> {
        let window = if d[0] == cs::STORE {
            self.lss_timeout.max(STORE_TIMEOUT)
        } else {
            self.lss_timeout
        };
        let got = self.lss_exchange(d, d[0], true, window)?;
        if let Some(a) = got.iter().find(|a| a[1] != 0) {
            return Err(LssError::Refused {
                bus: self.bus_name().to_string(),
                cs: d[0],
                code: a[1],
                spec: a[2],
            });
        }
        if got.is_empty() {
            let hint = "no node is in LSS configuration state, or the bus or bit rate is wrong";
            return Err(self.lss_silent(service(d[0]), window, hint));
        }
        Ok(())
    }

    /// Configure bit timing of every slave in configuration state.
    ///
    /// # Errors
    /// As [`Client::lss_configure_bit_timing`] (any slave's refusal); no
    /// answer at all.
    pub fn lss_configure_bit_timing_all(&mut self, kbps: u16) -> Result<(), LssError> {
        let index = table0_index(kbps)?;
        self.lss_configure_all(request(cs::CONFIGURE_BIT_TIMING, &[0, index]))
    }

    /// Store configuration of every slave in configuration state.
    ///
    /// # Errors
    /// As [`Client::lss_store`] (any slave's refusal); no answer at all.
    pub fn lss_store_all(&mut self) -> Result<(), LssError> {
        self.lss_configure_all(request(cs::STORE, &[]))
    }

    /// Inquire: the value the (one) slave in configuration state answers
    /// to `c` (0x5A..0x5D: the identity word; 0x5E: the active node-id).
    ///
    /// # Errors
    /// [`LssError::NoAnswer`].
    pub fn lss_inquire(&mut self, c: u8) -> Result<u32, LssError> {
        let a = self.lss_confirmed(request(c, &[]), "inquire")?;
        Ok(u32::from_le_bytes([a[1], a[2], a[3], a[4]]))
    }

    /// Inquire `c` of every slave in configuration state: all the values
    /// answered within the window (slaves answering the same value merge
    /// into one frame on a CAN bus: inquire the serial to count them).
    ///
    /// # Errors
    /// [`LssError::Bus`].
    pub fn lss_inquire_all(&mut self, c: u8) -> Result<Vec<u32>, LssError> {
        let window = self.lss_timeout;
        let got = self.lss_exchange(request(c, &[]), c, true, window)?;
        Ok(got
            .iter()
            .map(|a| u32::from_le_bytes([a[1], a[2], a[3], a[4]]))
            .collect())
    }

    /// The identity of the slave in configuration state (four inquiries).
    ///
    /// # Errors
    /// [`LssError::NoAnswer`].
    pub fn lss_inquire_identity(&mut self) -> Result<Identity, LssError> {
        let mut w = [0u32; 4];
        for (k, v) in w.iter_mut().enumerate() {
            *v = self.lss_inquire(cs::INQUIRE_VENDOR + k as u8)?;
        }
        Ok(Identity::from_words(w))
    }

    /// The active node-id of the slave in configuration state (0xFF:
    /// non-configured).
    ///
    /// # Errors
    /// [`LssError::NoAnswer`].
    pub fn lss_inquire_node_id(&mut self) -> Result<u8, LssError> {
        Ok(self.lss_inquire(cs::INQUIRE_NODE_ID)? as u8)
    }

    /// Identify non-configured remote slave: how many answers came within
    /// the window (identical answers of several slaves merge into one
    /// frame on a CAN bus: more than 0 means at least one slave).
    ///
    /// # Errors
    /// [`LssError::Bus`].
    pub fn lss_identify_non_configured(&mut self) -> Result<usize, LssError> {
        let d = request(cs::IDENTIFY_NON_CONFIGURED, &[]);
        let window = self.lss_timeout;
        Ok(self
            .lss_exchange(d, cs::NON_CONFIGURED_SLAVE, true, window)?
            .len())
    }

    /// Identify remote slave: how many answers came from slaves with this
    /// vendor and product and a revision and serial inside the ranges
    /// (more than 0: at least one, identical answers merge on a CAN bus).
    ///
    /// # Errors
    /// [`LssError::Bus`].
    pub fn lss_identify_remote(
        &mut self,
        vendor: u32,
        product: u32,
        revision: (u32, u32),
        serial: (u32, u32),
    ) -> Result<usize, LssError> {
        let w = [vendor, product, revision.0, revision.1, serial.0];
        for (k, word) in w.iter().enumerate() {
            self.lss_send(request(cs::IDENTIFY_VENDOR + k as u8, &word.to_le_bytes()))?;
        }
        let d = request(cs::IDENTIFY_SERIAL_HIGH, &serial.1.to_le_bytes());
        let window = self.lss_timeout;
        Ok(self
            .lss_exchange(d, cs::IDENTIFY_SLAVE, true, window)?
            .len())
    }

    /// One fastscan step: whether any slave answered within the window.
    fn fastscan_step(&mut self, id: u32, bit: u8, sub: u8, next: u8) -> Result<bool, LssError> {
        let d = fastscan_request(id, bit, sub, next);
        let window = self.lss_timeout;
        Ok(!self
            .lss_exchange(d, cs::IDENTIFY_SLAVE, true, window)?
            .is_empty())
    }

    /// Scans identity word `sub`, bit 31 to 0; the smallest value among
    /// the slaves at this word.
    fn fastscan_word(&mut self, sub: u8) -> Result<u32, LssError> {
        let mut id = 0u32;
        for bit in (0..32u8).rev() {
            if !self.fastscan_step(id, bit, sub, sub)? {
                id |= 1 << bit;
            }
        }
        Ok(id)
    }

    /// Fastscan: finds one non-configured slave in waiting state and puts
    /// it into configuration state; `None` when none answers. `expect`:
    /// vendor, product and revision to try before scanning each (the
    /// serial is always scanned). The slave found is checked by inquiry
    /// (a late answer of another step would make a wrong bit): a scan that
    /// does not check out is repeated, at most [`FASTSCAN_TRIES`] times.
    ///
    /// # Errors
    /// [`LssError::NoAnswer`] when no try checks out (a node joined or
    /// left the bus meanwhile, answers later than the window), bus errors.
    pub fn lss_fastscan(
        &mut self,
        expect: Option<&Identity>,
    ) -> Result<Option<Identity>, LssError> {
        let mut tries = 0;
        loop {
            tries += 1;
            match self.fastscan_once(expect) {
                Err(LssError::NoAnswer { .. }) if tries < FASTSCAN_TRIES => {
                    // Only the slave being scanned can be in configuration
                    // state: back to waiting, let late answers pass.
                    self.lss_switch_global(LssState::Waiting)?;
                    self.lss_settle()?;
                }
                r => return r,
            }
        }
    }

    /// Waits a few windows so that late answers arrive (and are dropped at
    /// the next request).
    fn lss_settle(&mut self) -> Result<(), LssError> {
        let _ = self.wait_for(self.lss_timeout * 4, |_| false)?;
        Ok(())
    }

    /// One fastscan, checked.
    fn fastscan_once(&mut self, expect: Option<&Identity>) -> Result<Option<Identity>, LssError> {
        if !self.fastscan_step(0, FASTSCAN_RESET, 0, 0)? {
            return Ok(None);
        }
        let mut w = [0u32; 4];
        for sub in 0..4u8 {
            let next = (sub + 1) & 3;
            let guess = expect.map(|e| e.words()[sub as usize]).filter(|_| sub < 3);
            if let Some(g) = guess {
                if self.fastscan_step(g, 0, sub, next)? {
                    w[sub as usize] = g;
                    continue;
                }
            }
            w[sub as usize] = self.fastscan_word(sub)?;
            if !self.fastscan_step(w[sub as usize], 0, sub, next)? {
                return Err(self.fastscan_lost(&w[..=sub as usize]));
            }
        }
        // The slave found is in configuration state (with those found
        // before, when listing): one of them must answer each word.
        for (k, want) in w.iter().enumerate() {
            if !self
                .lss_inquire_all(cs::INQUIRE_VENDOR + k as u8)?
                .contains(want)
            {
                return Err(self.fastscan_lost(&w));
            }
        }
        Ok(Some(Identity::from_words(w)))
    }

    fn fastscan_lost(&self, words: &[u32]) -> LssError {
        let words: Vec<String> = words.iter().map(|x| format!("{x:#010x}")).collect();
        let hint = format!(
            "the node scanned ({} so far) did not check out {FASTSCAN_TRIES} times: nodes \
             joined or left the bus during the scan, or their answers come later than the \
             window; run the scan again with a larger --timeout-ms",
            words.join(", ")
        );
        self.lss_silent("fastscan", self.lss_timeout, &hint)
    }

    /// Every non-configured slave in waiting state, smallest identity
    /// first (at most `max`): each one found stays in configuration state
    /// (CiA 305: it then takes no part in fastscan) so that the next scan
    /// finds the next; at the end all are switched back to waiting state.
    /// A scan that does not check out starts the listing again.
    ///
    /// # Errors
    /// As [`Client::lss_fastscan`].
    pub fn lss_list_non_configured(
        &mut self,
        expect: Option<&Identity>,
        max: usize,
    ) -> Result<Vec<Identity>, LssError> {
        self.lss_list_non_configured_with(expect, max, &mut |_| {})
    }

    /// [`Client::lss_list_non_configured`], calling `found(n)` each time
    /// the listing has found its n-th node (for a progress line).
    ///
    /// # Errors
    /// As [`Client::lss_fastscan`].
    pub fn lss_list_non_configured_with(
        &mut self,
        expect: Option<&Identity>,
        max: usize,
        found: &mut dyn FnMut(usize),
    ) -> Result<Vec<Identity>, LssError> {
        let mut tries = 0;
        loop {
            tries += 1;
            self.lss_switch_global(LssState::Waiting)?;
            let r = self.list_once(expect, max, found);
            self.lss_switch_global(LssState::Waiting)?;
            match r {
                Err(LssError::NoAnswer { .. }) if tries < FASTSCAN_TRIES => self.lss_settle()?,
                r => return r,
            }
        }
    }

    fn list_once(
        &mut self,
        expect: Option<&Identity>,
        max: usize,
        on_found: &mut dyn FnMut(usize),
    ) -> Result<Vec<Identity>, LssError> {
        let mut found = Vec::new();
        while found.len() < max {
            match self.fastscan_once(expect)? {
                Some(id) => found.push(id),
                None => break,
            }
            on_found(found.len());
        }
        Ok(found)
    }
}

/// Whether `id` is a node-id LSS can configure (1..127, or 0xFF).
pub fn configurable_node_id(id: u8) -> bool {
    (1..=127).contains(&id) || id == UNCONFIGURED
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
#[path = "lss_tests.rs"]
mod tests;
