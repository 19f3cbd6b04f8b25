//! `perpend node pdo`: show, map, switch off and on the board's transmit
//! PDOs (CiA 301 §7.5.2.35-38: 0x1800+k communication, 0x1A00+k mapping).
//!
//! `map` follows the order CiA 301 prescribes and the board enforces:
//! invalidate the PDO (COB-ID bit 31), clear the mapping (sub 0 = 0), write
//! the entries, write their count, set the transmission type, inhibit time,
//! event timer and SYNC start value, and make the PDO valid again with bit
//! 30 set (the board answers no remote frames and refuses a valid COB-ID
//! without it). Before anything is sent, each object is checked against
//! the board's dictionary ([`perpend_can::od`], the table its EDS is written
//! from): it must exist, be PDO-mappable, and all of them must fit the
//! frame's 64 bits. Every step is read back at the end; if a step fails,
//! the PDO's previous parameters are written back (first cause first, then
//! what the restore did). `--store` saves the communication parameters
//! (0x1010 sub 2) so the mapping survives a reset; without it the mapping
//! lasts until the next reset.
//!
//! Limits: the RPDO's mapping is fixed (0x1600 is const), so only TPDOs
//! are mapped here; objects are named by index and sub-index.

use std::time::Duration;

use anyhow::{bail, Context as _, Result};
use perpend_can::od::{self, SAVE_SIGNATURE};
use serde_json::json;

use super::{mapping, Node};
use crate::canopen::ClientError;

/// How long a store may take (the board writes flash before it answers).
const STORE_TIMEOUT: Duration = Duration::from_secs(5);

/// Options of `pdo`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// What to do.
    #[command(subcommand)]
    pub cmd: Cmd,
}

/// The `pdo` subcommands.
#[derive(clap::Subcommand, Debug)]
pub enum Cmd {
    /// Every PDO's COB-ID, timing and mapped objects in words.
    Show {
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Map objects into TPDO N (1..4), in order, and set its timing.
    Map(MapArgs),
    /// Switch TPDO N off (COB-ID bit 31).
    Off(OnOff),
    /// Switch TPDO N on again with its mapping and timing.
    On(OnOff),
}

/// Options of `pdo map`.
#[derive(clap::Args, Debug)]
pub struct MapArgs {
    /// The TPDO, 1..4.
    pub number: u8,
    /// The objects, `INDEX:SUB` (e.g. `0x2003:1 0x2003:2`), at most 64 bits.
    #[arg(required = true, num_args = 1..)]
    pub objects: Vec<String>,
    /// Transmission type: 0 acyclic synchronous, 1..240 every n-th SYNC,
    /// 254/255 event-driven (default: keep the PDO's).
    #[arg(long = "type")]
    pub transmission: Option<u8>,
    /// Event timer for types 254/255 [ms] (0: off).
    #[arg(long)]
    pub event_ms: Option<u16>,
    /// Inhibit time [ms, in steps of 0.1].
    #[arg(long)]
    pub inhibit_ms: Option<f64>,
    /// SYNC start value (0x1019 > 0: the SYNC counter that starts it).
    #[arg(long)]
    pub sync_start: Option<u8>,
    /// Save the communication parameters (0x1010 sub 2): the mapping
    /// survives a reset.
    #[arg(long)]
    pub store: bool,
}

/// Options of `pdo off` / `pdo on`.
#[derive(clap::Args, Debug)]
pub struct OnOff {
    /// The TPDO, 1..4.
    pub number: u8,
    /// Save the communication parameters (0x1010 sub 2).
    #[arg(long)]
    pub store: bool,
}

/// One TPDO's writable parameters, as read from or written to the board.
#[derive(Debug, Clone, PartialEq)]
struct Params {
    cob: u32,
    transmission: u32,
    inhibit: u32,
    event: u32,
    start: u32,
    mapped: Vec<u32>,
}

/// The 0-based TPDO of a 1-based number.
fn tpdo_index(n: u8) -> Result<u16> {
    if n == 0 || n as usize > od::TPDOS {
        bail!(
            "TPDO {n} does not exist: the board has TPDO 1..{}",
            od::TPDOS
        );
    }
    Ok(n as u16 - 1)
}

/// Parses `INDEX:SUB` (hex with `0x` or decimal, `.` also accepted) and
/// checks it against the dictionary: the mapping entry value.
fn parse_object(s: &str) -> Result<u32> {
    let (i, sub) = s
        .split_once([':', '.'])
        .with_context(|| format!("{s:?}: give an object as INDEX:SUB, e.g. 0x2003:1"))?;
    let num = |t: &str| -> Option<u32> {
        let t = t.trim();
        match t.strip_prefix("0x").or_else(|| t.strip_prefix("0X")) {
            Some(h) => u32::from_str_radix(h, 16).ok(),
            None => t.parse().ok(),
        }
    };
    let (Some(index), Some(sub)) = (num(i), num(sub)) else {
        bail!("{s:?}: INDEX and SUB must be numbers (0x hex or decimal)");
    };
    let (Ok(index), Ok(sub)) = (u16::try_from(index), u8::try_from(sub)) else {
        bail!("{s:?}: the index is 16 bits and the sub-index 8");
    };
    let e = match od::find(index, sub) {
        Ok((_, e)) => e,
        Err(_) => bail!("{index:#06x} sub {sub} is not in the board's dictionary (`perpend node sdo list` lists it)"),
    };
    if !e.pdo {
        bail!(
            "{index:#06x} sub {sub} ({}) cannot be mapped into a PDO (PDOMapping=0 in the EDS)",
            e.name
        );
    }
    Ok(od::mapping(index, sub, e.ty.bits()))
}

/// The mapping entries of `objects`, checked to fit one frame.
fn entries(objects: &[String]) -> Result<Vec<u32>> {
    let v: Vec<u32> = objects
        .iter()
        .map(|o| parse_object(o))
        .collect::<Result<_>>()?;
    let bits: u32 = v.iter().map(|m| m & 0xFF).sum();
    if bits > 64 {
        bail!("these objects take {bits} bits; a CAN frame carries 64");
    }
    if v.len() > od::MAX_MAPPED {
        bail!(
            "{} objects; a TPDO maps at most {}",
            v.len(),
            od::MAX_MAPPED
        );
    }
    Ok(v)
}

impl Params {
    /// Reads TPDO `k` (0-based).
    fn read(node: &mut Node, k: u16) -> Result<Self, ClientError> {
        let (c, id) = (&mut node.client, node.id);
        let (comm, map) = (0x1800 + k, 0x1A00 + k);
        let n = c.read_u32(id, map, 0)?.min(od::MAX_MAPPED as u32) as u8;
        let mut mapped = Vec::new();
        for s in 1..=n {
            mapped.push(c.read_u32(id, map, s)?);
        }
        Ok(Self {
            cob: c.read_u32(id, comm, 1)?,
            transmission: c.read_u32(id, comm, 2)?,
            inhibit: c.read_u32(id, comm, 3)?,
            event: c.read_u32(id, comm, 5)?,
            start: c.read_u32(id, comm, 6)?,
            mapped,
        })
    }

    /// Writes these parameters into TPDO `k` in the CiA 301 order; the PDO
    /// ends valid or not as `self.cob` says.
    fn write(&self, node: &mut Node, k: u16) -> Result<(), ClientError> {
        let (c, id) = (&mut node.client, node.id);
        let (comm, map) = (0x1800 + k, 0x1A00 + k);
        c.write_u32(id, comm, 1, self.cob | 0x8000_0000)?;
        c.download(id, map, 0, &[0])?;
        for (s, m) in self.mapped.iter().enumerate() {
            c.write_u32(id, map, s as u8 + 1, *m)?;
        }
        c.download(id, map, 0, &[self.mapped.len() as u8])?;
        c.download(id, comm, 2, &[self.transmission as u8])?;
        c.download(id, comm, 3, &(self.inhibit as u16).to_le_bytes())?;
        c.download(id, comm, 5, &(self.event as u16).to_le_bytes())?;
        c.download(id, comm, 6, &[self.start as u8])?;
        if self.cob & 0x8000_0000 == 0 {
            c.write_u32(id, comm, 1, self.cob | 0x4000_0000)?;
        }
        Ok(())
    }
}

/// Writes `new` into TPDO `k` over `old`, checks it by reading back; on a
/// failure writes `old` back and says both.
fn apply(node: &mut Node, k: u16, old: &Params, new: &Params) -> Result<()> {
    let done = new
        .write(node, k)
        .map_err(anyhow::Error::from)
        .and_then(|()| {
            let back = Params::read(node, k)?;
            if back != *new {
                bail!("TPDO {} reads back {back:?}, not what was written", k + 1);
            }
            Ok(())
        });
    let Err(first) = done else {
        return Ok(());
    };
    let restore = match old.write(node, k) {
        Ok(()) => "its previous parameters were written back".to_string(),
        Err(e) => format!("writing its previous parameters back failed too: {e}"),
    };
    Err(first.context(format!(
        "{}: TPDO {} not changed; {restore}",
        node.name(),
        k + 1
    )))
}

/// Saves the communication parameters (0x1010 sub 2).
fn store(node: &mut Node) -> Result<()> {
    let save = SAVE_SIGNATURE.to_le_bytes();
    node.client
        .download_timeout(node.id, 0x1010, 2, &save, STORE_TIMEOUT)
        .with_context(|| {
            format!(
                "{}: the store (0x1010 sub 2) failed; the change holds until the next reset",
                node.name()
            )
        })?;
    Ok(())
}

/// `pdo map`.
fn map(node: &mut Node, a: &MapArgs) -> Result<()> {
    let k = tpdo_index(a.number)?;
    let mapped = entries(&a.objects)?;
    let inhibit = match a.inhibit_ms {
        Some(ms) if !(0.0..=6553.5).contains(&ms) => bail!("--inhibit-ms {ms}: 0..6553.5 ms"),
        Some(ms) => Some((ms * 10.0).round() as u32),
        None => None,
    };
    if let Some(t) = a.transmission {
        if (241..=253).contains(&t) {
            bail!("--type {t}: 0..240 (synchronous) or 254/255 (event-driven); 241..253 are reserved or remote-request types the board does not offer");
        }
    }
    node.hello()?;
    let old = Params::read(node, k)?;
    let new = Params {
        cob: (old.cob & !0x8000_0000) | 0x4000_0000,
        transmission: a.transmission.map_or(old.transmission, u32::from),
        inhibit: inhibit.unwrap_or(old.inhibit),
        event: a.event_ms.map_or(old.event, u32::from),
        start: a.sync_start.map_or(old.start, u32::from),
        mapped,
    };
    apply(node, k, &old, &new)?;
    if a.store {
        store(node)?;
    }
    report(node, a.number, a.store)
}

/// `pdo off` / `pdo on`.
fn switch(node: &mut Node, a: &OnOff, on: bool) -> Result<()> {
    let k = tpdo_index(a.number)?;
    node.hello()?;
    let old = Params::read(node, k)?;
    if on && old.mapped.is_empty() {
        bail!(
            "{}: TPDO {} maps nothing: map objects first (`pdo map {} OBJ…`)",
            node.name(),
            a.number,
            a.number
        );
    }
    let mut new = old.clone();
    new.cob = if on {
        (old.cob & !0x8000_0000) | 0x4000_0000
    } else {
        old.cob | 0x8000_0000
    };
    apply(node, k, &old, &new)?;
    if a.store {
        store(node)?;
    }
    report(node, a.number, a.store)
}

/// Prints the PDO as it now is on the board.
fn report(node: &mut Node, number: u8, stored: bool) -> Result<()> {
    let pdos = mapping::read(node)?;
    let one = pdos
        .as_array()
        .and_then(|v| v.get(number as usize - 1))
        .cloned()
        .unwrap_or_default();
    println!(
        "{}: TPDO {number} {}",
        node.name(),
        if stored {
            "set and stored (0x1010 sub 2)"
        } else {
            "set (until the next reset; --store keeps it)"
        }
    );
    for l in mapping::lines(&json!([one])) {
        println!("  {l}");
    }
    Ok(())
}

/// Runs `perpend node pdo`.
///
/// # Errors
/// A bad object or TPDO number (nothing sent), client errors (the PDO
/// put back as it was).
pub fn run(node: &mut Node, a: &Args) -> Result<()> {
    match &a.cmd {
        Cmd::Show { json } => {
            node.hello()?;
            let pdos = mapping::read(node)?;
            if *json {
                let v = json!({"node_id": node.id, "pdos": pdos});
                println!("{}", crate::schema::tagged(crate::schema::PDO, &v));
            } else {
                println!("{}", node.name());
                for l in mapping::lines(&pdos) {
                    println!("  {l}");
                }
            }
            Ok(())
        }
        Cmd::Map(m) => map(node, m),
        Cmd::Off(x) => switch(node, x, false),
        Cmd::On(x) => switch(node, x, true),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn objects_are_checked_against_the_dictionary() {
        assert_eq!(
            parse_object("0x2003:1").unwrap(),
            od::mapping(0x2003, 1, 32)
        );
        assert_eq!(
            parse_object("0x2002.2").unwrap(),
            od::mapping(0x2002, 2, 32)
        );
        assert_eq!(parse_object("8199:0").unwrap(), od::mapping(0x2007, 0, 32));
        let e = |s: &str| parse_object(s).unwrap_err().to_string();
        assert!(e("0x2003").contains("INDEX:SUB"));
        assert!(e("0x6000:1").contains("not in the board's dictionary"));
        assert!(e("0x1017:0").contains("cannot be mapped"));
        assert!(e("0x2003:x").contains("must be numbers"));
        assert!(e("0x12345:0").contains("16 bits"));
        let three: Vec<String> = ["0x2001:1", "0x2001:2", "0x2001:3"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        assert!(entries(&three).unwrap_err().to_string().contains("96 bits"));
        assert!(tpdo_index(5).is_err() && tpdo_index(0).is_err());
    }
}
