//! The dependency rules of ARCHITECTURE.md, checked on the sources: every `crate::<module>`
//! a file names is a dependency of its module, and these must hold.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// The algorithms: they know nothing of ROS, records, messages or the node's wiring.
const ALGORITHMS: [&str; 10] = ["math", "mesh", "volume", "io", "gpu", "backend", "solver", "warp", "dpcm", "render"];
/// What no algorithm may import.
const ABOVE_ALGORITHMS: [&str; 8] = ["ros", "record", "msgs", "session", "shm", "pipeline", "scene", "bench"];
/// The stages: each one folder with its CPU path, GPU host code, shaders and agreement tests.
const STAGES: [&str; 4] = ["solver", "warp", "dpcm", "render"];

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

/// The top-level module a source file belongs to (`src/warp/gpu.rs` → `warp`).
fn module_of(src: &Path, file: &Path) -> String {
    let relative = file.strip_prefix(src).unwrap();
    let first = relative.components().next().unwrap().as_os_str().to_string_lossy().into_owned();
    first.trim_end_matches(".rs").to_owned()
}

/// The workspace modules a file names (`crate::x`, `defvol_core::x`, `defvol_gpu::x`), outside
/// comments. A stage crate's own `crate::` paths name its files, which are the stage itself.
fn dependencies(text: &str) -> BTreeSet<String> {
    let mut found = BTreeSet::new();
    for line in text.lines() {
        let code = line.split("//").next().unwrap_or_default();
        for prefix in ["crate::", "defvol_core::", "defvol_gpu::"] {
            let mut rest = code;
            while let Some(at) = rest.find(prefix) {
                let after = &rest[at + prefix.len()..];
                let name: String = after.chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
                if !name.is_empty() {
                    found.insert(name);
                }
                rest = after;
            }
        }
    }
    found
}

/// The source folders of the workspace: this crate's `src/` and each `crates/*/src/`, with
/// the module a stage crate's files all belong to (`crates/defvol-warp/src` → `warp`).
fn source_roots() -> Vec<(PathBuf, Option<String>)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut roots = vec![(root.join("src"), None)];
    for entry in std::fs::read_dir(root.join("crates")).unwrap() {
        let folder = entry.unwrap().path();
        let name = folder.file_name().unwrap().to_string_lossy().trim_start_matches("defvol-").to_owned();
        let stage = STAGES.contains(&name.as_str()).then_some(name);
        roots.push((folder.join("src"), stage));
    }
    roots
}

/// Every (module, dependency, file) in the workspace's libraries.
fn edges() -> Vec<(String, String, PathBuf)> {
    let mut files = Vec::new();
    for (src, stage) in source_roots() {
        let mut found = Vec::new();
        rust_files(&src, &mut found);
        files.extend(found.into_iter().map(|file| (src.clone(), stage.clone(), file)));
    }
    let mut out = Vec::new();
    for (src, stage, file) in files {
        let module = stage.unwrap_or_else(|| module_of(&src, &file));
        if ["main", "lib", "cli", "bin"].contains(&module.as_str()) {
            continue;
        }
        let text = std::fs::read_to_string(&file).unwrap();
        for dependency in dependencies(&text) {
            if dependency != module {
                out.push((module.clone(), dependency, file.clone()));
            }
        }
    }
    out
}

#[test]
fn the_module_scan_sees_the_known_dependencies() {
    // The rules below are only as good as the scan: it must see edges that exist.
    let edges = edges();
    let has = |a: &str, b: &str| edges.iter().any(|(m, d, _)| m == a && d == b);
    assert!(
        has("warp", "volume")
            && has("pipeline", "warp")
            && has("ros", "pipeline")
            && has("solver", "math")
            && has("io", "volume"),
        "{edges:?}"
    );
}

#[test]
fn algorithms_never_import_ros_records_messages_or_the_wiring() {
    let broken: Vec<_> = edges()
        .into_iter()
        .filter(|(m, d, _)| ALGORITHMS.contains(&m.as_str()) && ABOVE_ALGORITHMS.contains(&d.as_str()))
        .collect();
    assert!(broken.is_empty(), "algorithms importing upper layers: {broken:?}");
}

#[test]
fn the_gpu_plumbing_imports_no_stage_and_no_data() {
    let broken: Vec<_> = edges().into_iter().filter(|(m, d, _)| m == "gpu" && d != "math").collect();
    assert!(broken.is_empty(), "gpu/ imports more than the ground floor: {broken:?}");
}

#[test]
fn no_stage_imports_another() {
    let broken: Vec<_> =
        edges().into_iter().filter(|(m, d, _)| STAGES.contains(&m.as_str()) && STAGES.contains(&d.as_str())).collect();
    assert!(broken.is_empty(), "stages importing each other: {broken:?}");
}

#[test]
fn the_ground_floor_and_the_messages_stand_alone() {
    let broken: Vec<_> = edges().into_iter().filter(|(m, _, _)| m == "math" || m == "msgs").collect();
    assert!(broken.is_empty(), "math and msgs import nothing of the crate: {broken:?}");
}

#[test]
fn every_shader_sits_beside_its_host_code() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    assert!(!root.join("shaders").exists(), "shaders live in their stage's folder, not in shaders/");
    let mut shaders = Vec::new();
    for (src, stage) in source_roots() {
        let mut stack = vec![src.clone()];
        while let Some(dir) = stack.pop() {
            for entry in std::fs::read_dir(dir).unwrap() {
                let path = entry.unwrap().path();
                if path.is_dir() {
                    stack.push(path);
                } else if path.extension().is_some_and(|e| e == "wgsl") {
                    shaders.push((src.clone(), stage.clone(), path));
                }
            }
        }
    }
    assert!(shaders.len() >= 7, "{shaders:?}");
    for (src, stage, shader) in shaders {
        let module = stage.unwrap_or_else(|| module_of(&src, &shader));
        assert!(
            STAGES.contains(&module.as_str()) || module == "gpu",
            "{}: a shader outside the stages and gpu/",
            shader.display()
        );
        let name = shader.file_name().unwrap().to_string_lossy().into_owned();
        let folder = shader.parent().unwrap();
        let users: Vec<PathBuf> = std::fs::read_dir(folder)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| {
                p.extension().is_some_and(|e| e == "rs")
                    && std::fs::read_to_string(p).unwrap().contains(&format!("include_str!(\"{name}\")"))
            })
            .collect();
        assert!(!users.is_empty(), "{}: no host file beside it includes it", shader.display());
    }
}
