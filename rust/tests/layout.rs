//! The crate's layout: the dependencies between its top-level modules point one way. A node is
//! a module under `rust/` (a file or a directory), except that each module of `structures/` is
//! a node of its own: the directory only groups them. An edge is a `crate::` path in a module's
//! code (comments and `#[cfg(test)]` modules left out), through `structures`' re-exports to the
//! module that defines the item.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn source_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("rust")
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The node a file belongs to, or None for the crate root and the test modules (`rust/tests/`,
/// and a module's own `tests.rs`).
fn node_of(relative: &Path) -> Option<String> {
    let mut parts: Vec<String> = relative
        .with_extension("")
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    if parts.last().is_some_and(|p| p == "mod") {
        parts.pop();
    }
    match parts.as_slice() {
        [] => None,
        [root] if root == "lib" => None,
        _ if parts.iter().any(|p| p == "tests") => None,
        [first, second, ..] if first == "structures" => Some(format!("structures::{second}")),
        [first, ..] => Some(first.clone()),
    }
}

/// The code of a file: line comments and `#[cfg(test)]` modules removed (rustfmt closes such a
/// module with a `}` at the attribute's indentation).
fn code(text: &str) -> String {
    let mut out = String::new();
    let mut lines = text.lines();
    while let Some(line) = lines.next() {
        let trimmed = line.trim_start();
        if trimmed == "#[cfg(test)]" {
            let indent = &line[..line.len() - trimmed.len()];
            let next = lines.next().unwrap_or("");
            if next.trim_start().starts_with("mod ") && next.trim_end().ends_with('{') {
                let close = format!("{indent}}}");
                for l in lines.by_ref() {
                    if l == close {
                        break;
                    }
                }
                continue;
            }
            out.push_str(next.split("//").next().unwrap_or(""));
            out.push('\n');
            continue;
        }
        out.push_str(line.split("//").next().unwrap_or(""));
        out.push('\n');
    }
    out
}

fn identifier(s: &str) -> &str {
    let end = s
        .find(|c: char| !(c.is_alphanumeric() || c == '_'))
        .unwrap_or(s.len());
    &s[..end]
}

/// The entries of a `{ … }` group that starts `s` (after the brace), split at its top-level
/// commas.
fn group(s: &str) -> Vec<&str> {
    let (mut depth, mut start, mut out) = (0usize, 0, Vec::new());
    for (i, c) in s.char_indices() {
        match c {
            '{' => depth += 1,
            '}' if depth == 0 => {
                out.push(&s[start..i]);
                return out;
            }
            '}' => depth -= 1,
            ',' if depth == 0 => {
                out.push(&s[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    out
}

struct Crate {
    nodes: BTreeSet<String>,
    /// Items `structures` re-exports, by the module that defines them.
    reexports: BTreeMap<String, String>,
}

impl Crate {
    /// The nodes a path after `crate::` names (several for a group).
    fn targets(&self, path: &str, out: &mut BTreeSet<String>) {
        let path = path.trim_start();
        if let Some(rest) = path.strip_prefix('{') {
            for entry in group(rest) {
                self.targets(entry, out);
            }
            return;
        }
        let first = identifier(path);
        if first == "structures" {
            let rest = path[first.len()..].trim_start();
            let Some(rest) = rest.strip_prefix("::") else {
                return;
            };
            let rest = rest.trim_start();
            if let Some(inner) = rest.strip_prefix('{') {
                for entry in group(inner) {
                    self.structures_target(entry, out);
                }
            } else {
                self.structures_target(rest, out);
            }
        } else if self.nodes.contains(first) {
            out.insert(first.to_string());
        }
    }

    fn structures_target(&self, path: &str, out: &mut BTreeSet<String>) {
        let name = identifier(path.trim_start());
        let node = format!("structures::{name}");
        if self.nodes.contains(&node) {
            out.insert(node);
        } else if let Some(module) = self.reexports.get(name) {
            out.insert(format!("structures::{module}"));
        }
    }
}

/// Every node and the nodes its code names.
fn dependencies() -> BTreeMap<String, BTreeSet<String>> {
    let root = source_root();
    let mut files = Vec::new();
    rust_files(&root, &mut files);
    let mut by_node: BTreeMap<String, Vec<PathBuf>> = BTreeMap::new();
    for f in files {
        if let Some(node) = node_of(f.strip_prefix(&root).unwrap()) {
            by_node.entry(node).or_default().push(f);
        }
    }
    let mut reexports = BTreeMap::new();
    let structures = std::fs::read_to_string(root.join("structures/mod.rs")).unwrap();
    for stmt in code(&structures).split(';') {
        let Some(rest) = stmt.trim().strip_prefix("pub use ") else {
            continue;
        };
        let module = identifier(rest);
        let tail = rest[module.len()..].trim_start_matches("::").trim();
        let items = match tail.strip_prefix('{') {
            Some(inner) => group(inner),
            None => vec![tail],
        };
        for item in items {
            let name = identifier(item.trim());
            if !name.is_empty() {
                reexports.insert(name.to_string(), module.to_string());
            }
        }
    }
    let krate = Crate {
        nodes: by_node.keys().cloned().collect(),
        reexports,
    };
    let mut edges = BTreeMap::new();
    for (node, files) in &by_node {
        let mut out = BTreeSet::new();
        for f in files {
            let text = code(&std::fs::read_to_string(f).unwrap());
            for (i, _) in text.match_indices("crate::") {
                // `$crate::` in a macro names the crate root, not a module.
                if text[..i].ends_with('$') {
                    continue;
                }
                krate.targets(&text[i + "crate::".len()..], &mut out);
            }
        }
        out.remove(node);
        edges.insert(node.clone(), out);
    }
    edges
}

/// The nodes `start` reaches.
fn reach(edges: &BTreeMap<String, BTreeSet<String>>, start: &str) -> BTreeSet<String> {
    let mut seen = BTreeSet::new();
    let mut todo = vec![start.to_string()];
    while let Some(n) = todo.pop() {
        for m in &edges[&n] {
            if seen.insert(m.clone()) {
                todo.push(m.clone());
            }
        }
    }
    seen
}

#[test]
fn the_parser_sees_the_dependencies() {
    let edges = dependencies();
    for (from, to) in [
        ("stepper", "realization"),
        ("stepper", "structures::lie_groupoid"),
        ("model", "structures::log_canonical"),
        ("lanes", "classical"),
        ("generating", "isa"),
    ] {
        assert!(
            edges[from].contains(to),
            "{from} -> {to} not seen: {edges:?}"
        );
    }
    // A group over structures' re-exports resolves to the defining modules.
    let mut out = BTreeSet::new();
    let krate = Crate {
        nodes: edges.keys().cloned().collect(),
        reexports: [("LogCanonical".to_string(), "log_canonical".to_string())].into(),
    };
    krate.targets(
        "structures::{LogCanonical, lie_poisson::{VectorField}}",
        &mut out,
    );
    let expect = ["structures::lie_poisson", "structures::log_canonical"];
    assert_eq!(out, expect.iter().map(|s| s.to_string()).collect());
}

#[test]
fn no_module_cycles() {
    let edges = dependencies();
    let cycles: Vec<String> = edges
        .iter()
        .flat_map(|(a, to)| to.iter().map(move |b| (a, b)))
        .filter(|(a, b)| reach(&edges, b).contains(*a))
        .map(|(a, b)| format!("{a} -> {b}"))
        .collect();
    assert!(
        cycles.is_empty(),
        "edges on a module cycle (each target reaches its source back): {cycles:?}"
    );
}
