//! Import circles between the modules of one crate, for `cargo xtask deps-check`.
//!
//! A small parser, not a compiler: each `.rs` file under a crate's `src/` is a module
//! (`lib.rs`/`main.rs` the root, `a/mod.rs` and `a.rs` the module `a`, `a/b.rs` the module
//! `a::b`). Its edges are the paths it names that start with `crate::`, `super::` or `self::`
//! (in `use` trees, braces expanded, and inline in code; comments and string literals skipped),
//! and in a module with children the `use child::…` paths. A path goes to the longest module
//! prefix it names; when that module only re-exports the item (`pub use x::Item`), the edge
//! follows the re-export, so a facade (`lib.rs`, a `mod.rs`) does not join its children into a
//! circle. Edges into a module's own descendants from a facade are the facade's re-exports and
//! do not count. Test modules inside a file (`#[cfg(test)] mod tests`) are part of the file,
//! as the compiler sees them. A circle is reported as the modules along it.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

/// One module: its path (`["estimate", "run"]`; empty for the root) and its text.
struct Module {
    path: Vec<String>,
    text: String,
}

/// The module path of a file under `src`.
fn module_path(src: &Path, file: &Path) -> Option<Vec<String>> {
    let rel = file.strip_prefix(src).ok()?;
    let mut parts: Vec<String> = rel
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    let last = parts.pop()?;
    let stem = last.strip_suffix(".rs")?;
    match stem {
        "lib" | "main" if parts.is_empty() => {}
        "mod" => {}
        _ => parts.push(stem.to_string()),
    }
    Some(parts)
}

fn rs_files(dir: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            // `src/bin/` holds separate crates.
            if p.file_name().is_some_and(|n| n == "bin") && p.parent() == Some(dir) {
                continue;
            }
            rs_files(&p, out)?;
        } else if p.extension().is_some_and(|e| e == "rs") {
            out.push(p);
        }
    }
    Ok(())
}

/// The text with comments, string and character literals blanked (newlines kept).
fn strip_comments_and_strings(text: &str) -> String {
    let b: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        let next = b.get(i + 1).copied();
        if c == '/' && next == Some('/') {
            while i < b.len() && b[i] != '\n' {
                i += 1;
            }
        } else if c == '/' && next == Some('*') {
            let mut depth = 1;
            i += 2;
            while i < b.len() && depth > 0 {
                if b[i] == '/' && b.get(i + 1) == Some(&'*') {
                    depth += 1;
                    i += 2;
                } else if b[i] == '*' && b.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    i += 2;
                } else {
                    if b[i] == '\n' {
                        out.push('\n');
                    }
                    i += 1;
                }
            }
            out.push(' ');
        } else if c == 'r' && (next == Some('"') || next == Some('#')) && !ident_char_before(&b, i)
        {
            // Raw string r"…" or r#"…"#.
            let mut j = i + 1;
            let mut hashes = 0;
            while b.get(j) == Some(&'#') {
                hashes += 1;
                j += 1;
            }
            if b.get(j) != Some(&'"') {
                out.push(c);
                i += 1;
                continue;
            }
            j += 1;
            loop {
                if j >= b.len() {
                    break;
                }
                if b[j] == '"' && (0..hashes).all(|h| b.get(j + 1 + h) == Some(&'#')) {
                    j += 1 + hashes;
                    break;
                }
                j += 1;
            }
            out.push(' ');
            i = j;
        } else if c == '"' {
            i += 1;
            while i < b.len() && b[i] != '"' {
                if b[i] == '\\' {
                    i += 1;
                }
                i += 1;
            }
            i += 1;
            out.push(' ');
        } else if c == '\'' {
            // A char literal ('a', '\n', '\'') or a lifetime ('a): only the former is skipped.
            if next == Some('\\') {
                let mut j = i + 2;
                while j < b.len() && b[j] != '\'' {
                    j += 1;
                }
                i = j + 1;
                out.push(' ');
            } else if b.get(i + 2) == Some(&'\'') {
                i += 3;
                out.push(' ');
            } else {
                out.push(c);
                i += 1;
            }
        } else {
            out.push(c);
            i += 1;
        }
    }
    out
}

fn ident_char_before(b: &[char], i: usize) -> bool {
    i > 0 && (b[i - 1].is_alphanumeric() || b[i - 1] == '_')
}

/// The paths of one `use` tree (`a::{b, c::{d as e}, self}` → `a::b`, `a::c::d`, `a`).
fn expand_use_tree(tree: &str) -> Vec<Vec<String>> {
    fn split_top(s: &str) -> Vec<&str> {
        let mut parts = Vec::new();
        let (mut depth, mut start) = (0, 0);
        for (i, c) in s.char_indices() {
            match c {
                '{' => depth += 1,
                '}' => depth -= 1,
                ',' if depth == 0 => {
                    parts.push(&s[start..i]);
                    start = i + 1;
                }
                _ => {}
            }
        }
        parts.push(&s[start..]);
        parts
    }
    let tree = tree.split_whitespace().collect::<Vec<_>>().join(" ");
    let mut out = Vec::new();
    for part in split_top(&tree) {
        let part = part.trim();
        if part.is_empty() {
            continue;
        }
        if let Some(open) = part.find('{') {
            let prefix: Vec<String> = part[..open]
                .split("::")
                .map(str::trim)
                .filter(|s| !s.is_empty())
                .map(str::to_string)
                .collect();
            let inner = part[open + 1..].trim_end();
            let inner = inner.strip_suffix('}').unwrap_or(inner);
            for mut rest in expand_use_tree(inner) {
                if rest.first().is_some_and(|s| s == "self") {
                    rest.remove(0);
                }
                let mut p = prefix.clone();
                p.extend(rest);
                out.push(p);
            }
        } else {
            let name = part.split(" as ").next().unwrap_or(part);
            out.push(
                name.split("::")
                    .map(str::trim)
                    .filter(|s| !s.is_empty())
                    .map(str::to_string)
                    .collect(),
            );
        }
    }
    out
}

/// `use` statements of a (stripped) text: (is `pub`, the tree).
fn use_statements(text: &str) -> Vec<(bool, String)> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(pos) = find_word(rest, "use") {
        let before = rest[..pos].trim_end();
        let public = before.ends_with("pub") || before.ends_with(')') && before.contains("pub(");
        let after = &rest[pos + 3..];
        let Some(end) = after.find(';') else { break };
        out.push((public, after[..end].to_string()));
        rest = &after[end + 1..];
    }
    out
}

/// The byte position of `word` standing alone (not part of an identifier).
fn find_word(text: &str, word: &str) -> Option<usize> {
    let bytes = text.as_bytes();
    let mut from = 0;
    while let Some(p) = text[from..].find(word) {
        let at = from + p;
        let end = at + word.len();
        let before_ok = at == 0 || !is_ident_byte(bytes[at - 1]);
        let after_ok = end >= bytes.len() || !is_ident_byte(bytes[end]);
        if before_ok && after_ok {
            return Some(at);
        }
        from = end;
    }
    None
}

fn is_ident_byte(c: u8) -> bool {
    c.is_ascii_alphanumeric() || c == b'_'
}

/// Inline paths starting with `crate::`, `super::` or `self::` (outside `use` statements too).
fn inline_paths(text: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let bytes = text.as_bytes();
    for head in ["crate::", "super::", "self::"] {
        let mut from = 0;
        while let Some(p) = text[from..].find(head) {
            let at = from + p;
            from = at + head.len();
            if at > 0 && (is_ident_byte(bytes[at - 1]) || bytes[at - 1] == b':') {
                continue;
            }
            let mut path = vec![head.trim_end_matches(':').to_string()];
            let mut i = at + head.len();
            loop {
                // `super::super::x`
                let start = i;
                while i < bytes.len() && is_ident_byte(bytes[i]) {
                    i += 1;
                }
                if i == start {
                    break;
                }
                path.push(text[start..i].to_string());
                if text[i..].starts_with("::") && !text[i + 2..].starts_with('{') {
                    i += 2;
                } else {
                    break;
                }
            }
            out.push(path);
        }
    }
    out
}

/// Resolves a path named in module `from` to an absolute path (without `crate`).
fn absolute(from: &[String], path: &[String], children: &BTreeSet<String>) -> Option<Vec<String>> {
    let first = path.first()?;
    match first.as_str() {
        "crate" => Some(path[1..].to_vec()),
        "self" => {
            let mut p = from.to_vec();
            p.extend_from_slice(&path[1..]);
            Some(p)
        }
        "super" => {
            let mut base = from.to_vec();
            let mut i = 0;
            while path.get(i).is_some_and(|s| s == "super") {
                base.pop()?;
                i += 1;
            }
            base.extend_from_slice(&path[i..]);
            Some(base)
        }
        name if children.contains(name) => {
            let mut p = from.to_vec();
            p.extend_from_slice(path);
            Some(p)
        }
        _ => None,
    }
}

/// The circles of the crate whose sources are in `src`: each as the module names along it.
pub fn crate_cycles(src: &Path) -> Result<Vec<Circle>> {
    let mut files = Vec::new();
    rs_files(src, &mut files)?;
    let mut modules = Vec::new();
    for file in files {
        let Some(path) = module_path(src, &file) else {
            continue;
        };
        let text = std::fs::read_to_string(&file)
            .with_context(|| format!("reading {}", file.display()))?;
        modules.push(Module {
            path,
            text: strip_comments_and_strings(&text),
        });
    }
    Ok(cycles_of(&modules))
}

fn cycles_of(modules: &[Module]) -> Vec<Circle> {
    let known: BTreeSet<Vec<String>> = modules.iter().map(|m| m.path.clone()).collect();
    let children_of = |p: &[String]| -> BTreeSet<String> {
        known
            .iter()
            .filter(|k| k.len() == p.len() + 1 && k.starts_with(p))
            .filter_map(|k| k.last().cloned())
            .collect()
    };
    // Re-exports: module → item name → the absolute path it re-exports.
    let mut reexports: HashMap<Vec<String>, HashMap<String, Vec<String>>> = HashMap::new();
    for m in modules {
        let children = children_of(&m.path);
        for (public, tree) in use_statements(&m.text) {
            if !public {
                continue;
            }
            for path in expand_use_tree(&tree) {
                if let (Some(abs), Some(name)) = (absolute(&m.path, &path, &children), path.last())
                {
                    reexports
                        .entry(m.path.clone())
                        .or_default()
                        .insert(name.clone(), abs);
                }
            }
        }
    }
    // The module an absolute path lands in, following re-exports (bounded).
    let resolve = |abs: &[String]| -> Option<Vec<String>> {
        let mut abs = abs.to_vec();
        for _ in 0..8 {
            let module = (0..=abs.len())
                .rev()
                .map(|k| abs[..k].to_vec())
                .find(|p| known.contains(p))?;
            let item = abs.get(module.len());
            match item.and_then(|i| reexports.get(&module).and_then(|r| r.get(i))) {
                Some(target) if target != &abs => abs = target.clone(),
                _ => return Some(module),
            }
        }
        None
    };
    let mut edges: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = BTreeMap::new();
    // One path that makes each edge, for the report.
    let mut why: BTreeMap<(Vec<String>, Vec<String>), String> = BTreeMap::new();
    for m in modules {
        let children = children_of(&m.path);
        let mut paths: Vec<Vec<String>> = use_statements(&m.text)
            .into_iter()
            .flat_map(|(_, tree)| expand_use_tree(&tree))
            .collect();
        paths.extend(inline_paths(&m.text));
        for path in paths {
            let Some(abs) = absolute(&m.path, &path, &children) else {
                continue;
            };
            let Some(target) = resolve(&abs) else {
                continue;
            };
            // A module's own items, and a facade naming its descendants, are no edge.
            if target == m.path || target.starts_with(&m.path) {
                continue;
            }
            why.entry((m.path.clone(), target.clone()))
                .or_insert_with(|| path.join("::"));
            edges.entry(m.path.clone()).or_default().insert(target);
        }
    }
    let name = |p: &[String]| {
        if p.is_empty() {
            "crate".to_string()
        } else {
            p.join("::")
        }
    };
    strongly_connected(&known, &edges)
        .into_iter()
        .filter(|c| c.len() > 1)
        .map(|c| {
            let members: BTreeSet<&Vec<String>> = c.iter().collect();
            let mut edges_in = Vec::new();
            for a in &c {
                for b in edges.get(a).into_iter().flatten() {
                    if members.contains(b) {
                        let via = why
                            .get(&(a.clone(), b.clone()))
                            .cloned()
                            .unwrap_or_default();
                        edges_in.push(format!("{} → {} ({via})", name(a), name(b)));
                    }
                }
            }
            Circle {
                modules: c.iter().map(|p| name(p)).collect(),
                edges: edges_in,
            }
        })
        .collect()
}

/// A circle: its modules (sorted) and the edges between them, each with one path that makes
/// it.
#[derive(Debug)]
pub struct Circle {
    /// The modules along it.
    pub modules: Vec<String>,
    /// `a → b (the path a names)`.
    pub edges: Vec<String>,
}

/// Tarjan's strongly connected components (iterative), each sorted.
fn strongly_connected(
    nodes: &BTreeSet<Vec<String>>,
    edges: &BTreeMap<Vec<String>, BTreeSet<Vec<String>>>,
) -> Vec<Vec<Vec<String>>> {
    let ids: Vec<&Vec<String>> = nodes.iter().collect();
    let index_of: HashMap<&Vec<String>, usize> =
        ids.iter().enumerate().map(|(i, n)| (*n, i)).collect();
    let adj: Vec<Vec<usize>> = ids
        .iter()
        .map(|n| {
            edges
                .get(*n)
                .map(|t| t.iter().filter_map(|x| index_of.get(x).copied()).collect())
                .unwrap_or_default()
        })
        .collect();
    let n = ids.len();
    let (mut index, mut low) = (vec![usize::MAX; n], vec![0; n]);
    let mut on_stack = vec![false; n];
    let (mut stack, mut out) = (Vec::new(), Vec::new());
    let mut next = 0;
    for root in 0..n {
        if index[root] != usize::MAX {
            continue;
        }
        let mut work = vec![(root, 0usize)];
        index[root] = next;
        low[root] = next;
        next += 1;
        stack.push(root);
        on_stack[root] = true;
        while let Some(&mut (v, ref mut k)) = work.last_mut() {
            if let Some(&w) = adj[v].get(*k) {
                *k += 1;
                if index[w] == usize::MAX {
                    index[w] = next;
                    low[w] = next;
                    next += 1;
                    stack.push(w);
                    on_stack[w] = true;
                    work.push((w, 0));
                } else if on_stack[w] {
                    low[v] = low[v].min(index[w]);
                }
            } else {
                work.pop();
                if let Some(&(u, _)) = work.last() {
                    low[u] = low[u].min(low[v]);
                }
                if low[v] == index[v] {
                    let mut comp = Vec::new();
                    while let Some(w) = stack.pop() {
                        on_stack[w] = false;
                        comp.push(ids[w].clone());
                        if w == v {
                            break;
                        }
                    }
                    comp.sort();
                    out.push(comp);
                }
            }
        }
    }
    out
}

/// The circles of every crate in the workspace (`crates/*/src`, `xtask/src`), as lines.
pub fn workspace_cycles(root: &Path) -> Result<Vec<String>> {
    let mut srcs = Vec::new();
    for entry in std::fs::read_dir(root.join("crates")).context("reading crates/")? {
        let src = entry?.path().join("src");
        if src.is_dir() {
            srcs.push(src);
        }
    }
    srcs.push(root.join("xtask/src"));
    srcs.sort();
    let mut out = Vec::new();
    for src in srcs {
        let krate = src
            .parent()
            .and_then(Path::file_name)
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        for cycle in crate_cycles(&src)? {
            out.push(format!(
                "{krate}: {}\n      {}",
                cycle.modules.join(" ↔ "),
                cycle.edges.join("\n      ")
            ));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(circles: Vec<Circle>) -> Vec<Vec<String>> {
        circles.into_iter().map(|c| c.modules).collect()
    }

    fn module(path: &str, text: &str) -> Module {
        Module {
            path: path
                .split("::")
                .filter(|s| !s.is_empty())
                .map(str::to_string)
                .collect(),
            text: strip_comments_and_strings(text),
        }
    }

    #[test]
    fn a_circle_made_on_purpose_is_found() {
        let modules = [
            module("", "mod a; mod b; mod c;"),
            module("a", "use crate::b::Thing;"),
            module("b", "pub struct Thing; fn f() { crate::c::g(); }"),
            module("c", "use super::a::Other as O;"),
        ];
        assert_eq!(names(cycles_of(&modules)), vec![vec!["a", "b", "c"]]);
    }

    #[test]
    fn a_chain_is_no_circle() {
        let modules = [
            module("", "mod a; mod b; pub use a::Thing;"),
            module("a", "use crate::b::{x, y::{z}};"),
            module("b", "pub fn x() {}"),
        ];
        assert!(cycles_of(&modules).is_empty());
    }

    #[test]
    fn re_exports_are_followed_and_comments_and_strings_ignored() {
        // `b` names `crate::Thing`, which the root re-exports from `a`: the edge goes to `a`,
        // and `a` naming `b` only in a comment or a string is no edge.
        let modules = [
            module("", "mod a; mod b; pub use a::Thing; use b::helper;"),
            module(
                "a",
                "// crate::b::helper\nconst S: &str = \"crate::b::helper\"; pub struct Thing;",
            ),
            module("b", "use crate::Thing; pub fn helper() {}"),
        ];
        assert!(cycles_of(&modules).is_empty());
        let modules = [
            module("", "mod a; mod b; pub use a::Thing;"),
            module("a", "pub struct Thing; fn f() { crate::b::helper() }"),
            module("b", "use crate::Thing; pub fn helper() {}"),
        ];
        assert_eq!(names(cycles_of(&modules)), vec![vec!["a", "b"]]);
    }

    #[test]
    fn nested_modules_and_super_paths_resolve() {
        let modules = [
            module("", "mod est;"),
            module("est", "mod run; mod geo;"),
            module("est::run", "use super::geo::estimate; pub const W: u8 = 0;"),
            module("est::geo", "pub fn estimate() { let _ = super::run::W; }"),
        ];
        assert_eq!(
            names(cycles_of(&modules)),
            vec![vec!["est::geo", "est::run"]]
        );
    }

    #[test]
    fn use_trees_expand() {
        assert_eq!(
            expand_use_tree("crate::{a::{b, c as d}, e::{f::{g}}, self}"),
            vec![
                vec!["crate", "a", "b"],
                vec!["crate", "a", "c"],
                vec!["crate", "e", "f", "g"],
                vec!["crate"],
            ]
        );
    }

    #[test]
    fn this_workspace_is_read() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let found = workspace_cycles(&root);
        assert!(found.is_ok(), "{found:?}");
        for line in found.unwrap_or_default() {
            eprintln!("{line}");
        }
    }
}
