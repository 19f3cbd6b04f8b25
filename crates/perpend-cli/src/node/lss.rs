//! `perpend node lss`: the integrator's LSS master (CiA 305, protocol in
//! [`crate::canopen::lss`]): find the non-configured heads of a cell, give
//! them node-ids, change node-ids and bit rates, store.
//!
//! ```text
//! perpend node --bus BUS lss scan [--assign FIRST [--store]] [--json]   (alias fastscan)
//! perpend node --bus BUS lss inquire [--serial S | --node-id N] [--json]
//! perpend node --bus BUS lss set-node-id N [--serial S | --node-id OLD] [--store] [--reset]
//! perpend node --bus BUS lss set-bitrate KBPS [--serial S | --node-id N] [--store]
//! perpend node --bus BUS lss activate-bitrate --delay-ms D
//! perpend node --bus BUS lss store [--serial S | --node-id N]
//! ```
//!
//! One node is selected by switch state selective with its identity:
//! `--serial` (the label) with vendor, product and revision from
//! `--vendor/--product/--revision` or perpend's own (`Defaults::nominal`),
//! or `--node-id N` (the identity read from a configured node by SDO
//! 0x1018), or, with neither, the one node on the bus (more: refused).
//! `set-bitrate` and `store` without a selection address every node.
//! Every command leaves the nodes in LSS waiting state, except
//! `activate-bitrate` (the bus runs at another rate then; see its help).
//!
//! A new node-id takes effect at once for a non-configured node (it starts
//! with it when switched back to waiting state: its boot-up is awaited),
//! else at the node's next NMT reset communication (`--reset` sends it).
//!
//! Limits: CiA 305 bit timing table 0; a scan finds at most 127 nodes;
//! `activate-bitrate` does not re-open the adapter at the new rate.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{bail, Context as _, Result};
use perpend_can::lss::{cs, LssState, UNCONFIGURED};
use perpend_can::Defaults;
use serde_json::json;

use super::LinkArgs;
use crate::board::parse_serial;
use crate::canopen::lss::{configurable_node_id, Identity};
use crate::canopen::{Client, Nmt};

/// Arguments of `perpend node lss`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// What to do.
    #[command(subcommand)]
    pub cmd: Cmd,
}

/// The LSS subcommands.
#[derive(clap::Subcommand, Debug)]
pub enum Cmd {
    /// List every non-configured node by fastscan; --assign gives them node-ids.
    #[command(visible_alias = "fastscan")]
    Scan(ScanArgs),
    /// Identity and active node-id of one node.
    Inquire(InquireArgs),
    /// Give one node a node-id (1..127, or 0xFF: non-configured).
    SetNodeId(SetNodeIdArgs),
    /// Configure the bit rate [kbit/s] of one node, or of every node.
    SetBitrate(SetBitrateArgs),
    /// Every node switches to its configured bit rate (after --delay-ms).
    ActivateBitrate(ActivateArgs),
    /// Store the LSS configuration (node-id, bit rate) of one node, or of every node.
    Store(Select),
}

/// Options of `lss scan`.
#[derive(clap::Args, Debug)]
pub struct ScanArgs {
    /// Give the nodes found consecutive node-ids from FIRST on (skipping
    /// node-ids heard on the bus); each starts with it at once.
    #[arg(long, value_name = "FIRST", value_parser = crate::board::parse_node_id)]
    pub assign: Option<u8>,
    /// Store the node-ids given (else a power cycle forgets them).
    #[arg(long, requires = "assign")]
    pub store: bool,
    /// JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Which node: by identity (`--serial`, the label), or by its node-id
/// (`--node-id`, a configured node), or the only one on the bus.
#[derive(clap::Args, Debug, Default)]
pub struct Select {
    /// Serial number (0x1018 sub 4, the board's label), decimal or 0x hex.
    #[arg(long, value_parser = parse_serial)]
    pub serial: Option<u32>,
    /// Vendor-ID (0x1018 sub 1; default: perpend's).
    #[arg(long, value_parser = parse_serial, requires = "serial")]
    pub vendor: Option<u32>,
    /// Product code (0x1018 sub 2; default: perpend's).
    #[arg(long, value_parser = parse_serial, requires = "serial")]
    pub product: Option<u32>,
    /// Revision number (0x1018 sub 3; default: perpend's).
    #[arg(long, value_parser = parse_serial, requires = "serial")]
    pub revision: Option<u32>,
}

/// Options of `lss inquire`.
#[derive(clap::Args, Debug)]
pub struct InquireArgs {
    /// The node.
    #[command(flatten)]
    pub select: Select,
    /// JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Options of `lss set-node-id`.
#[derive(clap::Args, Debug)]
pub struct SetNodeIdArgs {
    /// The new node-id: 1..127, or 0xFF (non-configured), decimal or 0x hex.
    #[arg(value_name = "N", value_parser = crate::board::parse_node_id)]
    pub new_id: u8,
    /// The node.
    #[command(flatten)]
    pub select: Select,
    /// Store it (LSS store configuration), else a power cycle forgets it.
    #[arg(long)]
    pub store: bool,
    /// Send NMT reset communication to a configured node afterwards and
    /// wait for its boot-up with the new node-id.
    #[arg(long)]
    pub reset: bool,
}

/// Options of `lss set-bitrate`.
#[derive(clap::Args, Debug)]
pub struct SetBitrateArgs {
    /// Bit rate [kbit/s] of CiA 305 table 0: 1000, 800, 500, 250, 125, 50,
    /// 20, 10 (perpend boards run 1000, 500, 250 and 125).
    pub kbps: u16,
    /// The node (default: every node).
    #[command(flatten)]
    pub select: Select,
    /// Store it (LSS store configuration): the board starts with it.
    #[arg(long)]
    pub store: bool,
}

/// Options of `lss activate-bitrate`.
#[derive(clap::Args, Debug)]
pub struct ActivateArgs {
    /// Switch delay [ms]: every node stops sending, switches after D and
    /// starts sending after another D.
    #[arg(long, default_value_t = 100)]
    pub delay_ms: u16,
}

/// The perpend identity: vendor, product, revision of `Defaults::nominal`.
pub fn perpend_identity(serial: u32) -> Identity {
    let i = Defaults::nominal().identity;
    Identity {
        vendor: i.vendor_id,
        product: i.product_code,
        revision: i.revision,
        serial,
    }
}

/// Runs `perpend node lss`.
///
/// # Errors
/// Everything that went wrong, in sentences.
pub fn run(link: &LinkArgs, a: &Args, cancel: &AtomicBool) -> Result<()> {
    // a --node-id the command refuses is said before the bus is opened
    if let (Some(n), Cmd::Scan(_) | Cmd::ActivateBitrate(_)) = (link.node_id, &a.cmd) {
        let what = match a.cmd {
            Cmd::Scan(_) => "lss scan addresses every non-configured node on the bus",
            _ => "lss activate-bitrate switches every node on the bus",
        };
        bail!("{what}: leave out --node-id {n}");
    }
    let mut c = link.client()?;
    let r = match &a.cmd {
        Cmd::Scan(x) => scan(&mut c, link, x, cancel),
        Cmd::Inquire(x) => inquire(&mut c, link, x),
        Cmd::SetNodeId(x) => set_node_id(&mut c, link, x),
        Cmd::SetBitrate(x) => set_bitrate(&mut c, link, x),
        Cmd::ActivateBitrate(x) => activate(&mut c, link, x),
        Cmd::Store(x) => store(&mut c, link, x),
    };
    if r.is_err() && !matches!(a.cmd, Cmd::ActivateBitrate(_)) {
        // Leave no node in configuration state behind (best effort: the
        // error says what went wrong).
        let _ = c.lss_switch_global(LssState::Waiting);
    }
    r
}

/// One node in configuration state, alone.
struct Selected {
    identity: Identity,
    /// Its active node-id (0xFF: non-configured).
    node_id: u8,
    /// How it was selected, in words.
    how: String,
}

/// Puts one node into configuration state, all others in waiting state.
fn select(c: &mut Client, link: &LinkArgs, s: &Select) -> Result<Selected> {
    c.lss_switch_global(LssState::Waiting)?;
    let bus = c.bus_name().to_string();
    let how = if let Some(serial) = s.serial {
        let d = perpend_identity(serial);
        let id = Identity {
            vendor: s.vendor.unwrap_or(d.vendor),
            product: s.product.unwrap_or(d.product),
            revision: s.revision.unwrap_or(d.revision),
            serial,
        };
        c.lss_switch_selective(&id)?;
        format!("serial {serial:#010x}")
    } else if let Some(n) = link.node_id {
        let mut w = [0u32; 4];
        for (k, v) in w.iter_mut().enumerate() {
            *v = c.read_u32(n, 0x1018, k as u8 + 1).with_context(|| {
                format!(
                    "cannot read the identity (0x1018) of node {n} on {bus} to select it: \
                     a non-configured node has no SDO, select it with --serial S"
                )
            })?;
        }
        c.lss_switch_selective(&Identity::from_words(w))?;
        format!("node-id {n}")
    } else {
        only_node(c)?;
        "the only node on the bus".to_string()
    };
    let identity = c.lss_inquire_identity()?;
    let node_id = c.lss_inquire_node_id()?;
    Ok(Selected {
        identity,
        node_id,
        how,
    })
}

/// The error when no node answers an inquiry of all.
fn nobody(c: &Client) -> anyhow::Error {
    anyhow::anyhow!(
        "no node answered LSS on {} within {} ms: is the bus and bit rate right and a board \
         powered? (a slow adapter needs a larger --timeout-ms)",
        c.bus_name(),
        c.lss_timeout.as_millis()
    )
}

/// Switch state global to configuration, refused unless exactly one node
/// answers (its serial).
fn only_node(c: &mut Client) -> Result<()> {
    c.lss_switch_global(LssState::Configuration)?;
    let serials = c.lss_inquire_all(cs::INQUIRE_SERIAL)?;
    let bus = c.bus_name().to_string();
    match serials.as_slice() {
        [_] => Ok(()),
        [] => Err(nobody(c)),
        many => {
            let list: Vec<String> = many.iter().map(|s| format!("{s:#010x}")).collect();
            bail!(
                "{} nodes answered LSS on {bus} (serials {}): select one with --serial S \
                 (or --node-id N for a configured one)",
                many.len(),
                list.join(", ")
            )
        }
    }
}

/// `serial 0x.. (vendor …)` line of a node.
fn identity_line(id: &Identity) -> String {
    format!(
        "serial {:#010x}  vendor {:#010x}  product {:#010x}  revision {:#010x}",
        id.serial, id.vendor, id.product, id.revision
    )
}

fn identity_json(id: &Identity) -> serde_json::Value {
    json!({"vendor": id.vendor, "product": id.product, "revision": id.revision,
           "serial": id.serial})
}

/// `lss scan`: list, or assign node-ids.
fn scan(c: &mut Client, link: &LinkArgs, a: &ScanArgs, cancel: &AtomicBool) -> Result<()> {
    if let Some(n) = link.node_id {
        bail!("lss scan addresses every non-configured node on the bus: leave out --node-id {n}");
    }
    let expect = perpend_identity(0);
    let bus = c.bus_name().to_string();
    // about 2.3 s a node at the default timeout: a line on a terminal
    let ticker = crate::progress::Ticker::start(&format!("lss scan of {bus}"));
    let found: Vec<(Identity, Option<u8>)> = match a.assign {
        None => c
            .lss_list_non_configured_with(Some(&expect), 127, &mut |n| {
                ticker.note(format!("{n} non-configured node(s) found"));
            })?
            .into_iter()
            .map(|i| (i, None))
            .collect(),
        Some(first) => assign(c, first, a.store, cancel, &ticker)?,
    };
    drop(ticker);
    if a.json {
        let nodes: Vec<_> = found
            .iter()
            .map(|(i, n)| {
                let mut v = identity_json(i);
                v["node_id"] = json!(n);
                v
            })
            .collect();
        let v = json!({"bus": bus, "stored": a.store, "nodes": nodes});
        println!("{}", crate::schema::tagged(crate::schema::LSS_SCAN, &v));
        return Ok(());
    }
    if found.is_empty() {
        println!(
            "no non-configured node on {bus} (configured nodes take no part in fastscan: \
             `perpend node --bus {bus} --node-id N info`, or `lss inquire --node-id N`)"
        );
        return Ok(());
    }
    println!("{} non-configured node(s) on {bus}:", found.len());
    for (i, n) in &found {
        match n {
            None => println!("  {}", identity_line(i)),
            Some(n) => println!("  serial {:#010x} -> node-id {n}", i.serial),
        }
    }
    if a.assign.is_none() {
        println!("give them node-ids: perpend node --bus {bus} lss scan --assign FIRST --store");
    } else if !a.store {
        println!("not stored: a power cycle makes them non-configured again (add --store)");
    }
    Ok(())
}

/// The next node-id from `from` on that no node on the bus was heard with.
fn next_free(c: &Client, from: u8) -> Option<u8> {
    let heard = c.heard_nodes();
    (from..=127).find(|n| !heard.contains(n))
}

/// Fastscan one node after the other, each given the next free node-id,
/// stored if asked, switched back to waiting state (it starts at once).
fn assign(
    c: &mut Client,
    first: u8,
    store: bool,
    cancel: &AtomicBool,
    ticker: &crate::progress::Ticker,
) -> Result<Vec<(Identity, Option<u8>)>> {
    if first == UNCONFIGURED {
        bail!("--assign {first}: the first node-id must be 1..127");
    }
    let bus = c.bus_name().to_string();
    let expect = perpend_identity(0);
    c.lss_switch_global(LssState::Waiting)?;
    let mut done = Vec::new();
    let mut from = first;
    while !cancel.load(Ordering::SeqCst) {
        let Some(id) = c.lss_fastscan(Some(&expect))? else {
            break;
        };
        let Some(n) = next_free(c, from) else {
            bail!(
                "no free node-id left from {first} to 127 on {bus} for serial {:#010x} \
                 ({} given): it stays non-configured; start lower with --assign",
                id.serial,
                done.len()
            );
        };
        c.lss_configure_node_id(n)?;
        if store {
            c.lss_store()?;
        }
        c.lss_switch_global(LssState::Waiting)?;
        c.wait_bootup(n, Duration::from_secs(2)).with_context(|| {
            format!(
                "serial {:#010x} was given node-id {n} on {bus} but sent no boot-up",
                id.serial
            )
        })?;
        done.push((id, Some(n)));
        ticker.note(format!("{} node(s) given node-ids", done.len()));
        from = n.saturating_add(1);
    }
    if cancel.load(Ordering::SeqCst) {
        bail!(
            "interrupted on {bus} after {} node(s); nodes not reached stay non-configured",
            done.len()
        );
    }
    Ok(done)
}

/// `lss inquire`.
fn inquire(c: &mut Client, link: &LinkArgs, a: &InquireArgs) -> Result<()> {
    let s = select(c, link, &a.select)?;
    c.lss_switch_global(LssState::Waiting)?;
    let configured = s.node_id != UNCONFIGURED;
    if a.json {
        let mut v = identity_json(&s.identity);
        v["bus"] = json!(c.bus_name());
        v["node_id"] = json!(configured.then_some(s.node_id));
        println!("{}", crate::schema::tagged(crate::schema::LSS_INQUIRE, &v));
        return Ok(());
    }
    println!("{} ({}):", c.bus_name(), s.how);
    println!("  {}", identity_line(&s.identity));
    if configured {
        println!("  node-id {} (active)", s.node_id);
    } else {
        println!("  non-configured (node-id 0xFF): give it one with lss set-node-id N");
    }
    Ok(())
}

/// `lss set-node-id`.
fn set_node_id(c: &mut Client, link: &LinkArgs, a: &SetNodeIdArgs) -> Result<()> {
    let new = a.new_id;
    if !configurable_node_id(new) {
        bail!("node-id {new}: expected 1..127 or 0xFF");
    }
    let s = select(c, link, &a.select)?;
    c.lss_configure_node_id(new)?;
    if a.store {
        c.lss_store()?;
    }
    c.lss_switch_global(LssState::Waiting)?;
    let bus = c.bus_name().to_string();
    let stored = if a.store { "stored" } else { "not stored" };
    println!(
        "serial {:#010x} on {bus}: node-id {} -> {new} ({stored})",
        s.identity.serial,
        id_words(s.node_id)
    );
    if s.node_id == UNCONFIGURED {
        if new != UNCONFIGURED {
            c.wait_bootup(new, Duration::from_secs(2))
                .with_context(|| format!("node {new} on {bus} sent no boot-up"))?;
            println!("node {new} started (boot-up received)");
        }
    } else if a.reset {
        c.nmt(s.node_id, Nmt::ResetComm)?;
        if new != UNCONFIGURED {
            c.wait_bootup(new, Duration::from_secs(5))?;
            println!("reset communication: node {new} started (boot-up received)");
        } else {
            println!("reset communication: the node is non-configured now (silent)");
        }
    } else {
        println!(
            "it takes effect at the node's next reset communication: add --reset, or \
             `perpend node --bus {bus} --node-id {} nmt reset-comm` (the boot-up then \
             comes from node {})",
            s.node_id,
            id_words(new)
        );
    }
    if !a.store {
        println!("a power cycle or NMT reset node forgets it: add --store to keep it");
    }
    Ok(())
}

/// A node-id in words.
fn id_words(n: u8) -> String {
    if n == UNCONFIGURED {
        "none (0xFF)".into()
    } else {
        n.to_string()
    }
}

/// Selects one node (`Ok(Ok(_))`), or puts every node into configuration
/// state (no selection): `Ok(Err(n))`, `n` nodes (counted by their
/// serials: identical answers would merge into one frame on the bus).
fn select_or_all(
    c: &mut Client,
    link: &LinkArgs,
    s: &Select,
) -> Result<std::result::Result<Selected, usize>> {
    if s.serial.is_some() || link.node_id.is_some() {
        return Ok(Ok(select(c, link, s)?));
    }
    c.lss_switch_global(LssState::Configuration)?;
    let n = c.lss_inquire_all(cs::INQUIRE_SERIAL)?.len();
    if n == 0 {
        return Err(nobody(c));
    }
    Ok(Err(n))
}

/// `lss set-bitrate`.
fn set_bitrate(c: &mut Client, link: &LinkArgs, a: &SetBitrateArgs) -> Result<()> {
    let who = match select_or_all(c, link, &a.select)? {
        Ok(s) => {
            c.lss_configure_bit_timing(a.kbps)?;
            if a.store {
                c.lss_store()?;
            }
            format!("serial {:#010x}", s.identity.serial)
        }
        Err(n) => {
            c.lss_configure_bit_timing_all(a.kbps)?;
            if a.store {
                c.lss_store_all()?;
            }
            format!("{n} node(s)")
        }
    };
    c.lss_switch_global(LssState::Waiting)?;
    let bus = c.bus_name();
    let stored = if a.store {
        "stored: they start with it after a reset"
    } else {
        "not stored"
    };
    println!(
        "{who} on {bus}: bit rate {} kbit/s configured ({stored})",
        a.kbps
    );
    println!(
        "switch the whole bus together: perpend node --bus {bus} lss activate-bitrate \
         --delay-ms 100"
    );
    Ok(())
}

/// `lss activate-bitrate`: global, every node switches.
fn activate(c: &mut Client, link: &LinkArgs, a: &ActivateArgs) -> Result<()> {
    if let Some(n) = link.node_id {
        bail!("lss activate-bitrate switches every node on the bus: leave out --node-id {n}");
    }
    c.lss_switch_global(LssState::Configuration)?;
    c.lss_activate_bit_timing(a.delay_ms)?;
    std::thread::sleep(Duration::from_millis(2 * u64::from(a.delay_ms)));
    let bus = c.bus_name();
    println!(
        "every node on {bus} switched to the bit rate of lss set-bitrate after {} ms (nodes \
         without one keep theirs); they are in LSS configuration state. Set the adapter to \
         the new rate (slcan: --bitrate KBPS; SocketCAN: ip link set … bitrate), then \
         `perpend node --bus {bus} --bitrate KBPS lss store` keeps it, or any lss command \
         returns them to waiting state",
        a.delay_ms
    );
    Ok(())
}

/// `lss store`.
fn store(c: &mut Client, link: &LinkArgs, s: &Select) -> Result<()> {
    let who = match select_or_all(c, link, s)? {
        Ok(s) => {
            c.lss_store()?;
            format!("serial {:#010x}", s.identity.serial)
        }
        Err(n) => {
            c.lss_store_all()?;
            format!("{n} node(s)")
        }
    };
    c.lss_switch_global(LssState::Waiting)?;
    println!(
        "{who} on {}: LSS configuration (node-id, bit rate) stored",
        c.bus_name()
    );
    Ok(())
}
