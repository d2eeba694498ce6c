//! The workspace's source files depend on each other one way: no file reaches, through
//! the modules it names, back to itself. A circle between two files means neither can
//! be read, tested or moved without the other; code both sides need belongs below both.
//!
//! A file's dependencies are the modules its paths name (`use` trees, and `crate::`,
//! `super::`, `self::` and child-module paths in its code), each resolved to the file
//! of the deepest module that has one. A module naming its own submodules is not
//! counted: a parent declares and assembles its children, and they may use it.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Module path (within one crate) → file.
type Files = BTreeMap<Vec<String>, PathBuf>;

/// The source roots of the workspace's crates and test binaries.
const ROOTS: &[&str] = &[
    "src",
    "render/src",
    "protocol/src",
    "transport/src",
    "scheduler/src",
    "verify/src",
    "httpd/src",
    "coordinator/src",
    "worker/src",
    "localfarm/src",
    "bench/src",
    "tests/end_to_end",
    "render/tests/renderer",
    "scheduler/tests/scheduling",
    "protocol/tests/wire_format",
];

#[test]
fn no_source_file_depends_on_itself_through_others() {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut circles = Vec::new();
    for root in ROOTS {
        let root = workspace.join(root);
        assert!(root.is_dir(), "{} is not a directory", root.display());
        let files = modules(&root);
        assert!(files.len() > 1, "{}: no modules found", root.display());
        let edges: BTreeMap<&Vec<String>, BTreeSet<&Vec<String>>> = files
            .iter()
            .map(|(module, path)| (module, dependencies(module, path, &files)))
            .collect();
        for circle in strongly_connected(&edges) {
            let names: Vec<String> = circle.iter().map(|m| name(m)).collect();
            circles.push(format!("{}: {}", root.display(), names.join(" ↔ ")));
        }
    }
    assert!(circles.is_empty(), "import circles: {circles:#?}");
}

/// The detector itself finds a circle, a parent's use of its child is not one, and a
/// child's use of its parent is not one either.
#[test]
fn the_detector_finds_a_circle_between_siblings_only() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    std::fs::create_dir(root.join("server")).unwrap();
    let write = |file: &str, text: &str| std::fs::write(root.join(file), text).unwrap();
    write("lib.rs", "mod http;\nmod server;\nuse server::Server;\n");
    write(
        "server.rs",
        "mod core;\nuse self::core::Core;\nfn f() { crate::http::spawn(); }\n",
    );
    write(
        "server/core.rs",
        "use super::Shared;\nuse crate::{wire, http::{self, x}};\n",
    );
    write("http.rs", "use crate::server::Observer;\n");
    let files = modules(root);
    let edges: BTreeMap<&Vec<String>, BTreeSet<&Vec<String>>> = files
        .iter()
        .map(|(module, path)| (module, dependencies(module, path, &files)))
        .collect();
    let circles: Vec<Vec<String>> = strongly_connected(&edges)
        .into_iter()
        .map(|c| c.iter().map(|m| name(m)).collect())
        .collect();
    assert_eq!(
        circles,
        vec![vec!["http".to_string(), "server".to_string()]]
    );
    let core = &files
        .keys()
        .find(|m| name(m) == "server/core")
        .unwrap()
        .clone();
    let named: Vec<String> = edges[core].iter().map(|m| name(m)).collect();
    assert_eq!(named, ["lib", "http", "server"]);
}

fn name(module: &[String]) -> String {
    if module.is_empty() {
        "lib".to_string()
    } else {
        module.join("/")
    }
}

/// Every `.rs` file under `root`, by its module path (`a/mod.rs` and `a.rs` are `a`;
/// `lib.rs` and `main.rs` the root).
fn modules(root: &Path) -> Files {
    let mut files = Files::new();
    let mut dirs = vec![root.to_path_buf()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let relative = path.strip_prefix(root).unwrap().with_extension("");
                let mut module: Vec<String> = relative
                    .iter()
                    .map(|p| p.to_string_lossy().into_owned())
                    .collect();
                if matches!(module.last().map(String::as_str), Some("mod")) {
                    module.pop();
                }
                if matches!(module.as_slice(), [only] if only == "lib" || only == "main") {
                    module.clear();
                }
                files.insert(module, path);
            }
        }
    }
    files
}

/// The modules with a file that `module` (in `path`) names, but itself and its own
/// submodules.
fn dependencies<'a>(module: &[String], path: &Path, files: &'a Files) -> BTreeSet<&'a Vec<String>> {
    let code = without_comments(&std::fs::read_to_string(path).unwrap());
    // A file's unit tests (`mod tests { use super::*; }`) name the file's own module,
    // which the paths below would take for its parent.
    let code = match code.find("#[cfg(test)]\nmod tests") {
        Some(at) => code[..at].to_string(),
        None => code,
    };
    let mut paths: Vec<Vec<String>> = Vec::new();
    // `use` trees, braces expanded.
    for statement in code.split(';') {
        if let Some(at) = find_word(statement, "use") {
            // One space between words (`a as b`), none around punctuation.
            let mut tree = statement[at + 3..]
                .split_whitespace()
                .collect::<Vec<_>>()
                .join(" ");
            for mark in ["::", "{", "}", ","] {
                tree = tree
                    .replace(&format!(" {mark}"), mark)
                    .replace(&format!("{mark} "), mark);
            }
            expand(&[], &tree, &mut paths);
        }
    }
    // Paths in the code, and a child module's name used as a path.
    let children: BTreeSet<&String> = files
        .keys()
        .filter(|m| m.len() == module.len() + 1 && m.starts_with(module))
        .map(|m| m.last().unwrap())
        .collect();
    for (at, word) in words(&code) {
        let rest = &code[at + word.len()..];
        if !rest.starts_with("::") {
            continue;
        }
        if matches!(word, "crate" | "super" | "self") || children.contains(&word.to_string()) {
            let mut segments = vec![word.to_string()];
            let mut rest = rest;
            while let Some(next) = rest.strip_prefix("::") {
                let len = next
                    .find(|c: char| !(c.is_alphanumeric() || c == '_'))
                    .unwrap_or(next.len());
                if len == 0 {
                    break;
                }
                segments.push(next[..len].to_string());
                rest = &next[len..];
            }
            if !matches!(word, "crate" | "super" | "self") {
                segments.insert(0, "self".to_string());
            }
            paths.push(segments);
        }
    }
    let mut found = BTreeSet::new();
    for segments in paths {
        let (mut base, mut rest): (Vec<String>, &[String]) = match segments[0].as_str() {
            "crate" => (Vec::new(), &segments[1..]),
            "self" => (module.to_vec(), &segments[1..]),
            "super" => (
                module[..module.len().saturating_sub(1)].to_vec(),
                &segments[1..],
            ),
            _ => continue,
        };
        while let Some((first, tail)) = rest.split_first() {
            if first != "super" {
                break;
            }
            base.pop();
            rest = tail;
        }
        base.extend(rest.iter().filter(|s| *s != "self" && *s != "*").cloned());
        let Some(target) = (0..=base.len())
            .rev()
            .find_map(|k| files.get_key_value(&base[..k]).map(|(m, _)| m))
        else {
            continue;
        };
        if target.as_slice() != module && !target.starts_with(module) {
            found.insert(target);
        }
    }
    found
}

/// The paths of a `use` tree (`a::{b, c::{d, e}}`), each as its segments.
fn expand(prefix: &[String], tree: &str, out: &mut Vec<Vec<String>>) {
    let tree = tree.trim_start_matches("::");
    if let Some(open) = tree.find('{') {
        let mut head = prefix.to_vec();
        head.extend(
            tree[..open]
                .split("::")
                .filter(|s| !s.is_empty())
                .map(str::to_string),
        );
        // Not a `use` tree (the word in a string, say): nothing to take from it.
        let Some(close) = tree.rfind('}').filter(|&close| close > open) else {
            return;
        };
        let inner = &tree[open + 1..close];
        let (mut depth, mut start) = (0, 0);
        for (i, c) in inner.char_indices() {
            match c {
                '{' => depth += 1,
                '}' => depth -= 1,
                ',' if depth == 0 => {
                    expand(&head, &inner[start..i], out);
                    start = i + 1;
                }
                _ => {}
            }
        }
        expand(&head, &inner[start..], out);
    } else {
        let name = tree.split(" as ").next().unwrap_or(tree).trim();
        let mut path = prefix.to_vec();
        path.extend(
            name.split("::")
                .filter(|s| !s.is_empty())
                .map(str::to_string),
        );
        if !path.is_empty() {
            out.push(path);
        }
    }
}

/// The code without its comments (line comments, doc comments and block comments).
fn without_comments(code: &str) -> String {
    let mut out = String::with_capacity(code.len());
    let mut chars = code.chars().peekable();
    while let Some(c) = chars.next() {
        if c == '/' && chars.peek() == Some(&'/') {
            for c in chars.by_ref() {
                if c == '\n' {
                    out.push('\n');
                    break;
                }
            }
        } else if c == '/' && chars.peek() == Some(&'*') {
            chars.next();
            let mut last = ' ';
            for c in chars.by_ref() {
                if last == '*' && c == '/' {
                    break;
                }
                last = c;
            }
        } else {
            out.push(c);
        }
    }
    out
}

/// Each identifier of `code` with its byte offset.
fn words(code: &str) -> impl Iterator<Item = (usize, &str)> {
    let mut at = 0;
    std::iter::from_fn(move || {
        let bytes = code.as_bytes();
        while at < bytes.len() {
            let c = bytes[at];
            if c.is_ascii_alphabetic() || c == b'_' {
                let start = at;
                while at < bytes.len() && (bytes[at].is_ascii_alphanumeric() || bytes[at] == b'_') {
                    at += 1;
                }
                return Some((start, &code[start..at]));
            }
            at += 1;
        }
        None
    })
}

/// Where `word` first stands alone in `text`.
fn find_word(text: &str, word: &str) -> Option<usize> {
    words(text).find(|(_, w)| *w == word).map(|(at, _)| at)
}

/// The circles of the graph: its strongly connected parts of more than one file.
fn strongly_connected<'a>(
    edges: &BTreeMap<&'a Vec<String>, BTreeSet<&'a Vec<String>>>,
) -> Vec<Vec<&'a Vec<String>>> {
    // Two passes of depth-first search (Kosaraju), iterative.
    let nodes: Vec<&Vec<String>> = edges.keys().copied().collect();
    let mut order = Vec::new();
    let mut seen = BTreeSet::new();
    for &start in &nodes {
        if !seen.insert(start) {
            continue;
        }
        let mut stack = vec![(start, edges[start].iter().copied().collect::<Vec<_>>())];
        while let Some((node, next)) = stack.last_mut() {
            if let Some(to) = next.pop() {
                if edges.contains_key(to) && seen.insert(to) {
                    let more = edges[to].iter().copied().collect();
                    stack.push((to, more));
                }
            } else {
                order.push(*node);
                stack.pop();
            }
        }
    }
    let mut reverse: BTreeMap<&Vec<String>, Vec<&Vec<String>>> = BTreeMap::new();
    for (&from, tos) in edges {
        for &to in tos {
            reverse.entry(to).or_default().push(from);
        }
    }
    let mut assigned = BTreeSet::new();
    let mut circles = Vec::new();
    for &start in order.iter().rev() {
        if !assigned.insert(start) {
            continue;
        }
        let mut part = vec![start];
        let mut stack = vec![start];
        while let Some(node) = stack.pop() {
            for &from in reverse.get(node).into_iter().flatten() {
                if assigned.insert(from) {
                    part.push(from);
                    stack.push(from);
                }
            }
        }
        if part.len() > 1 {
            part.sort();
            circles.push(part);
        }
    }
    circles
}
