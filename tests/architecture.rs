//! The engine's layering rules (docs/architecture.md), checked on the source tree itself
//! so that breaking one fails the build's tests:
//!
//! 1. no file of `technique/<a>/` refers to `technique::<b>`, to the technique table or to
//!    the `technique` module's root (a technique sees only `technique::api` and the layers
//!    below it);
//! 2. `gpu`, `plan`, `atlas` and `scene` refer to no technique at all;
//! 3. the modules of `engine` form no import cycle (each technique and `technique::api`,
//!    `technique::table` count as modules of their own);
//! 4. the engine never refers to `service` (or to the CLI's `bench`).
//!
//! How: every `crate::…` and `super::…` path in `src/engine` is resolved to the engine
//! module it names (comments and string literals stripped first; `{…}` groups expanded one
//! level, which is all `rustfmt` writes). A path that leaves the engine is kept as
//! `crate::<name>`. A file's trailing `#[cfg(test)] mod tests` is not read (its `super::`
//! is the file itself). This reads text, not the compiler's name resolution: a glob import or
//! a macro could hide an edge, and the project writes neither across modules.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// A reference from one engine file to a module.
#[derive(Debug, Clone)]
struct Edge {
    file: String,
    from: String,
    to: String,
}

fn engine_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src/engine")
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).expect("src/engine is readable") {
        let p = e.expect("a directory entry").path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// Source text with comments and the contents of string and char literals removed.
fn strip(src: &str) -> String {
    let b = src.as_bytes();
    let mut out = String::with_capacity(src.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'/' && b.get(i + 1) == Some(&b'/') {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if b[i] == b'/' && b.get(i + 1) == Some(&b'*') {
            i += 2;
            while i + 1 < b.len() && !(b[i] == b'*' && b[i + 1] == b'/') {
                i += 1;
            }
            i += 2;
        } else if b[i] == b'r'
            && (b.get(i + 1) == Some(&b'"') || b.get(i + 1) == Some(&b'#'))
            && (i == 0 || !b[i - 1].is_ascii_alphanumeric())
        {
            // Raw string: r"…" or r#"…"#.
            let mut j = i + 1;
            let mut hashes = 0;
            while b.get(j) == Some(&b'#') {
                hashes += 1;
                j += 1;
            }
            if b.get(j) != Some(&b'"') {
                out.push(b[i] as char);
                i += 1;
                continue;
            }
            j += 1;
            loop {
                if j >= b.len() {
                    break;
                }
                if b[j] == b'"' && (0..hashes).all(|k| b.get(j + 1 + k) == Some(&b'#')) {
                    j += 1 + hashes;
                    break;
                }
                j += 1;
            }
            out.push_str("\"\"");
            i = j;
        } else if b[i] == b'"' {
            i += 1;
            while i < b.len() && b[i] != b'"' {
                if b[i] == b'\\' {
                    i += 1;
                }
                i += 1;
            }
            i += 1;
            out.push_str("\"\"");
        } else if b[i] == b'\'' && b.get(i + 2) == Some(&b'\'') {
            // 'x' (a lifetime has no closing quote two bytes on).
            i += 3;
        } else if b[i] == b'\'' && b.get(i + 1) == Some(&b'\\') {
            i += 2;
            while i < b.len() && b[i] != b'\'' {
                i += 1;
            }
            i += 1;
        } else {
            out.push(b[i] as char);
            i += 1;
        }
    }
    out
}

/// The module path of a file under src/engine: `technique/sdb/mod.rs` -> engine::technique::sdb.
fn module_of(rel: &Path) -> Vec<String> {
    let mut m = vec!["engine".to_string()];
    let parts: Vec<String> = rel.iter().map(|s| s.to_string_lossy().into_owned()).collect();
    for (k, p) in parts.iter().enumerate() {
        if k + 1 == parts.len() {
            let stem = p.trim_end_matches(".rs");
            if stem != "mod" {
                m.push(stem.to_string());
            }
        } else {
            m.push(p.clone());
        }
    }
    m
}

fn is_ident(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// Every path a source refers to that starts with `crate::` or `super::`, as segments
/// (after `{…}` expansion one level deep), resolved against `module`.
fn paths_in(src: &str, module: &[String]) -> Vec<Vec<String>> {
    let mut text = strip(src);
    // A unit-test module at the end of a file: its `super::` means the file's module,
    // not the file's parent, and it may use what it tests freely.
    if let Some(at) = text.find("#[cfg(test)]\nmod tests") {
        text.truncate(at);
    }
    let chars: Vec<char> = text.chars().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < chars.len() {
        let starts = |w: &str| {
            let n = w.len();
            i + n <= chars.len()
                && chars[i..i + n].iter().collect::<String>() == w
                && (i == 0 || !is_ident(chars[i - 1]))
        };
        let (base, skip): (Vec<String>, usize) = if starts("crate::") {
            (vec![], 7)
        } else if starts("super::") {
            let mut b = module.to_vec();
            let mut j = i;
            // super::super::…
            while chars[j..].iter().take(7).collect::<String>() == "super::" {
                b.pop();
                j += 7;
            }
            (b, j - i)
        } else {
            i += 1;
            continue;
        };
        let mut j = i + skip;
        let mut segs = base.clone();
        // Segments, then an optional group; `j` is just past a `::`.
        loop {
            let s = j;
            while j < chars.len() && is_ident(chars[j]) {
                j += 1;
            }
            if j > s {
                segs.push(chars[s..j].iter().collect());
            }
            let group_next = j == s && j < chars.len() && chars[j] == '{';
            if group_next || (j + 1 < chars.len() && chars[j] == ':' && chars[j + 1] == ':') {
                if !group_next {
                    j += 2;
                }
                if j < chars.len() && chars[j] == '{' {
                    // Expand the group: its entries' leading segment paths.
                    let mut depth = 0;
                    let mut k = j;
                    let mut entry = String::new();
                    let mut entries = Vec::new();
                    while k < chars.len() {
                        let c = chars[k];
                        if c == '{' {
                            depth += 1;
                            if depth == 1 {
                                k += 1;
                                continue;
                            }
                        }
                        if c == '}' {
                            depth -= 1;
                            if depth == 0 {
                                entries.push(std::mem::take(&mut entry));
                                break;
                            }
                        }
                        if c == ',' && depth == 1 {
                            entries.push(std::mem::take(&mut entry));
                        } else {
                            entry.push(c);
                        }
                        k += 1;
                    }
                    for e in entries {
                        let e = e.split(" as ").next().unwrap_or("");
                        let e: String = e.split_whitespace().collect::<Vec<_>>().join("");
                        let mut p = segs.clone();
                        for s in e.split("::").map(|s| s.split('{').next().unwrap_or("")) {
                            let s: String = s.chars().take_while(|c| is_ident(*c)).collect();
                            if s.is_empty() || s == "self" {
                                break;
                            }
                            p.push(s);
                        }
                        out.push(p);
                    }
                    j = k;
                    segs.clear();
                    break;
                }
                continue;
            }
            break;
        }
        if !segs.is_empty() {
            out.push(segs);
        }
        i = j.max(i + 1);
    }
    out
}

/// The engine module (the unit the rules speak of) a resolved path names.
fn unit_of(path: &[String], top: &BTreeSet<String>, techniques: &BTreeSet<String>) -> Option<String> {
    if path.first().map(String::as_str) != Some("engine") {
        return path.first().map(|s| format!("crate::{s}"));
    }
    let m = path.get(1)?;
    if !top.contains(m) {
        return None; // a name re-exported at engine's root, or not a module
    }
    if m == "technique" {
        return Some(match path.get(2) {
            Some(s) if techniques.contains(s) || s == "api" || s == "table" => format!("technique::{s}"),
            _ => "technique".into(),
        });
    }
    Some(m.clone())
}

fn module_names(dir: &Path) -> BTreeSet<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| {
            let p = e.ok()?.path();
            let name = p.file_stem()?.to_string_lossy().into_owned();
            (p.is_dir() || p.extension().is_some_and(|x| x == "rs")).then_some(name)
        })
        .filter(|n| n != "mod")
        .collect()
}

fn edges() -> (Vec<Edge>, BTreeSet<String>) {
    let root = engine_dir();
    let top = module_names(&root);
    let techniques: BTreeSet<String> = std::fs::read_dir(root.join("technique"))
        .unwrap()
        .filter_map(|e| {
            let p = e.ok()?.path();
            p.is_dir()
                .then(|| p.file_name().unwrap().to_string_lossy().into_owned())
        })
        .collect();
    let mut files = Vec::new();
    rust_files(&root, &mut files);
    let mut out = Vec::new();
    for f in files {
        let rel = f.strip_prefix(&root).unwrap().to_path_buf();
        let module = module_of(&rel);
        let Some(from) = unit_of(&module, &top, &techniques) else {
            continue;
        };
        let src = std::fs::read_to_string(&f).unwrap();
        for p in paths_in(&src, &module) {
            if let Some(to) = unit_of(&p, &top, &techniques)
                && to != from
            {
                out.push(Edge {
                    file: rel.to_string_lossy().into_owned(),
                    from: from.clone(),
                    to,
                });
            }
        }
    }
    (out, techniques)
}

/// Macros the engine exports (`#[macro_export]` puts them at the crate's root).
fn engine_macros() -> BTreeSet<String> {
    let mut files = Vec::new();
    rust_files(&engine_dir(), &mut files);
    files
        .iter()
        .flat_map(|f| {
            let src = std::fs::read_to_string(f).unwrap();
            src.split("macro_rules!")
                .skip(1)
                .filter_map(|rest| {
                    rest.split_whitespace()
                        .next()
                        .map(|n| n.trim_end_matches('{').to_string())
                })
                .collect::<Vec<_>>()
        })
        .collect()
}

fn is_technique(unit: &str) -> bool {
    unit == "technique" || unit.starts_with("technique::")
}

#[test]
fn the_parser_finds_grouped_and_relative_paths() {
    let m: Vec<String> = ["engine", "technique", "sdb"].iter().map(|s| s.to_string()).collect();
    let src = "use super::api::{BakeInputs, Technique};\n// use super::vpl::X;\nuse crate::engine::{gpu::frame::SceneFrame, plan};\nlet s = \"super::hemicube\";\nfn f() { super::super::job::plan_for(); }";
    let p = paths_in(src, &m);
    let joined: Vec<String> = p.iter().map(|s| s.join("::")).collect();
    assert!(
        joined.contains(&"engine::technique::api::BakeInputs".to_string()),
        "{joined:?}"
    );
    assert!(
        joined.contains(&"engine::gpu::frame::SceneFrame".to_string()),
        "{joined:?}"
    );
    assert!(joined.contains(&"engine::plan".to_string()), "{joined:?}");
    assert!(joined.contains(&"engine::job::plan_for".to_string()), "{joined:?}");
    assert!(
        !joined.iter().any(|j| j.contains("vpl") || j.contains("hemicube")),
        "comments and strings are skipped: {joined:?}"
    );
}

#[test]
fn the_engine_has_edges_to_check() {
    // Guards the rules below against a parser that finds nothing.
    let (e, techniques) = edges();
    assert!(techniques.len() >= 6, "{techniques:?}");
    assert!(e.iter().any(|x| x.from == "technique::sdb" && x.to == "gpu"));
    assert!(
        e.iter()
            .any(|x| x.from == "technique::table" && x.to == "technique::path")
    );
    assert!(e.iter().any(|x| x.from == "job" && x.to == "technique"));
    assert!(e.len() > 100, "only {} edges", e.len());
}

#[test]
fn no_technique_imports_another_technique_or_the_table() {
    let (e, _) = edges();
    let bad: Vec<String> = e
        .iter()
        .filter(|x| {
            x.from.starts_with("technique::")
                && x.from != "technique::table"
                && x.from != "technique::api"
                && is_technique(&x.to)
                && x.to != "technique::api"
        })
        .map(|x| format!("{} ({}) -> {}", x.file, x.from, x.to))
        .collect();
    assert!(
        bad.is_empty(),
        "techniques must import only technique::api:\n{}",
        bad.join("\n")
    );
    let api: Vec<String> = e
        .iter()
        .filter(|x| x.from == "technique::api" && is_technique(&x.to))
        .map(|x| format!("{} -> {}", x.file, x.to))
        .collect();
    assert!(
        api.is_empty(),
        "technique::api depends on a technique:\n{}",
        api.join("\n")
    );
}

#[test]
fn shared_layers_import_no_technique() {
    let (e, _) = edges();
    let bad: Vec<String> = e
        .iter()
        .filter(|x| ["gpu", "plan", "atlas", "scene"].contains(&x.from.as_str()) && is_technique(&x.to))
        .map(|x| format!("{} -> {}", x.file, x.to))
        .collect();
    assert!(
        bad.is_empty(),
        "shared layers must not import techniques:\n{}",
        bad.join("\n")
    );
}

#[test]
fn the_engine_never_imports_the_service() {
    let (e, _) = edges();
    let bad: Vec<String> = e
        .iter()
        .filter(|x| x.to.starts_with("crate::") && !engine_macros().contains(&x.to["crate::".len()..]))
        .map(|x| format!("{} -> {}", x.file, x.to))
        .collect();
    assert!(bad.is_empty(), "the engine refers outside itself:\n{}", bad.join("\n"));
}

#[test]
fn engine_modules_form_no_cycle() {
    let (e, _) = edges();
    let mut graph: BTreeMap<&str, BTreeSet<&str>> = BTreeMap::new();
    for x in &e {
        graph.entry(&x.from).or_default().insert(&x.to);
        graph.entry(&x.to).or_default();
    }
    // Depth-first search for a back edge; report the cycle it closes.
    fn visit<'a>(
        n: &'a str,
        g: &BTreeMap<&'a str, BTreeSet<&'a str>>,
        state: &mut BTreeMap<&'a str, u8>,
        stack: &mut Vec<&'a str>,
        cycles: &mut Vec<String>,
    ) {
        state.insert(n, 1);
        stack.push(n);
        for &m in &g[n] {
            match state.get(m).copied().unwrap_or(0) {
                0 => visit(m, g, state, stack, cycles),
                1 => {
                    let at = stack.iter().position(|s| *s == m).unwrap();
                    let mut c: Vec<&str> = stack[at..].to_vec();
                    c.push(m);
                    cycles.push(c.join(" -> "));
                }
                _ => {}
            }
        }
        stack.pop();
        state.insert(n, 2);
    }
    let mut state = BTreeMap::new();
    let mut cycles = Vec::new();
    for n in graph.keys() {
        if state.get(n).copied().unwrap_or(0) == 0 {
            visit(n, &graph, &mut state, &mut Vec::new(), &mut cycles);
        }
    }
    let witness = |a: &str, b: &str| {
        e.iter()
            .filter(|x| x.from == a && x.to == b)
            .map(|x| x.file.clone())
            .collect::<BTreeSet<_>>()
            .into_iter()
            .collect::<Vec<_>>()
            .join(", ")
    };
    let explained: Vec<String> = cycles
        .iter()
        .map(|c| {
            let nodes: Vec<&str> = c.split(" -> ").collect();
            let steps: Vec<String> = nodes
                .windows(2)
                .map(|w| format!("{} -> {} ({})", w[0], w[1], witness(w[0], w[1])))
                .collect();
            steps.join("; ")
        })
        .collect();
    assert!(
        explained.is_empty(),
        "import cycles in engine:\n{}",
        explained.join("\n")
    );
}
