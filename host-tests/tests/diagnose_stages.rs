//! `perpend diagnose` is one pass through stages in the order the data
//! move, each entered once (issue 35).
//!
//! [`ORDER`] declares the files of the pass (`crates/perpend-diagnosis/src/
//! diagnose/`) in the order a reader takes them: the toolbox first (the
//! modules several stages call: the settings, the effect-free
//! re-simulations, the calibrated decision; the statistics, folds, the
//! candidates' fits, cross-validation, noise and lags the calibration
//! shares are in `crates/perpend-calib/src/`, below the pass, issue 48),
//! then the stages in the order the readings reach
//! them, then the diagnosis they fill, the report and the pass itself
//! (`mod.rs`). Four checks, each shown to fail on a synthetic case:
//!
//! 1. every file under `diagnose/` is declared, in the pass or beside it
//!    ([`BESIDE`]: other commands that share the toolbox);
//! 2. every file of the pass imports only files declared before it (so
//!    the toolbox imports no stage, and no stage a later one) and none
//!    beside it; test modules are held to a list that may only shrink;
//! 3. `diagnose()` calls each stage's entry point exactly once, in the
//!    declared order, and no other file of the pass that imports a stage
//!    calls its entry;
//! 4. the readers of the diagnosis (report, plots, `json()`, `--out`)
//!    call none of the toolbox's fitting functions ([`REFITS`]).
//!
//! Limits: the import graph is the lexical one of `common/mod.rs` (see
//! there). Production code is `#[cfg(test)] mod x { .. }` blocks left
//! out (a test module declared as a file would be counted). The calls are
//! found lexically too: an identifier followed by `(` that is neither a
//! method (`.x(`) nor a definition (`fn x(`); a stage entered through a
//! closure, a function pointer or a macro is not seen, and a local
//! function of the same name as an entry point elsewhere in the pass
//! would be counted as a call of it (the refit check leaves out
//! unqualified calls of a function defined in the same file).
//!
//! `MODULE_GRAPH=1 cargo test -p host-tests --test diagnose_stages --
//! --nocapture` prints the walk of the readings: the stage entries as
//! `diagnose()` calls them, with their files and return types.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;

use common::{graph, graph_of, tokens, Graph, Tok};
use std::collections::BTreeSet;
use std::path::Path;

/// The folder of the pass, relative to the workspace root.
const DIR: &str = "crates/perpend-diagnosis/src/diagnose/";

/// What a file of the pass is.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Role {
    /// Called by several stages; imports no stage.
    Toolbox,
    /// A stage, entered through this function.
    Stage(&'static str),
    /// The stage outputs side by side (`Diagnosis`).
    Output,
    /// Reads the diagnosis, never refits.
    Report,
    /// The pass (`diagnose()`) and the command around it.
    Pass,
}

/// The files of the pass in the order a reader takes them: each imports
/// only files above it.
const ORDER: [(&str, Role); 16] = [
    ("settings.rs", Role::Toolbox),
    ("insample.rs", Role::Toolbox),
    ("expect.rs", Role::Toolbox),
    ("select.rs", Role::Toolbox),
    ("nested.rs", Role::Toolbox),
    ("direction.rs", Role::Toolbox),
    ("load.rs", Role::Stage("load")),
    ("fits.rs", Role::Stage("fit")),
    ("decision.rs", Role::Stage("decide_run")),
    ("scores.rs", Role::Stage("scores")),
    ("checks.rs", Role::Stage("compare")),
    ("limits.rs", Role::Stage("limits")),
    ("diagnosis.rs", Role::Output),
    ("report.rs", Role::Report),
    ("plot.rs", Role::Report),
    ("mod.rs", Role::Pass),
];

/// Files under `diagnose/` outside the pass (`perpend bench`, `perpend
/// study`, the blind grid): they may import the pass; it imports none of
/// them. A name ending in `/` is a folder.
const BESIDE: [&str; 4] = ["bench.rs", "blind.rs", "scenario.rs", "study/"];

/// Imports against the order in test modules only (end-to-end tests that
/// run the whole pass from inside a module of it). The list may only
/// shrink: a pair listed here that is gone fails the test too.
const KNOWN_IN_TESTS: [(&str, &str); 0] = [];

/// The tokens without the `#[cfg(test)] mod x { .. }` blocks.
fn without_test_mods(toks: Vec<Tok>) -> Vec<Tok> {
    let attr: Vec<Tok> = ["#", "[", "cfg", "(", "test", ")", "]"]
        .iter()
        .map(|s| match *s {
            "cfg" | "test" => Tok::Ident((*s).into()),
            p => Tok::Punct(p.chars().next().unwrap()),
        })
        .collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < toks.len() {
        if toks[i..].starts_with(&attr) {
            // Further attributes, a visibility (`pub`, `pub(crate)`), then
            // `mod name {`.
            let mut j = i + attr.len();
            while toks.get(j) == Some(&Tok::Punct('#')) {
                j = block_end(&toks, j + 1, '[', ']');
            }
            if toks.get(j) == Some(&Tok::Ident("pub".into())) {
                j += 1;
                if toks.get(j) == Some(&Tok::Punct('(')) {
                    j = block_end(&toks, j, '(', ')');
                }
            }
            let is_mod = toks.get(j) == Some(&Tok::Ident("mod".into()))
                && toks.get(j + 2) == Some(&Tok::Punct('{'));
            if is_mod {
                i = block_end(&toks, j + 2, '{', '}');
                continue;
            }
        }
        out.push(toks[i].clone());
        i += 1;
    }
    out
}

/// The index after the `open … close` group starting at `toks[i]`.
fn block_end(toks: &[Tok], i: usize, open: char, close: char) -> usize {
    let mut depth = 0usize;
    for (k, t) in toks.iter().enumerate().skip(i) {
        if *t == Tok::Punct(open) {
            depth += 1;
        } else if *t == Tok::Punct(close) {
            depth = depth.saturating_sub(1);
            if depth == 0 {
                return k + 1;
            }
        }
    }
    toks.len()
}

/// The import graph restricted to `DIR`, file names relative to it.
fn pass_graph(with_tests: bool) -> Graph {
    let (g, _) = if with_tests {
        graph()
    } else {
        graph_of(&without_test_mods)
    };
    let local = |p: &Path| {
        p.to_string_lossy()
            .strip_prefix(DIR)
            .map(std::path::PathBuf::from)
    };
    g.iter()
        .filter_map(|(a, to)| Some((local(a)?, to.iter().filter_map(|b| local(b)).collect())))
        .collect()
}

fn is_beside(f: &str) -> bool {
    BESIDE.iter().any(|b| {
        if b.ends_with('/') {
            f.starts_with(b)
        } else {
            f == *b
        }
    })
}

/// The imports of `g` against `order`: (importer, imported, why).
fn against_order(order: &[(&str, Role)], g: &Graph) -> Vec<(String, String, String)> {
    let pos = |f: &str| order.iter().position(|(n, _)| *n == f);
    let mut out = Vec::new();
    for (i, (me, role)) in order.iter().enumerate() {
        for to in g.get(Path::new(me)).into_iter().flatten() {
            let to = to.to_string_lossy().to_string();
            let why = match (pos(&to), order.get(pos(&to).unwrap_or(0))) {
                _ if is_beside(&to) => "a file beside the pass".to_string(),
                (None, _) => "an undeclared file".to_string(),
                (Some(j), Some((_, r))) if j > i && *role == Role::Toolbox => {
                    format!("a later file ({r:?}): the toolbox imports no stage")
                }
                (Some(j), Some((_, r))) if j > i => format!("a later file ({r:?})"),
                _ => continue,
            };
            out.push((me.to_string(), to, why));
        }
    }
    out
}

/// Every file under `diagnose/` is in [`ORDER`] or [`BESIDE`], and every
/// file of [`ORDER`] exists.
#[test]
fn every_file_of_the_folder_is_declared() {
    let g = pass_graph(false);
    assert!(g.len() > 20, "only {} files found under {DIR}", g.len());
    let files: BTreeSet<String> = g.keys().map(|p| p.to_string_lossy().into()).collect();
    let stray: Vec<&String> = files
        .iter()
        .filter(|f| !is_beside(f) && !ORDER.iter().any(|(n, _)| n == f))
        .collect();
    assert!(
        stray.is_empty(),
        "{stray:?} under {DIR} are neither in ORDER nor in BESIDE of {}: declare where they stand \
         in the pass (toolbox, stage, report) or beside it",
        file!()
    );
    let gone: Vec<&str> = ORDER
        .iter()
        .map(|(n, _)| *n)
        .filter(|n| !files.contains(*n))
        .collect();
    assert!(gone.is_empty(), "{gone:?} of ORDER no longer exist");
}

/// The files of the pass import only files declared before them
/// (production code); test modules only as [`KNOWN_IN_TESTS`] lists.
#[test]
fn each_file_of_the_pass_imports_only_earlier_ones() {
    let found = against_order(&ORDER, &pass_graph(false));
    let lines: Vec<String> = found
        .iter()
        .map(|(a, b, why)| format!("  {a} imports {b}, {why}"))
        .collect();
    assert!(
        lines.is_empty(),
        "{} imports against the order of the pass (ORDER in {}); move what the earlier file \
         needs into it or into the toolbox:\n{}",
        lines.len(),
        file!(),
        lines.join("\n")
    );
    let in_tests: BTreeSet<(String, String)> = against_order(&ORDER, &pass_graph(true))
        .into_iter()
        .map(|(a, b, _)| (a, b))
        .collect();
    let known: BTreeSet<(String, String)> = KNOWN_IN_TESTS
        .iter()
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .collect();
    assert_eq!(
        in_tests, known,
        "imports against the order in test modules (left) differ from KNOWN_IN_TESTS (right): \
         a new one is a test reaching a later stage (build its input in the test instead), a \
         gone one is to be removed from the list"
    );
}

/// The calls in `toks`: identifiers followed by `(`, neither methods nor
/// definitions, with their index.
fn call_sites(toks: &[Tok]) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    for (i, t) in toks.iter().enumerate() {
        if let (Tok::Ident(name), Some(Tok::Punct('('))) = (t, toks.get(i + 1)) {
            let before = i.checked_sub(1).map(|k| &toks[k]);
            let method_or_def =
                matches!(before, Some(Tok::Punct('.'))) || before == Some(&Tok::Ident("fn".into()));
            if !method_or_def {
                out.push((i, name.clone()));
            }
        }
    }
    out
}

/// The names [`call_sites`] calls, in order.
fn calls(toks: &[Tok]) -> Vec<String> {
    call_sites(toks).into_iter().map(|(_, n)| n).collect()
}

/// The index of `fn name` in `toks`.
fn fn_at(toks: &[Tok], name: &str) -> Option<usize> {
    toks.windows(2)
        .position(|w| w[0] == Tok::Ident("fn".into()) && w[1] == Tok::Ident(name.into()))
}

/// The tokens of the body of `fn name` in `toks` (empty when absent).
fn body_of(toks: &[Tok], name: &str) -> Vec<Tok> {
    let Some(at) = fn_at(toks, name) else {
        return Vec::new();
    };
    let Some(open) = toks[at..].iter().position(|t| *t == Tok::Punct('{')) else {
        return Vec::new();
    };
    let end = block_end(toks, at + open, '{', '}');
    toks[at + open + 1..end.saturating_sub(1)].to_vec()
}

/// Mistakes of the walk `called` (the calls of the pass, in order)
/// against the stage entries `entries`, in the declared order: an entry
/// not called exactly once, or called before the one declared before it.
fn walk_mistakes(called: &[String], entries: &[&str]) -> Vec<String> {
    let mut out = Vec::new();
    let mut last: Option<(usize, &str)> = None;
    for e in entries {
        let at: Vec<usize> = (0..called.len()).filter(|&i| called[i] == *e).collect();
        if at.len() != 1 {
            out.push(format!("`{e}` is called {} times, not once", at.len()));
            continue;
        }
        if let Some((p, prev)) = last.filter(|(p, _)| at[0] < *p) {
            out.push(format!(
                "`{e}` is called before `{prev}` (call {} < {p})",
                at[0]
            ));
        }
        last = Some((at[0], e));
    }
    out
}

/// The stage entries in the declared order.
fn entries() -> Vec<&'static str> {
    ORDER
        .iter()
        .filter_map(|(_, r)| match r {
            Role::Stage(e) => Some(*e),
            _ => None,
        })
        .collect()
}

fn source(file: &str) -> Vec<Tok> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(DIR)
        .join(file);
    without_test_mods(tokens(&std::fs::read_to_string(&path).unwrap()))
}

/// `diagnose()` enters each stage once, in the declared order, and no
/// other file of the pass enters one.
#[test]
fn diagnose_enters_each_stage_once_in_order() {
    let body = body_of(&source("mod.rs"), "diagnose");
    assert!(body.len() > 20, "no `fn diagnose` found in {DIR}mod.rs");
    let called = calls(&body);
    let mistakes = walk_mistakes(&called, &entries());
    assert!(
        mistakes.is_empty(),
        "diagnose() in {DIR}mod.rs does not walk the stages of ORDER once each, in order:\n  {}",
        mistakes.join("\n  ")
    );
    // Only a file after a stage may import it (the order check): those
    // must not call its entry.
    let g = pass_graph(false);
    let mut elsewhere = Vec::new();
    for (k, (stage, role)) in ORDER.iter().enumerate() {
        let Role::Stage(e) = role else { continue };
        for (file, _) in ORDER[k + 1..].iter().filter(|(f, _)| *f != "mod.rs") {
            let imports = g
                .get(Path::new(file))
                .is_some_and(|t| t.contains(Path::new(stage)));
            if imports && calls(&source(file)).iter().any(|c| c == e) {
                elsewhere.push(format!("{file} calls {stage}'s `{e}`"));
            }
        }
    }
    assert!(
        elsewhere.is_empty(),
        "a stage is entered outside diagnose(): {elsewhere:?}; pass its output instead"
    );
    if std::env::var_os("MODULE_GRAPH").is_some() {
        print_walk(&called);
    }
}

/// The return type of `fn name` in `toks`, its tokens joined.
fn returns(toks: &[Tok], name: &str) -> String {
    let Some(at) = fn_at(toks, name) else {
        return "?".into();
    };
    let sig: Vec<&Tok> = toks[at..]
        .iter()
        .take_while(|t| **t != Tok::Punct('{'))
        .collect();
    let arrow = sig
        .windows(2)
        .position(|w| *w[0] == Tok::Punct('-') && *w[1] == Tok::Punct('>'))
        .map_or(sig.len(), |p| p + 2);
    let ret: Vec<String> = sig[arrow..]
        .iter()
        .map(|t| match t {
            Tok::Ident(s) => s.clone(),
            Tok::Path => "::".into(),
            Tok::Punct(c) => c.to_string(),
        })
        .collect();
    ret.concat()
}

/// Prints the stages in the order `diagnose()` enters them.
fn print_walk(called: &[String]) {
    println!("the walk of the readings through diagnose() ({DIR}mod.rs):");
    let stages = ORDER.iter().filter_map(|(f, r)| match r {
        Role::Stage(e) => Some((*f, *e)),
        _ => None,
    });
    let mut steps: Vec<(usize, &str, &str)> = stages
        .filter_map(|(f, e)| Some((called.iter().position(|c| c == e)?, f, e)))
        .collect();
    steps.sort();
    for (k, (_, file, entry)) in steps.iter().enumerate() {
        println!(
            "  {}. {file:<12} {entry:<11} -> {}",
            k + 1,
            returns(&source(file), entry)
        );
    }
    println!(
        "  then Diagnosis (diagnosis.rs) -> report.rs, plot.rs, json(), param_file(): read only"
    );
}

/// The toolbox functions that fit, cross-validate or simulate: what a
/// reader of the diagnosis must not call (it would refit).
const REFITS: [&str; 14] = [
    "fit",
    "fit_from",
    "fit_all",
    "cross_validate",
    "analyse",
    "expect",
    "base_residuals",
    "model_residuals",
    "full_residuals",
    "reject",
    "decide",
    "judge",
    "measure_normal",
    "normal_errors",
];

/// The calls of [`REFITS`] in `toks`, but unqualified calls of a
/// function of that name defined in `toks` (a local `fn normal_errors`).
fn refits(toks: &[Tok]) -> Vec<String> {
    let fn_tok = Tok::Ident("fn".into());
    let local: Vec<&Tok> = toks
        .windows(2)
        .filter(|w| w[0] == fn_tok)
        .map(|w| &w[1])
        .collect();
    call_sites(toks)
        .into_iter()
        .filter(|(i, name)| {
            let qualified = i.checked_sub(1).map(|k| &toks[k]) == Some(&Tok::Path);
            let mine = local.contains(&&toks[*i]) && !qualified;
            !mine && REFITS.contains(&name.as_str())
        })
        .map(|(_, n)| n)
        .collect()
}

/// The readers of the diagnosis (the report, the plots, the diagnosis
/// itself, `json()`, `param_file` and the command around them in
/// `mod.rs`) refit nothing: they call no function of [`REFITS`].
#[test]
fn the_readers_of_the_diagnosis_never_refit() {
    let mut found = Vec::new();
    for (file, role) in ORDER {
        if matches!(role, Role::Output | Role::Report) {
            found.extend(
                refits(&source(file))
                    .into_iter()
                    .map(|c| format!("{file}: `{c}`")),
            );
        }
    }
    let pass = source("mod.rs");
    for f in ["json", "param_file", "run_to", "write_record"] {
        let body = body_of(&pass, f);
        assert!(!body.is_empty(), "no `fn {f}` in {DIR}mod.rs");
        found.extend(
            refits(&body)
                .into_iter()
                .map(|c| format!("mod.rs {f}(): `{c}`")),
        );
    }
    assert!(
        found.is_empty(),
        "the readers of the diagnosis refit: {found:?}; read what the stages computed (Diagnosis) instead"
    );
    let fake = tokens(
        "fn text(d: &D) { candidates::fit_all(a); d.fit(b); analyse(c); cv::normal_errors(e); \
         normal_errors(f) } fn normal_errors(x: X) {}",
    );
    assert_eq!(refits(&fake), ["fit_all", "analyse", "normal_errors"]);
}

/// The order check flags a toolbox file importing a stage, a stage
/// importing a later one, and an import of a file beside the pass; an
/// import of an earlier file passes.
#[test]
fn the_order_check_fails_on_imports_of_later_files() {
    let order = [
        ("tool.rs", Role::Toolbox),
        ("a.rs", Role::Stage("a")),
        ("b.rs", Role::Stage("b")),
    ];
    let g = |edges: &[(&str, &str)]| {
        let mut g = Graph::new();
        for (a, b) in edges {
            g.entry(Path::new(a).into())
                .or_default()
                .insert(Path::new(b).into());
        }
        g
    };
    assert!(against_order(&order, &g(&[("b.rs", "a.rs"), ("a.rs", "tool.rs")])).is_empty());
    let bad = against_order(&order, &g(&[("a.rs", "b.rs")]));
    assert_eq!(bad.len(), 1);
    assert!(bad[0].2.contains("later"), "{bad:?}");
    let bad = against_order(&order, &g(&[("tool.rs", "a.rs")]));
    assert!(bad[0].2.contains("toolbox imports no stage"), "{bad:?}");
    let bad = against_order(&order, &g(&[("a.rs", "bench.rs"), ("b.rs", "x.rs")]));
    assert_eq!(bad.len(), 2, "{bad:?}");
}

/// The walk check flags a stage entered twice, one skipped and two out of
/// order, and passes the walk in order; methods, definitions and test
/// modules are not calls.
#[test]
fn the_walk_check_fails_on_twice_skipped_and_out_of_order() {
    let body = |src: &str| calls(&body_of(&without_test_mods(tokens(src)), "pass"));
    let entries = ["load", "fit", "decide"];
    let good =
        body("fn pass() { let r = load(x)?; let f = fits::fit(&r); x.decide(); decide(&f) }");
    assert_eq!(walk_mistakes(&good, &entries), Vec::<String>::new());
    let twice = body("fn pass() { load(x); fit(y); fit(z); decide(w) }");
    assert_eq!(walk_mistakes(&twice, &entries).len(), 1);
    let skipped = body("fn pass() { load(x); decide(w) } fn fit() {}");
    assert_eq!(walk_mistakes(&skipped, &entries).len(), 1);
    let swapped = body("fn pass() { load(x); decide(w); fit(y) }");
    let m = walk_mistakes(&swapped, &entries);
    assert!(m.len() == 1 && m[0].contains("before"), "{m:?}");
    let t = without_test_mods(tokens(
        "fn a() {} #[cfg(test)] #[allow(x)] mod tests { fn b() { fit(1) } } fn c() { load(2) }",
    ));
    assert_eq!(calls(&t), vec!["load".to_string()]);
}

/// Test modules are left out whatever their attributes and visibility
/// (`pub(crate) mod tests` shares fixtures with other test modules);
/// code around them stays.
#[test]
fn test_modules_are_left_out_with_any_visibility() {
    let kept = |src: &str| {
        without_test_mods(tokens(src))
            .into_iter()
            .filter_map(|t| match t {
                Tok::Ident(s) => Some(s),
                _ => None,
            })
            .collect::<Vec<_>>()
            .join(" ")
    };
    for vis in ["", "pub", "pub(crate)", "pub(super)"] {
        let src = format!(
            "fn a() {{}} #[cfg(test)] #[allow(x)] {vis} mod tests {{ use super::later; }} fn b() {{}}"
        );
        assert_eq!(kept(&src), "fn a fn b", "{vis}");
    }
    assert_eq!(kept("#[cfg(test)] fn c() {}"), "cfg test fn c");
}
