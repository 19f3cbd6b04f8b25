//! `perpend eds` and `perpend node sdo` end to end: the printed EDS is the
//! committed `perpend.eds`; read, write (checked before sending, read
//! back), the refusals (limits, const, an unknown object's type) and an
//! abort in words, against a virtual board over slcan/TCP on loopback
//! (its own free port, killed when the test ends, also on failure);
//! `sdo list` without a bus; another EDS with `--eds`.
#![allow(clippy::unwrap_used, clippy::panic)]

use std::process::{Command, Output};
use std::time::{Duration, Instant};

use crate::support;

use support::{failed, ok, VirtualBus};

const NODE: &str = "21";

/// A running virtual board; killed on drop.
struct Board {
    _vb: VirtualBus,
    bus: String,
}

impl Board {
    fn start() -> Self {
        let vb = VirtualBus::start(&["--node-id", NODE]);
        let bus = vb.bus.clone();
        Board { _vb: vb, bus }
    }

    /// `perpend node <args> --bus … --node-id 21` (the link options last:
    /// they are global).
    fn node(&self, args: &[&str]) -> Output {
        let t = Instant::now();
        let out = perpend(&[&["node"], args, &["--bus", &self.bus, "--node-id", NODE]].concat());
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "{args:?} took too long"
        );
        out
    }
}

fn perpend(args: &[&str]) -> Output {
    Command::new(support::BIN)
        .arg("--quiet")
        .args(args)
        .output()
        .unwrap()
}

fn json(o: &Output) -> serde_json::Value {
    serde_json::from_str(ok(o).trim()).unwrap()
}

const COMMITTED: &str = include_str!("../../../../perpend.eds");

#[test]
fn perpend_eds_prints_the_committed_file() {
    assert_eq!(ok(&perpend(&["eds"])), COMMITTED);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("x.eds");
    ok(&perpend(&["eds", "--out", p.to_str().unwrap()]));
    assert_eq!(std::fs::read_to_string(&p).unwrap(), COMMITTED);
}

#[test]
fn sdo_list_needs_no_bus_and_reads_another_eds() {
    let out = ok(&perpend(&["node", "sdo", "list", "0x2300"]));
    assert!(
        out.contains("Residual limit mm  [mm]  limits 0.0001..100"),
        "{out}"
    );
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("other.eds");
    let other = COMMITTED.replace("1=0x1000\n", "1=0x1234\n");
    std::fs::write(&p, other).unwrap();
    let err = failed(&perpend(&[
        "node",
        "sdo",
        "list",
        "--eds",
        p.to_str().unwrap(),
    ]));
    assert!(
        err.contains("other.eds line 49") && err.contains("no section [1234]"),
        "{err}"
    );
    let v = json(&perpend(&[
        "node",
        "sdo",
        "--eds",
        "../../perpend.eds",
        "list",
        "--json",
        "0x1017",
    ]));
    assert_eq!(v["entries"][0]["type"], "UNSIGNED16");
    assert_eq!(v["eds"], "../../perpend.eds");
}

#[test]
fn sdo_read_and_write_the_virtual_board() {
    let b = Board::start();
    let out = ok(&b.node(&["sdo", "read", "0x2300", "4"]));
    assert_eq!(
        out.trim(),
        "0x2300 sub 4  Acquisition: Residual limit mm (REAL32, rw) = 0.05 mm  [limits 0.0001..100]"
    );
    let out = ok(&b.node(&["sdo", "read", "1008h", "0"]));
    assert!(out.contains("= \"perpend normal sensor\""), "{out}");
    // write, read back, old → new
    let out = ok(&b.node(&["sdo", "write", "0x1017", "0", "250"]));
    assert!(
        out.contains("Producer heartbeat time (UNSIGNED16, rw): 1000 (0x3e8) → 250 (0xfa)"),
        "{out}"
    );
    let v = json(&b.node(&["sdo", "read", "0x1017", "0", "--json"]));
    assert_eq!(
        (v["schema"].as_str(), v["value"].as_u64()),
        (Some("perpend.sdo/1"), Some(250))
    );
    assert_eq!(
        (v["index"].as_u64(), v["raw_hex"].as_str()),
        (Some(0x1017), Some("fa 00"))
    );
    let v = json(&b.node(&["sdo", "write", "0x2300", "4", "0.1", "--json"]));
    assert_eq!(
        (v["old"].as_f64(), v["value"].as_f64()),
        (Some(0.05), Some(0.1))
    );
    assert_eq!(v["unit"], "mm");
    // refused before sending: limits, const
    let err = failed(&b.node(&["sdo", "write", "0x2300", "4", "200"]));
    assert!(
        err.contains("outside the EDS limits 0.0001..100") && err.contains("nothing was sent"),
        "{err}"
    );
    let err = failed(&b.node(&["sdo", "write", "0x1018", "4", "7"]));
    assert!(
        err.contains("Serial number (UNSIGNED32, const) is constant"),
        "{err}"
    );
    let err = failed(&b.node(&["sdo", "write", "0x3000", "0", "1"]));
    assert!(
        err.contains("type is unknown") && err.contains("--eds"),
        "{err}"
    );
    let out = ok(&b.node(&["sdo", "read", "0x2300", "4"]));
    assert!(
        out.contains("= 0.1 mm"),
        "a refused write changed the value: {out}"
    );
    // --force sends it: the node's own abort, in words
    let err = failed(&b.node(&["sdo", "write", "0x2300", "4", "200", "--force"]));
    assert!(
        err.contains("abort 0x06090031") && err.contains("too high"),
        "{err}"
    );
    // the board's lock and state aborts, with what to do
    let err = failed(&b.node(&["sdo", "write", "0x2101", "1", "-1.5"]));
    assert!(
        err.contains("abort 0x08000021") && err.contains("sdo write 0x2010 0 0x6c616375"),
        "{err}"
    );
    ok(&b.node(&["nmt", "start"]));
    let err = failed(&b.node(&["sdo", "write", "0x2101", "1", "1.5"]));
    assert!(
        err.contains("abort 0x08000022") && err.contains("nmt preop` first"),
        "{err}"
    );
    let o = b.node(&["sdo", "write", "0x2300", "1", "500", "--json"]);
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(v["error"].as_str().unwrap().contains("0x08000022"), "{v}");
    // an object the node lacks
    let err = failed(&b.node(&["sdo", "read", "0x3000", "0"]));
    assert!(err.contains("abort 0x06020000"), "{err}");
}

/// Issue 47 point 1: oversampling 3 and 256 are inside the EDS limits
/// 1..256; the refusal says the rule that refuses them (a power of two;
/// one scan must fit into the sample period), never the limits.
#[test]
fn a_refused_value_inside_the_eds_limits_names_the_real_rule() {
    let b = Board::start();
    let err = failed(&b.node(&["sdo", "write", "0x2300", "2", "3"]));
    assert!(
        err.contains("3 is not a power of two")
            && err.contains("1, 2, 4, 8, 16, 32, 64, 128, 256")
            && err.contains("nothing was sent"),
        "{err}"
    );
    // the node's own abort of 3 (--force) says the same rule
    let err = failed(&b.node(&["sdo", "write", "0x2300", "2", "3", "--force"]));
    assert!(
        err.contains("abort 0x0609003") && err.contains("not a power of two"),
        "{err}"
    );
    // 256× needs a 3012 µs period; the factory period is 1000 µs
    let err = failed(&b.node(&["sdo", "write", "0x2300", "2", "256"]));
    assert!(
        err.contains("abort 0x06090030")
            && err.contains("3012 µs")
            && err.contains("sample period of 1000 µs")
            && err.contains("sdo write 0x2300 1 3012"),
        "{err}"
    );
    assert!(!err.contains("the EDS gives"), "{err}");
    let err = failed(&b.node(&["sdo", "write", "0x2300", "1", "100"]));
    assert!(
        err.contains("shorter than one ADC scan at the present 16× oversampling"),
        "{err}"
    );
    // the order the hint gives works
    ok(&b.node(&["sdo", "write", "0x2300", "1", "3012"]));
    ok(&b.node(&["sdo", "write", "0x2300", "2", "256"]));
}

/// Issue 47 point 3: an EDS of another device (its VendorNumber and
/// ProductNumber are not the node's 0x1018) is named in one warning line
/// before a read, and stops a write before anything is sent.
#[test]
fn an_eds_of_another_device_is_named_before_the_first_transfer() {
    let b = Board::start();
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("other.eds");
    let other = COMMITTED
        .replace("VendorNumber=0xAFFF5050", "VendorNumber=0x00000123")
        .replace("ProductNumber=0x50455250", "ProductNumber=0x00000456");
    std::fs::write(&p, other).unwrap();
    let eds = p.to_str().unwrap();
    let out = b.node(&["sdo", "read", "0x1017", "0", "--eds", eds]);
    let (_, err) = support::text(&out);
    assert!(out.status.success(), "{err}");
    let warn: Vec<&str> = err.lines().filter(|l| l.contains("warning")).collect();
    assert_eq!(warn.len(), 1, "{err}");
    assert!(
        warn[0].contains("vendor 0xafff5050 product 0x50455250")
            && warn[0].contains("vendor 0x00000123 product 0x00000456")
            && warn[0].contains("--eds"),
        "{err}"
    );
    let err = failed(&b.node(&["sdo", "write", "0x1017", "0", "300", "--eds", eds]));
    assert!(
        err.contains("product 0x00000456") && err.contains("Nothing was sent"),
        "{err}"
    );
    assert!(ok(&b.node(&["sdo", "read", "0x1017", "0"])).contains("= 1000"));
    // `sdo list` with a link reads it: the same check
    let out = b.node(&["sdo", "list", "0x1017", "--eds", eds]);
    let (_, err) = support::text(&out);
    assert!(
        out.status.success() && err.contains("warning:") && err.contains("0x00000456"),
        "{err}"
    );
    let out = b.node(&["sdo", "list", "0x1017"]);
    assert!(
        support::text(&out).1.contains("agrees with its identity"),
        "{:?}",
        support::text(&out)
    );
    // the board's own EDS: no warning
    let out = b.node(&["sdo", "read", "0x1017", "0"]);
    assert!(
        support::text(&out).1.is_empty(),
        "{:?}",
        support::text(&out)
    );
}
