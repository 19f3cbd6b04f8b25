//! `perpend node lss` end to end against a cell of virtual boards on one
//! bus (slcan/TCP on loopback): two configured heads (`--serial S:NODEID`)
//! and one non-configured. The fastscan finds exactly the non-configured
//! one, `--assign` gives it a node-id and stores it, an NMT reset brings
//! it back at that node-id and `node info` reads its serial there; the
//! refusals (several nodes for a global inquiry, an unknown serial, a bit
//! rate the board cannot run) are sentences. The boards are killed at the
//! end, also on failure.
#![allow(clippy::unwrap_used, clippy::panic)]

use std::process::{Command, Output};
use std::time::{Duration, Instant};

use crate::support;

use support::{text, VirtualBus, BIN};

const NEW: u32 = 0x0C0F_FEE3;

/// A running cell of virtual boards; killed on drop.
struct Cell {
    _vb: VirtualBus,
    bus: String,
}

impl Cell {
    fn start(serials: &[&str]) -> Self {
        let mut args = vec!["--node-id", "0xFF"];
        for s in serials {
            args.extend(["--serial", s]);
        }
        let vb = VirtualBus::start(&args);
        // "perpend board: 3 boards, nodes 16,17,255 on 127.0.0.1:PORT"
        assert!(vb.banner.contains("nodes 16,17,255"), "{}", vb.banner);
        let bus = vb.bus.clone();
        Cell { _vb: vb, bus }
    }

    /// Runs `perpend node --bus … <args>` (bounded in time).
    fn node(&self, args: &[&str]) -> Output {
        let t = Instant::now();
        let out = Command::new(BIN)
            .args(["--quiet", "node", "--bus", &self.bus])
            .args(args)
            .output()
            .unwrap();
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "{args:?} took too long"
        );
        out
    }

    fn ok(&self, args: &[&str]) -> String {
        let o = self.node(args);
        let (out, err) = text(&o);
        assert!(o.status.success(), "{args:?} failed:\n{out}\n{err}");
        out
    }

    fn failed(&self, args: &[&str]) -> String {
        let o = self.node(args);
        let (out, err) = text(&o);
        assert_eq!(o.status.code(), Some(1), "{args:?}:\n{out}\n{err}");
        err
    }
}

fn json(s: &str) -> serde_json::Value {
    serde_json::from_str(s.trim()).unwrap_or_else(|e| panic!("{e}: {s}"))
}

#[test]
fn fastscan_finds_the_non_configured_head_and_assign_commissions_it() {
    let cell = Cell::start(&["0x101:16", "0x102:17", &format!("{NEW:#x}")]);
    // Only the non-configured head takes part in fastscan.
    let v = json(&cell.ok(&["lss", "fastscan", "--json"]));
    let nodes = v["nodes"].as_array().unwrap();
    assert_eq!(nodes.len(), 1, "{v}");
    assert_eq!(nodes[0]["serial"], NEW);
    assert_eq!(nodes[0]["node_id"], serde_json::Value::Null);
    // Listing left it non-configured and in waiting state: assign.
    let out = cell.ok(&["lss", "scan", "--assign", "0x20", "--store"]);
    assert!(out.contains("serial 0x0c0ffee3 -> node-id 32"), "{out}");
    let out = cell.ok(&["lss", "scan"]);
    assert!(out.contains("no non-configured node"), "{out}");
    // Stored: a reset node brings it back at 32.
    let out = cell.ok(&["--node-id", "32", "nmt", "reset"]);
    assert!(out.contains("boot-up received"), "{out}");
    let v = json(&cell.ok(&["--node-id", "32", "info", "--json"]));
    assert_eq!(v["serial"], NEW);
    assert_eq!(v["stored_node_id"], 32);
    // LSS sees it configured now.
    let v = json(&cell.ok(&["lss", "inquire", "--serial", "0x0C0FFEE3", "--json"]));
    assert_eq!(v["node_id"], 32);
}

#[test]
fn inquire_and_set_node_id_address_one_head() {
    let cell = Cell::start(&["0x101:16", "0x102:17", &format!("{NEW:#x}")]);
    let err = cell.failed(&["lss", "inquire"]);
    assert!(err.contains("3 nodes answered LSS"), "{err}");
    assert!(err.contains("--serial S"), "{err}");
    let out = cell.ok(&["--node-id", "17", "lss", "inquire"]);
    assert!(
        out.contains("serial 0x00000102") && out.contains("node-id 17 (active)"),
        "{out}"
    );
    let err = cell.failed(&["lss", "set-node-id", "5", "--serial", "0x999"]);
    assert!(err.contains("no node in LSS waiting state has"), "{err}");
    // A configured head: pending until its reset communication.
    let out = cell.ok(&["lss", "set-node-id", "0x30", "--serial", "0x101", "--reset"]);
    assert!(out.contains("node-id 16 -> 48 (not stored)"), "{out}");
    assert!(out.contains("node 48 started"), "{out}");
    let v = json(&cell.ok(&["--node-id", "48", "info", "--json"]));
    assert_eq!(v["serial"], 0x101);
    // The non-configured head: at once.
    let out = cell.ok(&[
        "lss",
        "set-node-id",
        "0x31",
        "--serial",
        &format!("{NEW:#x}"),
    ]);
    assert!(out.contains("node 49 started"), "{out}");
    // A bit rate the board cannot run: refused in words; one it can: ok.
    let err = cell.failed(&["lss", "set-bitrate", "800", "--serial", "0x102"]);
    assert!(err.contains("bit timing not supported"), "{err}");
    let out = cell.ok(&["lss", "set-bitrate", "500"]);
    assert!(
        out.contains("3 node(s)") && out.contains("500 kbit/s configured"),
        "{out}"
    );
    let out = cell.ok(&["lss", "store"]);
    assert!(out.contains("3 node(s)") && out.contains("stored"), "{out}");
}
