//! The import graph of the workspace's source files, shared by the tests
//! that check it (`module_cycles.rs`, `diagnose_stages.rs`).
//!
//! A file *imports* another when it names an item of a module that lives
//! in the other file: a `use` path or an inline path starting with
//! `crate::`, `super::`, `self::` or the name of a child module (`mod x;`
//! declared here), resolved through the crate's module tree (`mod x;`
//! declarations from `src/lib.rs`, `src/main.rs` and `src/bin/*.rs`,
//! `#[path]` attributes honoured, inline `mod x { .. }` blocks kept in
//! their file).
//!
//! Limits: a lexical scan, not a compiler: paths produced by macros, `use`
//! of a module through an alias and then its items, and `pub(in path)` are
//! not followed (they can only hide an import, never invent one). Tests
//! count: a child's `use super::*` in its test module imports the parent.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The workspace root (`MODULE_GRAPH_ROOT` scans another checkout, e.g.
/// an extracted older commit, to compare).
fn root() -> PathBuf {
    std::env::var_os("MODULE_GRAPH_ROOT").map_or_else(
        || Path::new(env!("CARGO_MANIFEST_DIR")).join(".."),
        PathBuf::from,
    )
}

/// A token of the cleaned source.
#[derive(Debug, Clone, PartialEq)]
pub enum Tok {
    Ident(String),
    /// `::`
    Path,
    /// Any other punctuation character.
    Punct(char),
}

/// Skips a string literal (plain or raw) starting at `i`; returns the
/// index after it, or `None` when `i` does not start one.
fn skip_string(b: &[u8], i: usize) -> Option<usize> {
    let mut j = i;
    if b[j] == b'b' {
        j += 1;
    }
    if j < b.len() && b[j] == b'r' {
        let mut k = j + 1;
        while k < b.len() && b[k] == b'#' {
            k += 1;
        }
        if k < b.len() && b[k] == b'"' {
            let hashes = k - j - 1;
            let close: Vec<u8> = std::iter::once(b'"')
                .chain(std::iter::repeat_n(b'#', hashes))
                .collect();
            let rest = &b[k + 1..];
            let end = rest
                .windows(close.len())
                .position(|w| w == close.as_slice())?;
            return Some(k + 1 + end + close.len());
        }
        return None;
    }
    if j < b.len() && b[j] == b'"' {
        let mut k = j + 1;
        while k < b.len() && b[k] != b'"' {
            k += if b[k] == b'\\' { 2 } else { 1 };
        }
        return Some(k + 1);
    }
    None
}

/// Skips a comment or a char literal at `i`; the index after it.
fn skip_comment_or_char(b: &[u8], i: usize) -> Option<usize> {
    match (b[i], b.get(i + 1)) {
        (b'/', Some(b'/')) => Some(
            b[i..]
                .iter()
                .position(|c| *c == b'\n')
                .map_or(b.len(), |p| i + p),
        ),
        (b'/', Some(b'*')) => {
            let (mut depth, mut k) = (1, i + 2);
            while k + 1 < b.len() && depth > 0 {
                match (b[k], b[k + 1]) {
                    (b'/', b'*') => (depth, k) = (depth + 1, k + 2),
                    (b'*', b'/') => (depth, k) = (depth - 1, k + 2),
                    _ => k += 1,
                }
            }
            Some(k)
        }
        // A char literal ('x', '\n', '\u{..}'); a lifetime has no closing quote.
        (b'\'', Some(c)) => {
            let end = if *c == b'\\' {
                b[i + 2..]
                    .iter()
                    .position(|c| *c == b'\'')
                    .map(|p| i + 2 + p + 1)
            } else {
                let ch_len = std::str::from_utf8(&b[i + 1..])
                    .ok()?
                    .chars()
                    .next()?
                    .len_utf8();
                (b.get(i + 1 + ch_len) == Some(&b'\'')).then_some(i + 2 + ch_len)
            };
            end.or(Some(i + 1))
        }
        _ => None,
    }
}

/// The tokens of a source file, comments and literals dropped.
pub fn tokens(src: &str) -> Vec<Tok> {
    let b = src.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        if c.is_ascii_alphabetic() || c == b'_' {
            if let Some(j) = skip_string(b, i) {
                i = j;
                continue;
            }
            let j = i + b[i..]
                .iter()
                .position(|c| !(c.is_ascii_alphanumeric() || *c == b'_'))
                .unwrap_or(b.len() - i);
            out.push(Tok::Ident(src[i..j].to_string()));
            i = j;
        } else if c == b'"' {
            i = skip_string(b, i).unwrap_or(b.len());
        } else if let Some(j) = skip_comment_or_char(b, i) {
            i = j;
        } else if c == b':' && b.get(i + 1) == Some(&b':') {
            out.push(Tok::Path);
            i += 2;
        } else if c.is_ascii_digit() || c.is_ascii_whitespace() || !c.is_ascii() {
            i += 1;
        } else {
            out.push(Tok::Punct(c as char));
            i += 1;
        }
    }
    out
}

/// One crate's module tree: module path → file.
#[derive(Default)]
pub struct Tree {
    pub modules: BTreeMap<Vec<String>, PathBuf>,
}

/// The `mod x;` declarations of a file: (name, `#[path]` value).
fn declared_mods(src: &str) -> Vec<(String, Option<String>)> {
    let mut out = Vec::new();
    let mut path_attr: Option<String> = None;
    for line in src.lines() {
        let t = line.trim();
        if let Some(rest) = t.strip_prefix("#[path = \"") {
            path_attr = rest.split('"').next().map(str::to_string);
            continue;
        }
        let decl = t
            .trim_start_matches("pub(crate) ")
            .trim_start_matches("pub(super) ")
            .trim_start_matches("pub ");
        if let Some(name) = decl.strip_prefix("mod ").and_then(|r| r.strip_suffix(';')) {
            out.push((name.trim().to_string(), path_attr.take()));
        } else if !t.starts_with("#[") {
            path_attr = None;
        }
    }
    out
}

/// Adds `file` (module `path`) and the modules it declares to `tree`.
fn walk(tree: &mut Tree, file: &Path, path: Vec<String>) {
    let Ok(src) = std::fs::read_to_string(file) else {
        return;
    };
    let dir = file.parent().unwrap().to_path_buf();
    let stem = file.file_stem().unwrap().to_string_lossy().to_string();
    let owns_dir = matches!(stem.as_str(), "mod" | "lib" | "main") || path.is_empty();
    let child_dir = if owns_dir {
        dir.clone()
    } else {
        dir.join(&stem)
    };
    tree.modules.insert(path.clone(), file.to_path_buf());
    for (name, attr) in declared_mods(&src) {
        let f = match attr {
            Some(p) => dir.join(p),
            None => {
                let flat = child_dir.join(format!("{name}.rs"));
                if flat.is_file() {
                    flat
                } else {
                    child_dir.join(&name).join("mod.rs")
                }
            }
        };
        let mut p = path.clone();
        p.push(name);
        walk(tree, &f, p);
    }
}

/// The module trees of every crate root of the workspace members.
fn trees() -> Vec<Tree> {
    let r = root();
    let mut members: Vec<PathBuf> = vec![
        r.clone(),
        r.join("host-tests"),
        r.join("xtask"),
        r.join("hil"),
    ];
    for e in std::fs::read_dir(r.join("crates")).unwrap() {
        members.push(e.unwrap().path());
    }
    let mut out = Vec::new();
    for m in members {
        let src = m.join("src");
        let mut roots = vec![src.join("lib.rs"), src.join("main.rs")];
        if let Ok(bins) = std::fs::read_dir(src.join("bin")) {
            roots.extend(bins.map(|e| e.unwrap().path()));
        }
        for r in roots.into_iter().filter(|p| p.is_file()) {
            let mut t = Tree::default();
            walk(&mut t, &r, Vec::new());
            out.push(t);
        }
    }
    out
}

/// The module a path (from `at`) names: the longest prefix that is a
/// module of the tree; `None` for paths outside the crate.
fn resolve(tree: &Tree, at: &[String], segs: &[String]) -> Option<Vec<String>> {
    let (mut base, mut rest) = match segs.first()?.as_str() {
        "crate" => (Vec::new(), &segs[1..]),
        "self" => (at.to_vec(), &segs[1..]),
        "super" => {
            let mut b = at.to_vec();
            let mut k = 0;
            while segs.get(k).map(String::as_str) == Some("super") {
                b.pop()?;
                k += 1;
            }
            (b, &segs[k..])
        }
        first => {
            let mut child = at.to_vec();
            child.push(first.to_string());
            if !tree.modules.contains_key(&child) {
                return None;
            }
            (at.to_vec(), segs)
        }
    };
    while let Some(s) = rest.first() {
        let mut next = base.clone();
        next.push(s.clone());
        if !tree.modules.contains_key(&next) {
            break;
        }
        base = next;
        rest = &rest[1..];
    }
    Some(base)
}

/// The paths of a `use` tree starting at `toks[i]`; returns them and the
/// index after the tree.
fn use_tree(toks: &[Tok], mut i: usize, prefix: Vec<String>, out: &mut Vec<Vec<String>>) -> usize {
    let mut p = prefix;
    while i < toks.len() {
        match &toks[i] {
            // `self` in a group names the module before it.
            Tok::Ident(s) if s == "self" && !p.is_empty() => {}
            Tok::Ident(s) if s != "as" => p.push(s.clone()),
            Tok::Ident(_) => i += 1, // `as alias`: skip the alias
            Tok::Path => {}
            Tok::Punct('{') => {
                loop {
                    i = use_tree(toks, i + 1, p.clone(), out);
                    if toks.get(i) != Some(&Tok::Punct(',')) {
                        break;
                    }
                }
                return i + 1;
            }
            Tok::Punct('*') => {}
            _ => {
                out.push(p);
                return i;
            }
        }
        i += 1;
    }
    out.push(p);
    i
}

/// The modules (of `tree`) the file of module `me` references.
pub fn references(tree: &Tree, me: &[String], toks: &[Tok]) -> BTreeSet<Vec<String>> {
    let mut out = BTreeSet::new();
    // Inline `mod x {` blocks: (name, brace depth inside it).
    let mut inline: Vec<(String, usize)> = Vec::new();
    let mut depth = 0usize;
    let mut i = 0;
    while i < toks.len() {
        let mut at = me.to_vec();
        at.extend(inline.iter().map(|(n, _)| n.clone()));
        let prev_path = i > 0 && matches!(toks[i - 1], Tok::Path | Tok::Punct('$'));
        match &toks[i] {
            Tok::Punct('{') => depth += 1,
            Tok::Punct('}') => {
                if inline.last().is_some_and(|(_, d)| *d == depth) {
                    inline.pop();
                }
                depth = depth.saturating_sub(1);
            }
            Tok::Ident(k) if k == "mod" => {
                if let (Some(Tok::Ident(n)), Some(Tok::Punct('{'))) =
                    (toks.get(i + 1), toks.get(i + 2))
                {
                    inline.push((n.clone(), depth + 1));
                }
            }
            Tok::Ident(k) if k == "use" && !prev_path => {
                let mut paths = Vec::new();
                i = use_tree(toks, i + 1, Vec::new(), &mut paths);
                out.extend(paths.iter().filter_map(|p| resolve(tree, &at, p)));
                continue;
            }
            Tok::Ident(s) if !prev_path && toks.get(i + 1) == Some(&Tok::Path) => {
                let mut segs = vec![s.clone()];
                let mut j = i + 1;
                while let (Some(Tok::Path), Some(Tok::Ident(n))) = (toks.get(j), toks.get(j + 1)) {
                    segs.push(n.clone());
                    j += 2;
                }
                out.extend(resolve(tree, &at, &segs));
                i = j;
                continue;
            }
            _ => {}
        }
        i += 1;
    }
    out
}

/// Edges file → file of every crate (paths relative to the workspace
/// root), and the pairs of files of which one is a module nested in the
/// other's (a parent and its child, `mod x;`).
pub type Graph = BTreeMap<PathBuf, BTreeSet<PathBuf>>;

/// [`Graph`] of the workspace, and its nested pairs (ordered).
pub fn graph() -> (Graph, BTreeSet<(PathBuf, PathBuf)>) {
    graph_of(&|t| t)
}

/// [`graph`] with each file's tokens passed through `prepare` first (to
/// leave out its test modules, say).
pub fn graph_of(prepare: &dyn Fn(Vec<Tok>) -> Vec<Tok>) -> (Graph, BTreeSet<(PathBuf, PathBuf)>) {
    let r = root().canonicalize().unwrap();
    let rel = |p: &Path| {
        p.canonicalize()
            .unwrap_or_else(|_| p.to_path_buf())
            .strip_prefix(&r)
            .map(Path::to_path_buf)
            .unwrap_or_else(|_| p.to_path_buf())
    };
    let mut g: Graph = BTreeMap::new();
    let mut nested = BTreeSet::new();
    for t in trees() {
        for (outer, f) in &t.modules {
            for (inner, h) in &t.modules {
                if inner.len() > outer.len() && inner.starts_with(outer) {
                    let (a, b) = (rel(f), rel(h));
                    nested.insert(if a < b { (a, b) } else { (b, a) });
                }
            }
        }
        for (me, file) in &t.modules {
            let src = std::fs::read_to_string(file).unwrap();
            let from = rel(file);
            for m in references(&t, me, &prepare(tokens(&src))) {
                let to = rel(&t.modules[&m]);
                if to != from {
                    g.entry(from.clone()).or_default().insert(to);
                }
            }
            g.entry(from).or_default();
        }
    }
    (g, nested)
}
