//! The link options of `perpend node` and `perpend cell` parse the same
//! before and after the subcommand (issue 31, item 4), through the same
//! clap definitions as the binary.
#![allow(clippy::unwrap_used, clippy::panic)]

use clap::Parser;
use perpend_cli::{cell, node};

#[derive(Parser)]
struct NodeCli {
    #[command(flatten)]
    a: node::Args,
}

#[derive(Parser)]
struct CellCli {
    #[command(flatten)]
    a: cell::Args,
}

const LINK: [&str; 8] = [
    "--bus",
    "tcp:127.0.0.1:7",
    "--node-id",
    "0x10",
    "--bitrate",
    "500",
    "--timeout-ms",
    "90",
];

fn check_link(l: &node::LinkArgs, order: &str) {
    assert_eq!(l.bus.as_deref(), Some("tcp:127.0.0.1:7"), "{order}");
    assert_eq!(l.node_id, Some(16), "{order}");
    assert_eq!(l.bitrate, 500, "{order}");
    assert_eq!(l.timeout_ms, Some(90), "{order}");
}

fn node_push(args: &[&str], order: &str) {
    let c = NodeCli::try_parse_from(args).unwrap_or_else(|e| panic!("{order}: {e}"));
    check_link(&c.a.link, order);
    match c.a.cmd {
        node::Cmd::Push(p) => {
            assert_eq!(p.file.to_str(), Some("params.json"), "{order}");
            assert!(p.preop, "{order}");
        }
        _ => panic!("{order}: not push"),
    }
}

#[test]
fn node_options_parse_before_and_after_the_subcommand() {
    let cmd = ["params.json", "--preop"];
    node_push(&[&["node"][..], &LINK, &["push"], &cmd].concat(), "before");
    node_push(&[&["node", "push"][..], &cmd, &LINK].concat(), "after");
    let mixed = ["node", "--bus", "tcp:127.0.0.1:7", "push", "params.json"];
    let rest = [
        "--node-id",
        "16",
        "--preop",
        "--bitrate",
        "500",
        "--timeout-ms",
        "90",
    ];
    node_push(&[&mixed[..], &rest].concat(), "mixed");
}

fn cell_run(args: &[&str], order: &str) {
    let c = CellCli::try_parse_from(args).unwrap_or_else(|e| panic!("{order}: {e}"));
    check_link(&c.a.link, order);
    match c.a.cmd {
        cell::Cmd::Run(r) => {
            assert_eq!(r.m.robot, "manual", "{order}");
            assert_eq!(r.samples, 7, "{order}");
        }
        cell::Cmd::SimHead(_) | cell::Cmd::Check(_) => panic!("{order}: not run"),
    }
}

#[test]
fn cell_options_parse_before_and_after_the_subcommand() {
    let run = [
        "--sensors",
        "s.csv",
        "--plan",
        "plan.csv",
        "--robot",
        "manual",
        "--out",
        "o",
        "--samples",
        "7",
    ];
    cell_run(&[&["cell"][..], &LINK, &["run"], &run].concat(), "before");
    cell_run(&[&["cell", "run"][..], &run, &LINK].concat(), "after");
}

#[test]
fn a_bad_node_id_is_refused_in_either_position() {
    for args in [
        vec!["node", "--node-id", "200", "info"],
        vec!["node", "info", "--node-id", "200"],
        vec!["cell", "sim-head", "--out", "o", "--node-id", "0"],
    ] {
        let e = if args[0] == "node" {
            NodeCli::try_parse_from(&args).err()
        } else {
            CellCli::try_parse_from(&args).err()
        };
        let e = e.unwrap_or_else(|| panic!("{args:?} parsed")).to_string();
        assert!(e.contains("node-id"), "{args:?}: {e}");
    }
}

/// Issue 47 point 7, the change `cell/mod.rs` needs: a subcommand that
/// flattens [`node::NoLink`] under a parent with global link options
/// neither lists them in its help nor takes them after its name; the
/// sibling that reads the link still takes them in either position.
#[test]
fn no_link_keeps_a_parents_link_options_out_of_a_subcommand() {
    #[derive(clap::Subcommand, Debug)]
    enum Sub {
        Run,
        Offline(Offline),
    }
    #[derive(clap::Args, Debug)]
    struct Offline {
        #[arg(long)]
        out: String,
        #[command(flatten)]
        _no_link: node::NoLink,
    }
    #[derive(Parser, Debug)]
    struct Top {
        #[command(flatten)]
        link: node::LinkArgs,
        #[command(subcommand)]
        cmd: Sub,
    }
    let mut cmd = <Top as clap::CommandFactory>::command();
    cmd.build();
    let off = cmd.find_subcommand_mut("offline").unwrap();
    let help = off.render_long_help().to_string();
    assert!(
        !help.contains("--bus") && !help.contains("--node-id"),
        "{help}"
    );
    let e = Top::try_parse_from(["t", "offline", "--out", "o", "--bus", "tcp:x:1"])
        .unwrap_err()
        .to_string();
    assert!(e.contains("opens no bus"), "{e}");
    let t = Top::try_parse_from(["t", "offline", "--out", "o"]).unwrap();
    assert!(matches!(t.cmd, Sub::Offline(_)));
    for args in [
        vec!["t", "--bus", "tcp:x:1", "--node-id", "5", "run"],
        vec!["t", "run", "--bus", "tcp:x:1", "--node-id", "5"],
    ] {
        let t = Top::try_parse_from(&args).unwrap();
        assert_eq!(t.link.bus.as_deref(), Some("tcp:x:1"), "{args:?}");
        assert_eq!(t.link.node_id, Some(5), "{args:?}");
    }
}
