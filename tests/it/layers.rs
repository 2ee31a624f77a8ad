//! What Cargo cannot see of ARCHITECTURE.md's rules, checked on the sources: the crates
//! depend downward only (read from their manifests), no two files of one crate import each
//! other (directly or round a longer loop), and every shader is included by host code that
//! tests it against its CPU twin.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn workspace() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn files_with(dir: &Path, extension: &str, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            files_with(&path, extension, out);
        } else if path.extension().is_some_and(|e| e == extension) {
            out.push(path);
        }
    }
}

/// The `src/` folders of the workspace's crates: the top crate's and each `crates/*/src`.
fn crate_sources() -> Vec<PathBuf> {
    let mut roots = vec![workspace().join("src")];
    for entry in std::fs::read_dir(workspace().join("crates")).unwrap() {
        roots.push(entry.unwrap().path().join("src"));
    }
    roots
}

/// The module path of a file under its crate's `src/` (`mesh/cpu.rs` → `mesh::cpu`,
/// `mesh/mod.rs` → `mesh`, `lib.rs` → ``).
fn module_path(src: &Path, file: &Path) -> String {
    let relative = file.strip_prefix(src).unwrap().with_extension("");
    let mut parts: Vec<String> = relative.components().map(|c| c.as_os_str().to_string_lossy().into_owned()).collect();
    if parts.last().is_some_and(|p| p == "mod" || p == "lib" || p == "main") {
        parts.pop();
    }
    parts.join("::")
}

fn parent(module: &str) -> String {
    module.rsplit_once("::").map_or(String::new(), |(p, _)| p.to_owned())
}

fn join(module: &str, name: &str) -> String {
    if module.is_empty() {
        name.to_owned()
    } else {
        format!("{module}::{name}")
    }
}

/// A file's code: comments, re-exports and module declarations left out (a parent that
/// declares or re-exports a child does not use it), and nothing from its test module on.
fn code_lines(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut lines = text.lines().peekable();
    while let Some(line) = lines.next() {
        let code = line.split("//").next().unwrap_or_default().trim();
        if code == "#[cfg(test)]" && lines.peek().is_some_and(|next| next.trim_start().starts_with("mod tests")) {
            break;
        }
        let declaration = ["pub use ", "pub(crate) use ", "mod ", "pub mod ", "pub(crate) mod "];
        if !declaration.iter().any(|d| code.starts_with(d)) {
            out.push(code.to_owned());
        }
    }
    out
}

/// The path segments after each `start` in `code` that is not itself part of a longer path.
fn paths_after<'a>(code: &'a str, start: &str) -> Vec<Vec<&'a str>> {
    let mut found = Vec::new();
    let mut from = 0;
    while let Some(at) = code[from..].find(start).map(|i| from + i) {
        from = at + start.len();
        let before = code[..at].chars().next_back();
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == ':') {
            continue;
        }
        let rest = &code[at + start.len()..];
        let path: Vec<&str> = rest
            .split("::")
            .map(|s| s.split(|c: char| !(c.is_alphanumeric() || c == '_')).next().unwrap_or_default())
            .take_while(|s| !s.is_empty())
            .collect();
        found.push(path);
    }
    found
}

/// The files of one crate each file uses, as module paths: `crate::`, `super::` and child
/// module paths resolved to the deepest module they name.
fn file_imports(src: &Path, files: &[PathBuf]) -> BTreeMap<String, BTreeSet<String>> {
    let modules: BTreeSet<String> = files.iter().map(|f| module_path(src, f)).collect();
    let deepest = |base: String, segments: &[&str]| {
        let mut at = base;
        for segment in segments {
            let next = join(&at, segment);
            if !modules.contains(&next) {
                break;
            }
            at = next;
        }
        at
    };
    let mut imports = BTreeMap::new();
    for file in files {
        let module = module_path(src, file);
        let children: Vec<&str> = modules
            .iter()
            .filter(|m| !m.is_empty() && parent(m) == module)
            .map(|m| m.rsplit("::").next().unwrap_or(m))
            .collect();
        let mut used = BTreeSet::new();
        for code in code_lines(&std::fs::read_to_string(file).unwrap()) {
            for path in paths_after(&code, "crate::") {
                used.insert(deepest(String::new(), &path));
            }
            for path in paths_after(&code, "super::") {
                used.insert(deepest(parent(&module), &path));
            }
            for child in &children {
                for path in paths_after(&code, &format!("{child}::")) {
                    used.insert(deepest(join(&module, child), &path));
                }
            }
        }
        used.remove(&module);
        imports.insert(module, used);
    }
    imports
}

/// A loop of files importing each other, if the graph has one.
fn find_loop(imports: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        at: &str,
        imports: &BTreeMap<String, BTreeSet<String>>,
        done: &mut BTreeSet<String>,
        stack: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        if let Some(start) = stack.iter().position(|m| m == at) {
            return Some(stack[start..].iter().cloned().chain([at.to_owned()]).collect());
        }
        if done.contains(at) {
            return None;
        }
        stack.push(at.to_owned());
        for next in imports.get(at).into_iter().flatten() {
            if let Some(cycle) = visit(next, imports, done, stack) {
                return Some(cycle);
            }
        }
        stack.pop();
        done.insert(at.to_owned());
        None
    }
    let mut done = BTreeSet::new();
    imports.keys().find_map(|m| visit(m, imports, &mut done, &mut Vec::new()))
}

/// Each crate's library files (and the binary's, apart), by crate.
fn crate_file_sets() -> Vec<(String, PathBuf, Vec<PathBuf>)> {
    let mut sets = Vec::new();
    for src in crate_sources() {
        let mut files = Vec::new();
        files_with(&src, "rs", &mut files);
        let in_binary = |f: &PathBuf| {
            let relative = f.strip_prefix(&src).unwrap();
            relative.starts_with("cli") || relative.starts_with("bin") || relative == Path::new("main.rs")
        };
        let (binary, library): (Vec<PathBuf>, Vec<PathBuf>) = files.into_iter().partition(in_binary);
        let name = match src == workspace().join("src") {
            true => "defvol".to_owned(),
            false => src.parent().unwrap().file_name().unwrap().to_string_lossy().into_owned(),
        };
        let binary: Vec<PathBuf> = binary.into_iter().filter(|f| !f.starts_with(src.join("bin"))).collect();
        if !binary.is_empty() {
            sets.push((format!("{name} (binary)"), src.clone(), binary));
        }
        sets.push((name, src, library));
    }
    sets
}

#[test]
fn the_file_scan_sees_the_known_imports() {
    // The loop rule is only as good as the scan: it must see imports that exist, in each
    // of the forms the sources use (`crate::`, `super::`, a child module's path).
    let sets = crate_file_sets();
    let imports_of = |krate: &str| {
        let (_, src, files) = sets.iter().find(|(name, ..)| name == krate).unwrap();
        file_imports(src, files)
    };
    let top = imports_of("defvol");
    let render = imports_of("defvol-render");
    let has = |graph: &BTreeMap<String, BTreeSet<String>>, a: &str, b: &str| graph[a].contains(b);
    assert!(has(&top, "ros::node", "pipeline"), "{top:?}");
    assert!(has(&top, "pipeline", "pipeline::frames"), "{top:?}");
    assert!(has(&render, "mesh::gpu", "mesh::look"), "{render:?}");
    assert!(has(&render, "mesh::source", "volume"), "{render:?}");
}

#[test]
fn the_loop_search_finds_a_loop_round_three_files_and_none_in_a_chain() {
    let graph = |edges: &[(&str, &str)]| {
        let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        for (a, b) in edges {
            g.entry((*a).to_owned()).or_default().insert((*b).to_owned());
            g.entry((*b).to_owned()).or_default();
        }
        g
    };
    let cycle = find_loop(&graph(&[("a", "b"), ("b", "c"), ("c", "a"), ("c", "d")]));
    assert_eq!(cycle, Some(["a", "b", "c", "a"].map(String::from).to_vec()));
    assert_eq!(find_loop(&graph(&[("a", "b"), ("b", "c"), ("a", "c")])), None);
}

#[test]
fn no_files_of_one_crate_import_each_other() {
    let loops: Vec<(String, Vec<String>)> = crate_file_sets()
        .into_iter()
        .filter_map(|(name, src, files)| find_loop(&file_imports(&src, &files)).map(|cycle| (name, cycle)))
        .collect();
    assert!(loops.is_empty(), "files importing each other round a loop: {loops:?}");
}

/// The workspace crates a crate's manifest depends on (dev-dependencies apart).
fn workspace_dependencies(manifest: &Path) -> BTreeSet<String> {
    let text = std::fs::read_to_string(manifest).unwrap();
    let mut section = String::new();
    let mut found = BTreeSet::new();
    for line in text.lines().map(str::trim) {
        if line.starts_with('[') {
            section = line.to_owned();
        } else if section == "[dependencies]" && line.starts_with("defvol-") {
            found.insert(line.split([' ', '=']).next().unwrap_or_default().to_owned());
        }
    }
    found
}

#[test]
fn the_crates_depend_downward_only() {
    // The ground crate stands alone, the GPU plumbing stands on it, each stage on both and
    // on no other stage; only the top crate gathers them.
    let allowed: BTreeMap<&str, &[&str]> = BTreeMap::from([
        ("defvol-core", &[][..]),
        ("defvol-gpu", &["defvol-core"][..]),
        ("defvol-solver", &["defvol-core", "defvol-gpu"][..]),
        ("defvol-warp", &["defvol-core", "defvol-gpu"][..]),
        ("defvol-dpcm", &["defvol-core", "defvol-gpu"][..]),
        ("defvol-render", &["defvol-core", "defvol-gpu"][..]),
    ]);
    let crates = std::fs::read_dir(workspace().join("crates")).unwrap();
    let mut seen = 0;
    for folder in crates.map(|e| e.unwrap().path()) {
        let name = folder.file_name().unwrap().to_string_lossy().into_owned();
        let below =
            allowed.get(name.as_str()).unwrap_or_else(|| panic!("{name}: a crate ARCHITECTURE.md does not place"));
        let depends = workspace_dependencies(&folder.join("Cargo.toml"));
        let upward: Vec<&String> = depends.iter().filter(|d| !below.contains(&d.as_str())).collect();
        assert!(upward.is_empty(), "{name} depends on {upward:?}");
        seen += 1;
    }
    assert_eq!(seen, allowed.len());
    assert!(workspace_dependencies(&workspace().join("Cargo.toml")).len() >= 6, "the top crate gathers the crates");
}

#[test]
fn the_messages_stand_alone() {
    let (_, src, files) = crate_file_sets().into_iter().find(|(name, ..)| name == "defvol").unwrap();
    let imports = file_imports(&src, &files);
    let reaching: Vec<_> = imports
        .iter()
        .filter(|(m, used)| m.starts_with("msgs") && used.iter().any(|u| !u.starts_with("msgs")))
        .collect();
    assert!(reaching.is_empty(), "msgs import nothing else of the crate: {reaching:?}");
}

#[test]
fn every_shader_is_included_by_host_code_that_tests_it() {
    assert!(!workspace().join("shaders").exists(), "shaders live beside their host code, not in shaders/");
    let mut shaders = Vec::new();
    let mut hosts = Vec::new();
    for src in crate_sources() {
        files_with(&src, "wgsl", &mut shaders);
        files_with(&src, "rs", &mut hosts);
    }
    assert!(shaders.len() >= 8, "{shaders:?}");
    for shader in shaders {
        let including: Vec<&PathBuf> = hosts
            .iter()
            .filter(|host| {
                let text = std::fs::read_to_string(host).unwrap();
                text.split("include_str!(\"").skip(1).any(|rest| {
                    let relative = rest.split('"').next().unwrap_or_default();
                    host.parent().unwrap().join(relative).canonicalize().ok() == shader.canonicalize().ok()
                })
            })
            .collect();
        assert!(!including.is_empty(), "{}: no host file includes it", shader.display());
        // The agreement tests sit with the host code: a test that runs the kernel and a CPU
        // twin side by side.
        let tested = including.iter().any(|host| {
            let text = std::fs::read_to_string(host).unwrap();
            text.contains("#[test]") && text.contains("mod tests")
        });
        assert!(tested, "{}: its host code {including:?} has no agreement test", shader.display());
    }
}
