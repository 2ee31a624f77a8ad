//! Every defvol command in the shell blocks of the README and of the guide in `docs/`, run
//! through the real binaries in the order they appear (the README first): each line as it stands, on tiny files standing in for the ones it names
//! (`ct.nii.gz`, `organ.vtu`, …), with the sizes that would take minutes cut by the
//! replacements listed beside it. A README command the table lacks fails the test, and so
//! does a listed line the README no longer has. The build-loop lines (`cargo test`,
//! `cargo clippy`, `tests/run.sh`) are this suite itself. Node lines run inside a private
//! network namespace (tests/netns-run), as every DDS participant here does. And every
//! relative link of those pages, and every pointer from a code comment into the perf
//! journal, reaches a file and a heading that exist.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use defvol::mesh::generate::{lattice, CellSplit};
use nalgebra::Vector3;

/// A README command, what the suite replaces in it, and the files it must leave behind.
struct Run {
    line: &'static str,
    replace: &'static [(&'static str, &'static str)],
    writes: &'static [&'static str],
}

const SMALL_BENCH: &str = "--steps 2 --tolerances 1e-2 --preconditioners amg --allow-software-gpu";

const RUNS: &[Run] = &[
    Run {
        line: "cargo run --release -- demo --seconds 2 --out out",
        replace: &[("--seconds 2", "--seconds 0.2")],
        writes: &["out"],
    },
    Run {
        line: "defvol node --record session.mcap --ros-args -r __ns:=/robot -p stages.warp:=false",
        replace: &[
            ("node --record", "node --seconds 1 --backend cpu --record"),
            ("stages.warp:=false", "stages.warp:=false -p scene_file:=my_scene.yaml"),
        ],
        writes: &["session.mcap"],
    },
    Run {
        line: "defvol_node --ros-args --params-file my_params.yaml",
        replace: &[("defvol_node --ros-args", "defvol_node --seconds 1 --backend cpu --ros-args")],
        writes: &[],
    },
    Run {
        line: "cargo run --release -- simulate --steps 100 --out out --warp-out out/warped.nii.gz",
        replace: &[("--steps 100", "--steps 3 --tets 300")],
        writes: &["out/rest.vtu", "out/final.vtu", "out/steps.csv", "out/warped.nii.gz"],
    },
    Run {
        line: "defvol simulate --mesh organ.vtu --integrator implicit-euler --dt 0.01 --steps 500 --backend gpu",
        replace: &[("--steps 500", "--steps 3 --out organ_out"), ("--backend gpu", "--backend gpu --allow-software-gpu")],
        writes: &["organ_out/final.vtu"],
    },
    Run {
        line: "defvol simulate --scene my_scene.yaml --f64",
        replace: &[("--f64", "--f64 --steps 3")],
        writes: &["out/final.vtu"],
    },
    Run {
        line: "defvol bench solver --backends cpu,gpu",
        replace: &[("cpu,gpu", "cpu,gpu --sizes 80 --steps 2 --tolerances 1e-2 --preconditioners amg --allow-software-gpu")],
        writes: &[],
    },
    Run {
        line: "defvol bench solver --sizes 80,14000 --json > solver.jsonl",
        replace: &[("80,14000", "80"), ("--json", SMALL_BENCH), (" >", " --json >")],
        writes: &["solver.jsonl"],
    },
    Run { line: "defvol bench report report --from solver.jsonl", replace: &[], writes: &["report/solver.svg", "report/index.html"] },
    Run {
        line: "defvol warp --rest out/rest.vtu --deformed out/final.vtu --volume ct.nii.gz --out warped.nii.gz",
        replace: &[],
        writes: &["warped.nii.gz"],
    },
    Run {
        line: "defvol warp --volume ct.mha --displace 10,5,0:0,0,4:30 --out pushed.mha",
        replace: &[],
        writes: &["pushed.mha"],
    },
    Run { line: "defvol warp --out warped.nrrd", replace: &[], writes: &["warped.nrrd"] },
    Run { line: "defvol info ct.nii.gz", replace: &[], writes: &[] },
    Run { line: "defvol info organ.vtu", replace: &[], writes: &[] },
    Run {
        line: "defvol bench warp --incremental --gpu",
        replace: &[("--gpu", "--gpu --allow-software-gpu --tets 40 --cases upright --dims 48,32,24 --runs 1")],
        writes: &[],
    },
    Run {
        line: "defvol dpcm --preset water --steps 2000 --out out/dpcm",
        replace: &[("--steps 2000", "--steps 20 --size 64x64")],
        writes: &["out/dpcm/colour.png", "out/dpcm/height.mha"],
    },
    Run {
        line: "defvol dpcm --preset sand --markers path.csv --out out/sand",
        replace: &[("--out", "--steps 20 --size 64x64 --out")],
        writes: &["out/sand/height.mha"],
    },
    Run {
        line: "defvol dpcm --preset loose_soil --udp 9000 --realtime --steps 60000",
        replace: &[("--udp 9000", "--udp 0"), ("--steps 60000", "--steps 20 --size 64x64 --out out/udp")],
        writes: &["out/udp/height.mha"],
    },
    Run {
        line: "defvol bench dpcm --gpu",
        replace: &[(
            "--gpu",
            "--gpu --allow-software-gpu --size 64,64 --markers 1 --topologies four --physics elastic --steps 5 --no-sweep",
        )],
        writes: &[],
    },
    Run {
        line: "defvol render --out view.png --depth-out depth.mha",
        replace: &[("--out", "--size 64x48 --out")],
        writes: &["view.png", "depth.mha"],
    },
    Run {
        line: "defvol render --volume ct.nii.gz --tf ct_bone --camera 0,-600,200:0,0,0 --size 1024x1024",
        replace: &[("1024x1024", "64x64")],
        writes: &["render.png"],
    },
    Run {
        line: "defvol render --mode iso --iso 300 --shading forward-difference --out bone.png",
        replace: &[("--out", "--size 64x48 --out")],
        writes: &["bone.png"],
    },
    Run {
        line: "defvol render --mesh out/final.vtu --volume ct.nii.gz --out mesh.png",
        replace: &[("--out", "--size 64x48 --out")],
        writes: &["mesh.png"],
    },
    Run {
        line: "defvol render --mesh organ.vtu --scalars dose --tf-file dose.yaml",
        // defvol writes a mesh's one point array under the name `scalar`.
        replace: &[("--scalars dose", "--scalars scalar"), ("dose.yaml", "dose.yaml --size 64x48 --out dose.png")],
        writes: &["dose.png"],
    },
    Run {
        line: "defvol render --mesh out/rest.vtu --deformed out/final.vtu --volume ct.nii.gz --out ct.png",
        replace: &[("--out", "--size 64x48 --out")],
        writes: &["ct.png"],
    },
    Run {
        line: "defvol bench render",
        replace: &[(
            "render",
            "render --sizes 32 --steps 4 --runs 1 --reference-step 2 --no-warped --meshes --source-meshes",
        )],
        writes: &[],
    },
    Run {
        line: "tests/netns-run defvol bench node",
        replace: &[("node", "node --tets 300 --steps 30 --settle 5 --volume-mib 1 --volume-frames 2")],
        writes: &[],
    },
    Run {
        line: "defvol bench report docs/perf --stages solver,warp,dpcm,render --pages README.md,docs/performance.md",
        replace: &[("--stages solver,warp,dpcm,render", "--stages solver --quick")],
        writes: &["docs/perf/solver.svg", "docs/perf/index.html", "docs/perf/rows.jsonl"],
    },
    Run {
        line: "tests/netns-run defvol bench report report",
        replace: &[("report report", "report report --quick --stages warp,node")],
        writes: &["report/warp.svg", "report/node.svg", "report/index.html"],
    },
];

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// Every file under `folder`, at any depth, sorted by path.
fn files_under(folder: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    let mut folders = vec![folder.to_path_buf()];
    while let Some(folder) = folders.pop() {
        for entry in std::fs::read_dir(folder).unwrap().map(|e| e.unwrap().path()) {
            match entry.is_dir() {
                true => folders.push(entry),
                false => files.push(entry),
            }
        }
    }
    files.sort();
    files
}

/// The README, then every Markdown page under `docs/` (sorted by path).
fn guide_pages() -> Vec<PathBuf> {
    let docs = files_under(&root().join("docs")).into_iter().filter(|f| f.extension().is_some_and(|e| e == "md"));
    std::iter::once(root().join("README.md")).chain(docs).collect()
}

/// The commands of the guide's shell blocks: comments and build-loop lines left out.
fn readme_commands() -> Vec<String> {
    let mut commands = Vec::new();
    for page in guide_pages() {
        commands.extend(shell_commands(&std::fs::read_to_string(page).unwrap()));
    }
    commands
}

/// The defvol commands of one page's `sh` and `bash` blocks.
fn shell_commands(text: &str) -> Vec<String> {
    let mut commands = Vec::new();
    let mut in_shell = false;
    for line in text.lines() {
        if line.starts_with("```") {
            in_shell = !in_shell && (line == "```sh" || line == "```bash");
            continue;
        }
        let command = line.split(" #").next().unwrap_or("").trim();
        let runs_defvol =
            ["defvol", "defvol_node", "cargo run", "tests/netns-run"].iter().any(|p| command.starts_with(p));
        if in_shell && runs_defvol {
            commands.push(command.to_owned());
        }
    }
    commands
}

/// The tiny stand-ins for the files the README's commands name.
fn stand_ins(dir: &Path) {
    let phantom = defvol::volume::phantom::phantom([64, 40, 31], 4.0).unwrap();
    defvol::io::write_volume(&dir.join("ct.nii.gz"), &phantom).unwrap();
    defvol::io::write_volume(&dir.join("ct.mha"), &phantom).unwrap();
    // An organ in millimetres with a point array, as a user's file would be.
    let mut organ = lattice(Vector3::repeat(-30.0), Vector3::repeat(30.0), [3, 3, 3], CellSplit::Five).unwrap();
    organ.set_scalars((0..organ.nodes().len()).map(|i| i as f32).collect()).unwrap();
    defvol::io::write_mesh(&dir.join("organ.vtu"), &organ, None, None).unwrap();
    let scene = root().join("tests/data/small_scene.yaml");
    std::fs::copy(&scene, dir.join("my_scene.yaml")).unwrap();
    std::fs::write(dir.join("path.csv"), "time,marker,x,y,z\n0,0,0,0,0.001\n0.02,0,0,0,-0.001\n").unwrap();
    let tf = "relative: true\npoints:\n  - { value: 0.0, color: [0, 0, 1], opacity: 0.0 }\n  - { value: 1.0, color: [1, 0, 0], opacity: 0.5 }\n";
    std::fs::write(dir.join("dose.yaml"), tf).unwrap();
    let params = format!(
        "/**:\n  ros__parameters:\n    scene_file: {}\n    warp.service: defvol/readme_{}\n",
        scene.display(),
        std::process::id()
    );
    std::fs::write(dir.join("my_params.yaml"), params).unwrap();
    // The pages whose figures `bench report --pages` rewrites.
    std::fs::create_dir_all(dir.join("docs")).unwrap();
    for page in ["README.md", "docs/performance.md"] {
        std::fs::copy(root().join(page), dir.join(page)).unwrap();
    }
}

/// The line's program and arguments as the suite runs them; stdout's file for a `>`.
fn command_for(line: &str) -> (Command, Option<PathBuf>) {
    let mut words: Vec<&str> = line.split_whitespace().collect();
    let stdout = words.iter().position(|w| *w == ">").map(|at| {
        let file = PathBuf::from(words[at + 1]);
        words.truncate(at);
        file
    });
    if words.starts_with(&["cargo", "run", "--release", "--"]) {
        words.splice(0..4, ["defvol"]);
    }
    let binary = |word: &str| match word {
        "defvol" => env!("CARGO_BIN_EXE_defvol"),
        "defvol_node" => env!("CARGO_BIN_EXE_defvol_node"),
        other => panic!("`{other}` is not a defvol binary"),
    };
    // DDS participants only inside a private network namespace.
    let dds = words.contains(&"node") || words[0] == "defvol_node";
    let (program, args) = match (words[0], dds) {
        ("tests/netns-run", _) => (
            root().join("tests/netns-run"),
            std::iter::once(binary(words[1])).chain(words[2..].iter().copied()).collect(),
        ),
        (first, true) => {
            (root().join("tests/netns-run"), std::iter::once(binary(first)).chain(words[1..].iter().copied()).collect())
        }
        (first, false) => (PathBuf::from(binary(first)), words[1..].to_vec()),
    };
    let mut command = Command::new(program);
    command.args(args);
    (command, stdout)
}

#[test]
fn every_readme_command_runs_as_written_on_tiny_stand_ins() {
    let listed: Vec<&str> = RUNS.iter().map(|r| r.line).collect();
    let commands = readme_commands();
    let missing: Vec<&String> = commands.iter().filter(|c| !listed.contains(&c.as_str())).collect();
    let stale: Vec<&&str> = listed.iter().filter(|l| !commands.iter().any(|c| c == *l)).collect();
    assert!(
        missing.is_empty() && stale.is_empty(),
        "README commands the suite does not run: {missing:#?}\nlisted lines the README lost: {stale:#?}"
    );
    let dir = tempfile::tempdir().unwrap();
    stand_ins(dir.path());
    for run in RUNS {
        let mut line = run.line.to_owned();
        for (from, to) in run.replace {
            assert!(line.contains(from), "`{from}` is not in `{}`", run.line);
            line = line.replacen(from, to, 1);
        }
        let (mut command, stdout) = command_for(&line);
        command.current_dir(dir.path()).env("ROS_DOMAIN_ID", "29").env_remove("RUST_LOG");
        let out = match &stdout {
            Some(file) => {
                let file = std::fs::File::create(dir.path().join(file)).unwrap();
                command.stdout(Stdio::from(file)).output().unwrap()
            }
            None => command.output().unwrap(),
        };
        assert!(out.status.success(), "`{line}` failed:\n{}", String::from_utf8_lossy(&out.stderr));
        for file in run.writes {
            assert!(dir.path().join(file).exists(), "`{line}` did not write {file}");
        }
    }
    let rows = std::fs::read_to_string(dir.path().join("solver.jsonl")).unwrap();
    assert!(rows.lines().all(|l| serde_json::from_str::<serde_json::Value>(l).is_ok()), "{rows}");
}

/// A heading's anchor as GitHub makes it: lower case, letters, digits, `-` and `_` kept,
/// spaces turned to `-`, the rest dropped.
fn anchor(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

/// The anchors of a Markdown file's headings (outside code blocks).
fn anchors(page: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(page).unwrap_or_else(|e| panic!("{}: {e}", page.display()));
    let mut in_code = false;
    let mut found = Vec::new();
    for line in text.lines() {
        in_code ^= line.starts_with("```");
        if !in_code && line.starts_with('#') {
            found.push(anchor(line.trim_start_matches('#')));
        }
    }
    found
}

/// Where `target` (a path, maybe with `#anchor`, relative to `from`'s folder) leads: none
/// when it does (a file, a folder, or a heading of a Markdown file).
fn dead_link(from: &Path, target: &str) -> Option<String> {
    let (path, heading) = target.split_once('#').unwrap_or((target, ""));
    let file = if path.is_empty() { from.to_path_buf() } else { from.parent().unwrap().join(path) };
    if !file.exists() {
        return Some(format!("{}: no {}", from.display(), file.display()));
    }
    let is_page = file.extension().is_some_and(|e| e == "md");
    (is_page && !heading.is_empty() && !anchors(&file).contains(&heading.to_owned()))
        .then(|| format!("{}: no heading #{heading} in {}", from.display(), file.display()))
}

/// The relative targets of a Markdown text's links `[text](target)`, outside code blocks.
fn relative_links(text: &str) -> Vec<String> {
    let mut in_code = false;
    let mut links = Vec::new();
    for line in text.lines() {
        in_code ^= line.starts_with("```");
        if in_code {
            continue;
        }
        for part in line.split("](").skip(1) {
            let target = part.split(')').next().unwrap_or("").trim();
            let external = target.contains("://") || target.starts_with("mailto:");
            if !target.is_empty() && !external {
                links.push(target.to_owned());
            }
        }
    }
    links
}

#[test]
fn every_relative_link_of_the_pages_and_every_journal_pointer_of_the_code_leads_somewhere() {
    let mut pages = guide_pages();
    pages.extend(["ARCHITECTURE.md", "CONTRIBUTING.md", "CHANGELOG.md"].map(|p| root().join(p)));
    let mut dead: Vec<String> = Vec::new();
    let mut links = 0;
    for page in &pages {
        for target in relative_links(&std::fs::read_to_string(page).unwrap()) {
            links += 1;
            dead.extend(dead_link(page, &target));
        }
    }
    // Comments that moved a measurement to the journal point at its entry.
    let journal = root().join("docs/perf/journal.md");
    let headings = anchors(&journal);
    let mut pointers = 0;
    for file in ["crates", "src"].iter().flat_map(|folder| files_under(&root().join(folder))) {
        let Ok(text) = std::fs::read_to_string(&file) else { continue };
        for part in text.split("docs/perf/journal.md#").skip(1) {
            let heading: String = part.chars().take_while(|c| c.is_alphanumeric() || *c == '-').collect();
            pointers += 1;
            if !headings.contains(&heading) {
                dead.push(format!("{}: no heading #{heading} in the journal", file.display()));
            }
        }
    }
    assert!(links > 5 && pointers > 10, "{links} links and {pointers} journal pointers read");
    assert!(dead.is_empty(), "dead links: {dead:#?}");
}

/// The parameter reference of `docs/scenes.md` (between its markers) is the node's own table
/// of parameters (`defvol::scene::descriptors::reference_table`), so the page cannot drift from
/// what `ros2 param describe` says.
#[test]
fn the_scene_reference_is_the_parameters_own_table() {
    let page = std::fs::read_to_string(root().join("docs/scenes.md")).unwrap();
    let table = defvol::bench::report::block(&page, "parameters");
    let expected = defvol::scene::descriptors::reference_table();
    assert!(expected.lines().count() > 40, "{expected}");
    assert_eq!(table, Some(expected.as_str()), "docs/scenes.md's parameter table should read:\n{expected}");
}

/// The figures of the README's performance table and of `docs/performance.md` are those
/// `defvol bench report --pages` writes from the rows it keeps (`docs/perf/rows.jsonl`):
/// none typed by hand, each row dated and naming its machine and command.
#[test]
fn the_pages_figures_are_the_benchmark_rows_own() {
    use defvol::bench::report::{block, parse_rows, summary, tables, SUMMARY, TABLES};
    let text = std::fs::read_to_string(root().join("docs/perf/rows.jsonl")).unwrap();
    let (rows, skipped) = parse_rows(&text, "docs/perf/rows.jsonl");
    assert!(skipped.is_empty() && rows.len() > 20, "{skipped:?}");
    for stage in ["solver", "warp", "dpcm", "render"] {
        assert!(rows.iter().any(|r| r.stage == stage), "no {stage} rows");
    }
    for row in &rows {
        assert!(
            row.date.is_some() && row.command.as_deref().is_some_and(|c| c.starts_with("defvol bench ")),
            "{}",
            row.line
        );
    }
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    assert_eq!(
        block(&readme, SUMMARY),
        Some(summary(&rows).as_str()),
        "README.md: rerun the command in docs/performance.md"
    );
    let page = std::fs::read_to_string(root().join("docs/performance.md")).unwrap();
    assert_eq!(block(&page, TABLES), Some(tables(&rows).as_str()), "docs/performance.md: rerun its command");
}
