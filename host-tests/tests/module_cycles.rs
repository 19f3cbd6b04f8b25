//! No two source files of the workspace import each other: the Rust
//! crates, and the Python of `host-tests/blind/` (issue 47: `score.py`
//! and `v3.py` were the last pair).
//!
//! What *imports* means, and the limits of the lexical scan that finds
//! it, are in `common/mod.rs` (shared with `diagnose_stages.rs`). A pair
//! of files that import each other has no order in which a reader can
//! take them: each needs the other first (issue 35).
//!
//! `MODULE_GRAPH=1 cargo test -p host-tests --test module_cycles -- --nocapture`
//! prints the parent/child pairs and every cycle longer than a pair too
//! (strongly connected files); `MODULE_GRAPH_ROOT=DIR` scans another
//! checkout.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;

use common::{graph, references, tokens, Graph, Tree};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Pairs of files that import each other.
fn mutual_pairs(g: &Graph) -> Vec<(PathBuf, PathBuf)> {
    let mut out = Vec::new();
    for (a, to) in g {
        for b in to {
            if a < b && g.get(b).is_some_and(|t| t.contains(a)) {
                out.push((a.clone(), b.clone()));
            }
        }
    }
    out
}

/// Strongly connected sets of more than one file (Kosaraju).
fn cycles(g: &Graph) -> Vec<Vec<PathBuf>> {
    fn order(
        g: &BTreeMap<PathBuf, BTreeSet<PathBuf>>,
        n: &PathBuf,
        seen: &mut BTreeSet<PathBuf>,
        out: &mut Vec<PathBuf>,
    ) {
        if !seen.insert(n.clone()) {
            return;
        }
        for m in g.get(n).into_iter().flatten() {
            order(g, m, seen, out);
        }
        out.push(n.clone());
    }
    let mut rev: BTreeMap<PathBuf, BTreeSet<PathBuf>> = BTreeMap::new();
    for (a, to) in g {
        for b in to {
            rev.entry(b.clone()).or_default().insert(a.clone());
        }
    }
    let (mut seen, mut fin) = (BTreeSet::new(), Vec::new());
    for n in g.keys() {
        order(g, n, &mut seen, &mut fin);
    }
    let mut done = BTreeSet::new();
    let mut out = Vec::new();
    for n in fin.iter().rev() {
        let mut comp = Vec::new();
        order(&rev, n, &mut done, &mut comp);
        if comp.len() > 1 {
            comp.sort();
            out.push(comp);
        }
    }
    out
}

/// Pairs that import each other in files this check's author does not own
/// (issue 35 leaves them to their owners). The list may only shrink: a
/// pair listed here that no longer imports both ways fails the test too.
const KNOWN: [(&str, &str); 0] = [];

/// Two files that are not parent and child import each other nowhere
/// (but the [`KNOWN`] pairs). A parent that uses its child while the child
/// uses the parent's items is Rust's usual nesting and is counted apart
/// (printed with `MODULE_GRAPH=1`).
#[test]
fn no_two_files_import_each_other() {
    let (g, nested) = graph();
    assert!(
        g.len() > 100,
        "only {} files found: the scan is broken",
        g.len()
    );
    let (inside, pairs): (Vec<_>, Vec<_>) = mutual_pairs(&g)
        .into_iter()
        .partition(|p| nested.contains(p));
    if std::env::var_os("MODULE_GRAPH").is_some() {
        eprintln!("{} parent/child pairs import each other:", inside.len());
        for (a, b) in &inside {
            eprintln!("  {} <-> {}", a.display(), b.display());
        }
        for c in cycles(&g) {
            eprintln!("cycle of {} files: {:?}", c.len(), c);
        }
    }
    let known: Vec<(PathBuf, PathBuf)> = KNOWN
        .iter()
        .map(|(a, b)| (PathBuf::from(a), PathBuf::from(b)))
        .collect();
    let gone: Vec<_> = known.iter().filter(|k| !pairs.contains(k)).collect();
    assert!(
        gone.is_empty(),
        "no longer import each other, remove from KNOWN: {gone:?}"
    );
    let lines: Vec<String> = pairs
        .iter()
        .filter(|p| !known.contains(p))
        .map(|(a, b)| format!("  {} <-> {}", a.display(), b.display()))
        .collect();
    assert!(
        lines.is_empty(),
        "{} pairs of files import each other; move what both need into the one the data reach first \
         (types first, then functions), so that only the later one imports:\n{}",
        lines.len(),
        lines.join("\n")
    );
}

/// The scan finds what it is meant to: a `use super::*` in an inline test
/// module, a child named by its `mod`, `crate::` paths inline and in use
/// groups; and ignores comments, strings and `$crate`.
#[test]
fn the_scan_sees_use_trees_inline_paths_and_skips_comments() {
    let mut t = Tree::default();
    for m in [
        vec![],
        vec!["a".to_string()],
        vec!["a".into(), "b".into()],
        vec!["c".into()],
    ] {
        t.modules.insert(m, PathBuf::new());
    }
    let a = vec!["a".to_string()];
    let src = "mod b; use crate::{c::X, a::b::{Y, Z as W}}; fn f() { b::g(); } \
               // crate::nope::x\n const S: &str = \"super::c\"; \
               #[cfg(test)] mod tests { use super::*; } macro_rules! m { () => { $crate::c::x } }";
    let refs = references(&t, &a, &tokens(src));
    let want: BTreeSet<Vec<String>> = [
        vec!["a".to_string()],
        vec!["a".into(), "b".into()],
        vec!["c".into()],
    ]
    .into_iter()
    .collect();
    assert_eq!(refs, want);
    // From inside `a::b`, `super::super` is the crate root.
    let refs = references(
        &t,
        &["a".to_string(), "b".to_string()],
        &tokens("use super::super::c;"),
    );
    assert_eq!(refs, [vec!["c".to_string()]].into_iter().collect());
}

/// `MODULE_GRAPH_INTO=path` prints the files that import `path`.
#[test]
fn print_importers() {
    let Some(into) = std::env::var_os("MODULE_GRAPH_INTO") else {
        return;
    };
    let (g, _) = graph();
    for (a, to) in &g {
        if to.contains(Path::new(&into)) {
            eprintln!("{} -> {}", a.display(), into.to_string_lossy());
        }
    }
}

/// The sibling modules a Python file imports (`import a, b`, `from a
/// import x`, also indented ones inside functions), outside triple-quoted
/// strings and `#` comments. `siblings`: the module names of its directory.
fn python_imports(src: &str, siblings: &BTreeSet<String>) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut in_string = false;
    for line in src.lines() {
        let quotes = line.matches("\"\"\"").count();
        let was = in_string;
        if quotes % 2 == 1 {
            in_string = !in_string;
        }
        if was || quotes > 0 {
            continue;
        }
        let code = line.split('#').next().unwrap_or("").trim();
        let names: Vec<&str> = if let Some(rest) = code.strip_prefix("import ") {
            rest.split(',')
                .filter_map(|n| n.split_whitespace().next())
                .collect()
        } else if let Some(rest) = code.strip_prefix("from ") {
            match rest.split_once(" import ") {
                Some((m, _)) => vec![m.trim()],
                None => vec![],
            }
        } else {
            vec![]
        };
        for n in names {
            let top = n.split('.').next().unwrap_or(n);
            if siblings.contains(top) {
                out.insert(top.to_string());
            }
        }
    }
    out
}

/// The import graph of the Python files of one directory.
fn python_graph(dir: &Path) -> Graph {
    let files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "py"))
        .collect();
    let stem = |p: &Path| p.file_stem().unwrap().to_string_lossy().into_owned();
    let siblings: BTreeSet<String> = files.iter().map(|p| stem(p)).collect();
    let mut g = Graph::new();
    for f in &files {
        let src = std::fs::read_to_string(f).unwrap();
        let to = python_imports(&src, &siblings)
            .into_iter()
            .filter(|m| *m != stem(f))
            .map(|m| PathBuf::from(format!("{m}.py")))
            .collect();
        g.insert(PathBuf::from(format!("{}.py", stem(f))), to);
    }
    g
}

/// No import circle among the Python files of `host-tests/blind/` (a
/// pair or longer): each can be read after the ones it imports.
#[test]
fn no_python_file_of_blind_imports_in_a_circle() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("blind");
    let g = python_graph(&dir);
    assert!(
        g.len() >= 8 && g.get(Path::new("score.py")).is_some_and(|t| !t.is_empty()),
        "the scan found {} files: it is broken",
        g.len()
    );
    let c = cycles(&g);
    assert!(
        c.is_empty(),
        "host-tests/blind: files that import each other (in a circle): {c:?}; move what they \
         share into a module of its own"
    );
}

/// The Python scan sees `import a, b`, `from a import x` and an import
/// inside a function, and skips docstrings, comments and other modules.
#[test]
fn the_python_scan_sees_imports_and_skips_docstrings() {
    let sib: BTreeSet<String> = ["a", "b", "c", "d"].iter().map(|s| s.to_string()).collect();
    let src = "\"\"\"Doc\nimport d\n\"\"\"\nimport os, a  # noqa\nfrom b import x\n\
               def f():\n    import c\n# import d\n";
    let got = python_imports(src, &sib);
    let want: BTreeSet<String> = ["a", "b", "c"].iter().map(|s| s.to_string()).collect();
    assert_eq!(got, want);
}
