//! The `defvol` binary end to end: the default scene runs and writes its outputs; bad input
//! stops with a message naming what was wrong.

use std::process::Command;

fn defvol() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_defvol"));
    c.env("RUST_LOG", "warn");
    c
}

#[test]
fn simulate_default_scene_writes_mesh_and_step_csv() {
    let dir = tempfile::tempdir().unwrap();
    let warped = dir.path().join("warped.nrrd");
    let out = defvol()
        .args(["simulate", "--steps", "12", "--tets", "800", "--backend", "cpu", "--out"])
        .arg(dir.path())
        .arg("--warp-out")
        .arg(&warped)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let csv = std::fs::read_to_string(dir.path().join("steps.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().collect();
    assert_eq!(rows.len(), 13, "header + one row per step");
    assert!(rows[0].starts_with("step,time,cg_iterations,residual"));
    let last: Vec<f64> = rows[12].split(',').map(|v| v.parse().unwrap()).collect();
    assert_eq!(last[0], 12.0);
    assert!((last[1] - 0.12).abs() < 1e-9);
    assert!(last[6] > 0.0, "the mesh moved: {}", rows[12]);
    let mesh = defvol::io::read_mesh(&dir.path().join("final.vtu")).unwrap();
    assert!(mesh.tets().len() > 500);
    // The phantom carried through the final mesh, still in millimetres at 1 mm spacing.
    let volume = defvol::io::read_volume(&warped).unwrap();
    assert_eq!(volume.spacing(), [1.0; 3]);
    let (lo, hi) = volume.range();
    assert!(lo <= -999.0 && hi >= 700.0, "air and bone present: {lo}..{hi}");
}

#[test]
fn impossible_parameters_and_missing_files_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let out = defvol().args(["simulate", "--dt=-0.01", "--tets", "200", "--out"]).arg(dir.path()).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("dt") && err.contains("-0.01"), "{err}");
    let out = defvol().args(["simulate", "--mesh", "no_such_mesh.vtu", "--out"]).arg(dir.path()).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no_such_mesh.vtu"));
}

#[test]
fn warp_round_trip_keeps_file_units_and_geometry() {
    use defvol::mesh::generate::{self, CellSplit};
    let dir = tempfile::tempdir().unwrap();
    let source = defvol::volume::phantom::phantom([40, 30, 20], 4.0).unwrap();
    let rotated = defvol::volume::Volume::new(
        source.dims(),
        [4.0, 4.0, 5.0],
        [-80.0, 12.0, 33.0],
        nalgebra::Rotation3::from_euler_angles(0.1, 0.0, 0.3).into_inner(),
        source.data().to_vec(),
        "rotated",
    )
    .unwrap();
    let vol_path = dir.path().join("src.mha");
    defvol::io::write_volume(&vol_path, &rotated).unwrap();
    // A lattice over the volume's voxel-centre box, in its own (rotated) frame.
    let cube = generate::lattice(
        nalgebra::Vector3::zeros(),
        nalgebra::Vector3::new(39.0, 29.0, 19.0),
        [4, 3, 2],
        CellSplit::Five,
    )
    .unwrap();
    let mut mesh = cube.clone();
    mesh.map_nodes(|p| rotated.world_from_index(*p));
    let rest_path = dir.path().join("rest.vtu");
    defvol::io::write_mesh(&rest_path, &mesh, None, None).unwrap();
    let out_path = dir.path().join("out.nrrd");
    let out = defvol()
        .args(["warp", "--rest"])
        .arg(&rest_path)
        .arg("--deformed")
        .arg(&rest_path)
        .arg("--volume")
        .arg(&vol_path)
        .arg("--out")
        .arg(&out_path)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let back = defvol::io::read_volume(&out_path).unwrap();
    assert_eq!(back.dims(), rotated.dims());
    assert!((back.direction() - rotated.direction()).norm() < 1e-6);
    for a in 0..3 {
        assert!(
            (back.origin()[a] - rotated.origin()[a]).abs() < 1e-6
                && (back.spacing()[a] - rotated.spacing()[a]).abs() < 1e-9
        );
    }
    let worst = back.data().iter().zip(rotated.data()).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(worst < 1e-2, "identity warp changed values by {worst}");
}

#[test]
fn dpcm_preset_writes_every_rendering_and_a_motion_file_drives_it() {
    let dir = tempfile::tempdir().unwrap();
    let out = defvol()
        .args([
            "dpcm",
            "--preset",
            "loose_soil",
            "--size",
            "96x64",
            "--steps",
            "400",
            "--every",
            "200",
            "--backend",
            "cpu",
            "--out",
        ])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for name in
        ["colour.png", "bump.png", "surface.vtu", "height.mha", "frames/colour_000200.png", "frames/bump_000400.png"]
    {
        assert!(dir.path().join(name).exists(), "{name} missing");
    }
    let decoder =
        png::Decoder::new(std::io::BufReader::new(std::fs::File::open(dir.path().join("colour.png")).unwrap()));
    let reader = decoder.read_info().unwrap();
    assert_eq!((reader.info().width, reader.info().height), (96, 64));
    let height = defvol::io::read_volume(&dir.path().join("height.mha")).unwrap();
    assert_eq!(height.dims(), [96, 64, 1]);
    assert!(height.range().0 < -5e-4, "the vehicles left tracks: {:?}", height.range());

    // A motion file: one tool tip pressing 1.5 mm into the grid's centre (world origin).
    let motion = dir.path().join("press.csv");
    std::fs::write(&motion, "time,marker,x,y,z\n0,0,0,0,0.0015\n0.2,0,0,0,-0.0015\n").unwrap();
    let pressed = dir.path().join("pressed");
    let press = |motion: &std::path::Path| {
        defvol()
            .args([
                "dpcm",
                "--preset",
                "sand",
                "--size",
                "64x64",
                "--steps",
                "200",
                "--render",
                "height",
                "--backend",
                "cpu",
                "--markers",
            ])
            .arg(motion)
            .arg("--out")
            .arg(&pressed)
            .output()
            .unwrap()
    };
    let out = press(&motion);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let h = defvol::io::read_volume(&pressed.join("height.mha")).unwrap();
    let centre = h.data()[32 * 64 + 32];
    let corner = h.data()[0];
    assert!(centre < -1e-3 && centre > -2e-3 && corner == 0.0, "the tip's 1.5 mm: centre {centre}, corner {corner}");
    // A tip that stays at or above the surface presses nothing, and is said to.
    std::fs::write(&motion, "time,marker,x,y,z\n0,0,0,0,0.001\n0.2,0,0,0,0\n").unwrap();
    let out = press(&motion);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && err.contains("no marker reaches below the surface's rest height"), "{err}");
    let h = defvol::io::read_volume(&pressed.join("height.mha")).unwrap();
    assert!(h.data().iter().all(|z| *z == 0.0), "untouched: {:?}", h.range());
}

#[test]
fn dpcm_bad_input_is_named() {
    let dir = tempfile::tempdir().unwrap();
    for (args, needle) in [
        (vec!["--preset", "mud"], "unknown DPCM preset `mud`"),
        (vec!["--size", "10by10"], "--size `10by10`"),
        (vec!["--size", "2x2"], "width"),
        (vec!["--markers", "/nonexistent/motion.csv"], "/nonexistent/motion.csv"),
        (vec!["--udp", "somewhere"], "neither a port nor ADDR:PORT"),
    ] {
        let out = defvol().arg("dpcm").args(&args).args(["--steps", "1", "--out"]).arg(dir.path()).output().unwrap();
        assert!(!out.status.success(), "{args:?} accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{args:?}: {err}");
    }
}

#[test]
fn render_writes_an_image_and_a_depth_map_and_names_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("view.png");
    let depth = dir.path().join("depth.mha");
    let out = defvol()
        .args(["render", "--size", "64x48", "--step", "2", "--out"])
        .arg(&png)
        .arg("--depth-out")
        .arg(&depth)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let reader = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&png).unwrap())).read_info().unwrap();
    assert_eq!((reader.info().width, reader.info().height), (64, 48));
    let d = defvol::io::read_volume(&depth).unwrap();
    assert_eq!(d.dims(), [64, 48, 1]);
    // The phantom fills the middle of the view, some hundreds of mm from the eye.
    let centre = d.data()[24 * 64 + 32];
    assert!(centre > 100.0 && centre < 2000.0, "depth at the centre {centre}");
    for (args, needle) in [
        (vec!["--tf", "pet"], "unknown transfer-function preset `pet`"),
        (vec!["--camera", "0,0,0:0,0,0"], "coincide"),
        (vec!["--size", "0x10"], "image size"),
    ] {
        let out = defvol().arg("render").args(&args).arg("--out").arg(dir.path().join("x.png")).output().unwrap();
        assert!(!out.status.success(), "{args:?} accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{args:?}: {err}");
    }
}

#[test]
fn an_empty_picture_and_a_degenerate_warp_are_said_so() {
    let dir = tempfile::tempdir().unwrap();
    // Looking away from the phantom: an empty picture, still written.
    let away = dir.path().join("away.png");
    let out = defvol()
        .args(["render", "--backend", "cpu", "--size", "32x32", "--camera=0,-2000,0:0,-4000,0", "--out"])
        .arg(&away)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && err.contains("the picture is one colour: nothing is in view"), "{err}");
    let pixels = image_pixels(&away);
    assert!(pixels.chunks(4).all(|p| p == &pixels[..4]), "the warning tells the truth");
    // A mesh over the phantom's empty corner warps air only.
    let phantom = defvol::volume::phantom::phantom(defvol::volume::phantom::DEFAULT_DIMS, 1.0).unwrap();
    let lo = nalgebra::Vector3::from(phantom.bounds().0);
    let corner = lo + nalgebra::Vector3::repeat(12.0);
    let mesh = defvol::mesh::generate::lattice(lo, corner, [2, 2, 2], defvol::mesh::generate::CellSplit::Five).unwrap();
    let rest = dir.path().join("corner.vtu");
    defvol::io::write_mesh(&rest, &mesh, None, None).unwrap();
    let warped = dir.path().join("corner.nrrd");
    let out = defvol()
        .args(["warp", "--backend", "cpu", "--rest"])
        .arg(&rest)
        .arg("--deformed")
        .arg(&rest)
        .arg("--out")
        .arg(&warped)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && err.contains("the warped volume is degenerate"), "{err}");
    let (low, high) = defvol::io::read_volume(&warped).unwrap().range();
    assert_eq!(low, high, "the warning tells the truth");
}

#[test]
fn render_draws_a_tetrahedral_mesh_with_sampled_or_named_scalars() {
    let dir = tempfile::tempdir().unwrap();
    let phantom = defvol::volume::phantom::phantom([64, 40, 31], 4.0).unwrap();
    let (lo, hi) = phantom.bounds();
    let mesh = defvol::mesh::generate::lattice_for_box(lo, hi, 600, defvol::mesh::generate::CellSplit::Five).unwrap();
    let mesh_path = dir.path().join("organ.vtu");
    defvol::io::write_mesh(&mesh_path, &mesh, None, None).unwrap();
    let png = dir.path().join("mesh.png");
    let depth = dir.path().join("depth.nrrd");
    let out = defvol()
        .args(["render", "--size", "48x48", "--step", "4", "--mesh"])
        .arg(&mesh_path)
        .arg("--out")
        .arg(&png)
        .arg("--depth-out")
        .arg(&depth)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let d = defvol::io::read_volume(&depth).unwrap();
    let hit = d.data().iter().filter(|v| **v > 0.0).count();
    assert!(hit > 48 * 48 / 10, "the mesh covers {hit} pixels");
    let out = defvol()
        .args(["render", "--mesh-scale", "0", "--mesh"])
        .arg(&mesh_path)
        .arg("--out")
        .arg(&png)
        .output()
        .unwrap();
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("--mesh-scale"));
    // Node values from a named point array: uniform dense tissue everywhere is opaque
    // wherever the mesh is, unlike the phantom's air-filled corners.
    let mut labelled = mesh.clone();
    labelled.set_scalars(vec![700.0; mesh.nodes().len()]).unwrap();
    let labelled_path = dir.path().join("labelled.vtu");
    defvol::io::write_mesh(&labelled_path, &labelled, None, None).unwrap();
    let out = defvol()
        .args(["render", "--size", "48x48", "--scalars", "scalar", "--mesh"])
        .arg(&labelled_path)
        .arg("--out")
        .arg(&png)
        .arg("--depth-out")
        .arg(&depth)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let dense = defvol::io::read_volume(&depth).unwrap().data().iter().filter(|v| **v > 0.0).count();
    assert!(dense > hit, "uniform dense tissue covers {dense} pixels, the phantom's values {hit}");
    let out = defvol()
        .args(["render", "--scalars", "dose", "--mesh"])
        .arg(&labelled_path)
        .arg("--out")
        .arg(&png)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("`dose`") && err.contains("scalar"), "{err}");
}

#[test]
fn render_shows_the_source_through_a_deformed_mesh_as_the_moved_volume_looks() {
    let dir = tempfile::tempdir().unwrap();
    let phantom = defvol::volume::phantom::phantom([64, 40, 31], 4.0).unwrap();
    let (lo, hi) = phantom.bounds();
    // The mesh on the voxel-centre box, moved 20 mm up: the source through it is the
    // phantom moved 20 mm up.
    let mesh = defvol::mesh::generate::lattice(lo, hi, [8, 5, 4], defvol::mesh::generate::CellSplit::Five).unwrap();
    let lift = nalgebra::Vector3::new(0.0, 0.0, 20.0);
    let mut moved = mesh.clone();
    moved.map_nodes(|p| p + lift);
    let lifted = defvol::volume::Volume::new(
        phantom.dims(),
        phantom.spacing(),
        (nalgebra::Vector3::from(phantom.origin()) + lift).into(),
        *phantom.direction(),
        phantom.data().to_vec(),
        "lifted",
    )
    .unwrap();
    let paths = ["src.mha", "lifted.mha", "rest.vtu", "moved.vtu", "a.png", "b.png", "a.nrrd", "b.nrrd"]
        .map(|name| dir.path().join(name));
    defvol::io::write_volume(&paths[0], &phantom).unwrap();
    defvol::io::write_volume(&paths[1], &lifted).unwrap();
    defvol::io::write_mesh(&paths[2], &mesh, None, None).unwrap();
    defvol::io::write_mesh(&paths[3], &moved, None, None).unwrap();
    let c = (lo + hi) / 2.0 + lift;
    let camera = format!("--camera={},{},{}:{},{},{}", c.x - 150.0, c.y - 380.0, c.z + 120.0, c.x, c.y, c.z);
    let common = ["render", "--size", "48x40", "--step", "2", "--shading", "none", &camera];
    let out = defvol()
        .args(common)
        .args(["--backend", "cpu", "--volume"])
        .arg(&paths[0])
        .arg("--mesh")
        .arg(&paths[2])
        .arg("--deformed")
        .arg(&paths[3])
        .arg("--out")
        .arg(&paths[4])
        .arg("--depth-out")
        .arg(&paths[6])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let out = defvol()
        .args(common)
        .args(["--backend", "cpu", "--volume"])
        .arg(&paths[1])
        .arg("--out")
        .arg(&paths[5])
        .arg("--depth-out")
        .arg(&paths[7])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (a, b) = (defvol::io::read_volume(&paths[6]).unwrap(), defvol::io::read_volume(&paths[7]).unwrap());
    let both: Vec<(f32, f32)> =
        a.data().iter().zip(b.data()).filter(|(x, y)| **x > 0.0 && **y > 0.0).map(|(x, y)| (*x, *y)).collect();
    assert!(both.len() > 48 * 40 / 5, "{} pixels see tissue in both", both.len());
    let off = both.iter().filter(|(x, y)| (x - y).abs() > 2.0).count();
    assert!(off <= both.len() / 50, "{off} of {} depths differ by more than a step", both.len());
    // A deformed mesh that is not the rest mesh's is named.
    let other = defvol::mesh::generate::lattice(lo, hi, [2, 2, 2], defvol::mesh::generate::CellSplit::Five).unwrap();
    defvol::io::write_mesh(&paths[3], &other, None, None).unwrap();
    let out = defvol()
        .args(["render", "--mesh"])
        .arg(&paths[2])
        .arg("--deformed")
        .arg(&paths[3])
        .arg("--out")
        .arg(&paths[4])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("its tets are not"), "{err}");
}

#[test]
fn logs_go_to_stderr_uncoloured_when_piped_and_numbers_print_plainly() {
    let dir = tempfile::tempdir().unwrap();
    let out = defvol()
        .env("RUST_LOG", "info")
        .args(["simulate", "--steps", "10", "--tets", "200", "--backend", "cpu", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.stdout.is_empty(), "stdout is for data: {}", String::from_utf8_lossy(&out.stdout));
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(log.contains("step    10"), "{log}");
    assert!(!log.contains('\u{1b}'), "no colour codes into a pipe: {log:?}");
    let reaction = log.lines().find(|l| l.contains("step    10")).unwrap();
    assert!(reaction.contains(" N") && !reaction.contains("Some(") && !reaction.contains("-0,"), "{reaction}");
}

#[cfg(feature = "ros")]
#[test]
fn the_node_prints_its_options_on_help_under_both_names() {
    for (program, prefix) in [(env!("CARGO_BIN_EXE_defvol"), vec!["node"]), (env!("CARGO_BIN_EXE_defvol_node"), vec![])]
    {
        let out = Command::new(program).args(prefix).arg("--help").output().unwrap();
        let help = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{program}: {}", String::from_utf8_lossy(&out.stderr));
        assert!(help.contains("--record") && help.contains("--backend") && help.contains("--ros-args"), "{help}");
        assert!(!help.contains("Error"), "{help}");
    }
}

#[test]
fn negative_numbers_are_values_not_flags() {
    let dir = tempfile::tempdir().unwrap();
    let out = defvol().args(["simulate", "--dt", "-0.01", "--tets", "200", "--out"]).arg(dir.path()).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("solver.dt = -0.01 is outside"), "refused by the scene's range, not by the parser: {err}");
}

#[test]
fn output_names_are_refused_before_the_work() {
    let dir = tempfile::tempdir().unwrap();
    let cases: [(Vec<String>, &str); 4] = [
        (vec!["render".into(), "--out".into(), dir.path().join("x.jpg").display().to_string()], "name the file .png"),
        (vec!["warp".into(), "--out".into(), dir.path().join("w.png").display().to_string()], ".nii, .nii.gz, .nrrd"),
        (
            vec!["warp".into(), "--out".into(), dir.path().join("no/such/w.nrrd").display().to_string()],
            "does not exist",
        ),
        (
            vec![
                "render".into(),
                "--out".into(),
                dir.path().join("r.png").display().to_string(),
                "--depth-out".into(),
                dir.path().join("depth.png").display().to_string(),
            ],
            ".nii, .nii.gz, .nrrd",
        ),
    ];
    for (args, expected) in cases {
        let out = defvol().args(&args).args(["--backend", "cpu"]).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(expected), "{args:?}: {err}");
    }
    // Nothing was written: the checks came first.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[cfg(feature = "mcap")]
#[test]
fn replay_refuses_a_missing_or_foreign_bag_before_it_builds_anything() {
    let dir = tempfile::tempdir().unwrap();
    let foreign = dir.path().join("notes.mcap");
    std::fs::write(&foreign, "not a bag").unwrap();
    for (bag, expected) in [(dir.path().join("none.mcap"), "none.mcap"), (foreign, "not an MCAP file")] {
        let out = defvol().env("RUST_LOG", "info").arg("replay").arg(&bag).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(expected), "{err}");
        assert!(!err.contains("DPCM") && !err.contains("warp:"), "refused before the pipeline: {err}");
    }
}

#[test]
fn choices_take_the_spelling_of_the_files_and_of_the_flags() {
    let dir = tempfile::tempdir().unwrap();
    for integrator in ["implicit_euler", "implicit-euler"] {
        let out = defvol()
            .args(["simulate", "--integrator", integrator, "--steps", "2", "--tets", "200", "--backend", "cpu"])
            .arg("--out")
            .arg(dir.path())
            .output()
            .unwrap();
        assert!(out.status.success(), "{integrator}: {}", String::from_utf8_lossy(&out.stderr));
    }
    let out = defvol().args(["simulate", "--integrator", "implicit_eulerr"]).output().unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("implicit_eulerr"), "an unknown one is still named");
    let file: defvol::dpcm::render::ColorMap = serde_yaml_ng::from_str("red-blue").unwrap();
    assert_eq!(file, serde_yaml_ng::from_str("red_blue").unwrap());
}

#[test]
fn a_users_mesh_simulates_held_by_its_lowest_layer_or_by_fix() {
    use defvol::mesh::generate::{self, CellSplit};
    let dir = tempfile::tempdir().unwrap();
    // A 10 cm cube on 5x5x5 cells: its bottom layer is 36 nodes, far from the default scene's
    // clamp plane.
    let cube = generate::lattice(
        nalgebra::Vector3::new(0.0, 0.0, 0.3),
        nalgebra::Vector3::new(0.1, 0.1, 0.4),
        [5, 5, 5],
        CellSplit::Five,
    )
    .unwrap();
    let path = dir.path().join("cube.vtu");
    defvol::io::write_mesh(&path, &cube, None, Some(1.0)).unwrap();
    let run = |extra: &[&str]| {
        defvol()
            .env("RUST_LOG", "info")
            .args(["simulate", "--steps", "20", "--backend", "cpu", "--mesh"])
            .arg(&path)
            .args(extra)
            .arg("--out")
            .arg(dir.path().join("out"))
            .output()
            .unwrap()
    };
    let out = run(&[]);
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{log}");
    assert!(log.contains("fixed 36 of 216 nodes: the lowest 2% of the mesh's height"), "{log}");
    let csv = std::fs::read_to_string(dir.path().join("out/steps.csv")).unwrap();
    let last: Vec<f64> = csv.lines().last().unwrap().split(',').map(|v| v.parse().unwrap()).collect();
    assert!(last[6] < 0.02, "held, it sags a little rather than falling: {} m", last[6]);
    // The same cube in millimetres with no unit recorded: read in the scene's file units.
    let mut in_mm = cube.clone();
    in_mm.map_nodes(|p| p * 1000.0);
    defvol::io::write_mesh(&path, &in_mm, None, None).unwrap();
    let out = run(&[]);
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && log.contains("x0.001 to metres (the scene's file_to_world 0.001)"), "{log}");
    assert!(log.contains("fixed 36 of 216 nodes") && log.contains("0.1000 m across"), "{log}");
    let out = run(&["--mesh-scale", "1"]);
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(log.contains("is 100.0000 m across: is its unit right?"), "{log}");
    let out = run(&["--fix", "nodes:0,1,2"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("fixed 3 of 216 nodes"));
    let out = run(&["--fix", "plane:0,0,1"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("plane takes 4 numbers, got 3"));
}

#[test]
fn simulate_meshes_record_metres_and_meet_a_millimetre_volume_by_that_unit() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    let out = defvol()
        .args(["simulate", "--steps", "5", "--tets", "200", "--backend", "cpu", "--out"])
        .arg(&sim)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (rest, last) = (sim.join("rest.vtu"), sim.join("final.vtu"));
    let read = defvol::io::read_mesh_with_metadata(&rest).unwrap();
    assert_eq!(read.metres_per_unit, Some(1.0), "simulate records metres");
    assert_eq!(read.mesh.nodes().len(), defvol::io::read_mesh(&last).unwrap().nodes().len());
    // The phantom (millimetres) under both commands, the meshes as simulate wrote them.
    let warp = |scale: &[&str], out: &std::path::Path| {
        defvol()
            .env("RUST_LOG", "info")
            .args(["warp", "--backend", "cpu", "--rest"])
            .arg(&rest)
            .arg("--deformed")
            .arg(&last)
            .args(scale)
            .arg("--out")
            .arg(out)
            .output()
            .unwrap()
    };
    let (by_unit, by_flag) = (dir.path().join("unit.nrrd"), dir.path().join("flag.nrrd"));
    let done = warp(&[], &by_unit);
    let log = String::from_utf8_lossy(&done.stderr);
    assert!(done.status.success() && log.contains("records 1 m per unit: x1000 into millimetres"), "{log}");
    let volume = defvol::io::read_volume(&by_unit).unwrap();
    assert!(volume.dims().iter().all(|d| *d > 10), "a real warp, not one voxel: {:?}", volume.dims());
    assert!(warp(&["--mesh-scale", "1000"], &by_flag).status.success());
    assert_eq!(volume.data(), defvol::io::read_volume(&by_flag).unwrap().data(), "the unit is the flag's 1000");
    let refused = warp(&["--mesh-scale", "1"], &dir.path().join("w.nrrd"));
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && err.contains("try --mesh-scale 1000"), "{err}");
    assert!(!dir.path().join("w.nrrd").exists(), "nothing written for a refused mesh");
    let render = |mesh: &std::path::Path, picture: &std::path::Path| {
        let mut render = defvol();
        render.args(["render", "--backend", "cpu", "--size", "64x64", "--mesh"]).arg(mesh);
        render.arg("--out").arg(picture).output().unwrap()
    };
    let picture = dir.path().join("r.png");
    let out = render(&last, &picture);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let pixels = image_pixels(&picture);
    let background = &pixels[..4];
    let drawn = pixels.chunks(4).filter(|p| *p != background).count();
    assert!(drawn > 64 * 64 / 10, "the mesh fills the picture: {drawn} pixels drawn");
    // The same nodes in a file that records no unit are taken as the volume's, and refused.
    let bare = dir.path().join("bare.vtu");
    defvol::io::write_mesh(&bare, &read.mesh, None, None).unwrap();
    let out = render(&bare, &dir.path().join("bare.png"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("try --mesh-scale 1000"), "{err}");
}

#[test]
fn displacement_volumes_alone_warp_the_phantom_on_its_own_grid_with_no_bend() {
    let dir = tempfile::tempdir().unwrap();
    let pushed = dir.path().join("pushed.mha");
    let out = defvol()
        .args(["warp", "--backend", "cpu", "--displace", "0,0,0:0,0,5:40", "--out"])
        .arg(&pushed)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let volume = defvol::io::read_volume(&pushed).unwrap();
    let phantom = defvol::volume::phantom::phantom(defvol::volume::phantom::DEFAULT_DIMS, 1.0).unwrap();
    assert_eq!(volume.dims(), phantom.dims(), "the source's grid, not a bent mesh's box");
    assert_eq!(volume.origin(), phantom.origin());
}

#[test]
fn an_error_names_its_cause_once() {
    let dir = tempfile::tempdir().unwrap();
    let out =
        defvol().args(["warp", "--volume", "nosuch.nrrd", "--out"]).arg(dir.path().join("w.nrrd")).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("nosuch.nrrd"), "{err}");
    assert_eq!(err.matches("No such file or directory").count(), 1, "{err}");
}

#[test]
fn a_scene_typo_is_named_by_its_field_path_with_the_nearest_name() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("typo.yaml");
    std::fs::write(&scene, defvol::scene::DEFAULT_SCENE.replace("  stiffness: 1000.0", "  stifness: 1000.0")).unwrap();
    let out = defvol().args(["simulate", "--steps", "1", "--scene"]).arg(&scene).arg("--out").arg(dir.path()).output();
    let out = out.unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(err.contains("typo.yaml: material: unknown field, expected"), "{err}");
    assert!(!err.contains("stifness"), "the text found is withheld: {err}");
    assert!(err.contains("(did you mean `stiffness`?)"), "{err}");
}

#[test]
fn solver_bench_cases_are_named_by_their_tets_as_the_readme_counts_them() {
    let common = ["bench", "solver", "--sizes", "80", "--steps", "2", "--tolerances", "1e-2", "--backends", "cpu"];
    let out = defvol().args(common).args(["--preconditioners", "amg", "--json"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let rows: Vec<serde_json::Value> =
        String::from_utf8_lossy(&out.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert!(!rows.is_empty());
    for row in &rows {
        assert_eq!((row["case"].as_str(), row["work"]["tets"].as_u64()), (Some("cantilever_80tets"), Some(80)));
    }
    let out = defvol().args(common).args(["--preconditioners", "amg"]).output().unwrap();
    let table = String::from_utf8_lossy(&out.stdout);
    let (header, first) = (table.lines().next().unwrap(), table.lines().nth(1).unwrap());
    assert_eq!(header.find("backend"), first.find(" cpu ").map(|at| at + 1), "columns line up:\n{table}");
    assert!(!table.contains("NaN"), "{table}");
}

/// `defvol ARGS --json` (ARGS split at spaces), its rows.
fn bench_rows(args: &str) -> Vec<serde_json::Value> {
    let out = defvol().args(args.split_whitespace()).arg("--json").output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

/// The DPCM bench's GPU rows say what a step cost the GPU: batched, a tenth of a submission
/// a step; nothing read back while stepping; GPU time measured by timestamps (lavapipe has
/// them) and no longer than the step's wall time; the batched state the single steps' one.
#[test]
fn dpcm_bench_gpu_rows_report_the_round_trips_and_gpu_time_of_a_batched_step() {
    let Some(_) = defvol::gpu::test_context() else { return };
    let rows = bench_rows(
        "bench dpcm --gpu --allow-software-gpu --size 64,64 --markers 3 --topologies eight --physics elastic \
         --steps 40 --no-sweep --batch 1,10",
    );
    let gpu: Vec<&serde_json::Value> = rows.iter().filter(|r| r["backend"] == "gpu").collect();
    assert_eq!(gpu.len(), 2, "{rows:?}");
    for (row, batch) in gpu.iter().zip([1.0, 10.0]) {
        let cost = &row["gpu"];
        assert_eq!(row["params"]["batch"].as_f64(), Some(batch));
        assert_eq!(cost["submissions"].as_f64(), Some(1.0 / batch), "{row}");
        assert_eq!(cost["readbacks"].as_f64(), Some(0.0), "{row}");
        assert_eq!(cost["timestamps"], "available", "{row}");
        let kernel_ms = cost["kernel_ms"].as_f64().unwrap();
        assert!(kernel_ms > 0.0 && kernel_ms <= row["time_ms"]["max"].as_f64().unwrap(), "{row}");
        assert!(row["error"]["value"].as_f64().unwrap() < 1e-4, "{row}");
    }
}

/// The solver bench's GPU rows: an explicit batch of 10 steps is one submission with its
/// read-back (0.1 each a step), its GPU time measured and its error that of the scheme;
/// the implicit row reads back at most once per CG window and once for the state.
#[test]
fn solver_bench_gpu_rows_report_batched_explicit_steps_and_the_implicit_round_trips() {
    let Some(_) = defvol::gpu::test_context() else { return };
    let rows = bench_rows(
        "bench solver --sizes 80 --steps 21 --tolerances 1e-4 --preconditioners block-jacobi --backends gpu \
         --allow-software-gpu --explicit-dt 1e-4 --explicit-batch 10",
    );
    assert_eq!(rows.len(), 4, "{rows:?}");
    for row in &rows {
        let cost = &row["gpu"];
        assert_eq!(cost["timestamps"], "available", "{row}");
        assert!(cost["kernel_ms"].as_f64().unwrap() > 0.0, "{row}");
        assert!(row["error"]["value"].as_f64().unwrap() < 1e-2, "{row}");
        // The cantilever bends a little: no tet turns inside out, and the row says so.
        assert_eq!(row["work"]["inverted_tets"].as_u64(), Some(0), "{row}");
        if row["params"]["integrator"] == "implicit_euler" {
            // 1 a step where the last step foretold its CG windows, else those beyond the
            // foretold ones and 3: below i / 16 + 3 on average.
            let windows = row["work"]["cg_iterations_mean"].as_f64().unwrap() / 16.0;
            assert!(cost["readbacks"].as_f64().unwrap() < windows + 3.0, "{row}");
        } else {
            assert_eq!(row["params"]["batch"].as_u64(), Some(10), "{row}");
            assert_eq!((cost["submissions"].as_f64(), cost["readbacks"].as_f64()), (Some(0.1), Some(0.1)), "{row}");
        }
    }
}

/// A PNG's pixels as RGBA bytes.
fn image_pixels(path: &std::path::Path) -> Vec<u8> {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut pixels = vec![0; reader.output_buffer_size().unwrap()];
    let frame = reader.next_frame(&mut pixels).unwrap();
    pixels.truncate(frame.buffer_size());
    pixels
}

/// A tet hung from its base under gravity, its springs far too soft for its weight: the apex
/// falls through the base and the tet turns inside out (at step 81; the fall diverges at 88).
/// `simulate` goes on, counts it in every step's row and warns once with the first step and
/// the worst tet.
#[test]
fn simulate_counts_and_reports_tets_turned_inside_out() {
    use nalgebra::Vector3;
    let dir = tempfile::tempdir().unwrap();
    // 3 m across and far from the default scene's probe: some tonnes on springs of 1000 N/m.
    let corner = Vector3::repeat(10.0);
    let nodes = [Vector3::zeros(), Vector3::x(), Vector3::y(), Vector3::new(0.2, 0.2, 1.0)].map(|p| corner + 3.0 * p);
    let tet = defvol::mesh::TetMesh::new(nodes.to_vec(), vec![[0, 1, 2, 3]], None, "tet").unwrap();
    defvol::io::write_mesh(&dir.path().join("tet.vtu"), &tet, None, Some(1.0)).unwrap();
    let out = defvol()
        .args(["simulate", "--mesh", "tet.vtu", "--steps", "85", "--backend", "cpu", "--out", "out"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let csv = std::fs::read_to_string(dir.path().join("out/steps.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().collect();
    assert!(rows[0].ends_with(",inverted_tets"), "{}", rows[0]);
    let counts: Vec<&str> = rows[1..].iter().map(|r| r.rsplit(',').next().unwrap()).collect();
    let first = counts.iter().position(|c| *c == "1").expect("the tet never turned inside out") + 1;
    assert!(first > 1 && counts[..first - 1].iter().all(|c| *c == "0"), "{counts:?}");
    assert!(
        stderr.contains(&format!("step {first}: 1 tet inverted (the worst, tet 0, at -"))
            && stderr.contains(&format!("tets turned inside out from step {first}")),
        "{stderr}"
    );
}

/// A deformed mesh with tets turned inside out (one node pushed through the opposite face
/// of its tet) is drawn, never refused, on both backends: the warning names how many and
/// the worst, and the picture differs from the uninverted one only where those tets lie.
#[test]
fn render_draws_a_deformed_mesh_with_inverted_tets_and_says_how_many() {
    let dir = tempfile::tempdir().unwrap();
    let run = |args: &[&str]| {
        let out = defvol().args(args).current_dir(dir.path()).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "{args:?}: {stderr}");
        stderr
    };
    run(&["simulate", "--steps", "3", "--tets", "300", "--backend", "cpu", "--out", "out"]);
    let rest = defvol::io::read_mesh(&dir.path().join("out/rest.vtu")).unwrap();
    let mut moved = defvol::io::read_raw_mesh(&dir.path().join("out/final.vtu")).unwrap().nodes;
    let [a, b, c, d] = rest.tets()[0].map(|n| n as usize);
    let normal = (moved[c] - moved[b]).cross(&(moved[d] - moved[b])).normalize();
    let through = 2.2 * (moved[a] - moved[b]).dot(&normal) * normal;
    moved[a] -= through;
    defvol::io::write_mesh(&dir.path().join("out/inverted.vtu"), &rest, Some(&moved), Some(1.0)).unwrap();
    let inverted = rest.inverted(&moved);
    assert!(inverted.count >= 1 && inverted.worst.is_some_and(|(t, r)| t == 0 && r < -1.0), "{inverted:?}");
    for backend in [&["--backend", "cpu"][..], &["--backend", "gpu", "--allow-software-gpu"]] {
        let render = |deformed: &str, png: &str| {
            let mut args = vec!["render", "--mesh", "out/rest.vtu", "--deformed", deformed, "--size", "64x48"];
            args.extend(backend);
            args.extend(["--out", png]);
            run(&args)
        };
        let stderr = render("out/inverted.vtu", "inverted.png");
        let said = format!("{} tets turned inside out (the worst, tet 0, at -1.", inverted.count);
        assert!(stderr.contains(&said) && !stderr.contains("one colour"), "{backend:?}: {stderr}");
        render("out/final.vtu", "upright.png");
        let pixels = |png: &str| image_pixels(&dir.path().join(png));
        let (bent, upright) = (pixels("inverted.png"), pixels("upright.png"));
        let differ = bent.chunks(4).zip(upright.chunks(4)).filter(|(p, q)| p != q).count();
        assert!(differ < 64 * 48 / 10, "{backend:?}: {differ} of {} pixels differ", 64 * 48);
    }
}

/// `info` describes a mesh the solver would refuse instead of refusing it: a unit cube in
/// five tets, a tet touching it along one edge only, a sliver, an inverted tet, a tet that
/// names a node twice and a node no tet uses, each counted; the quality figures are the
/// analytic ones (a cube corner tet's smallest dihedral angle is acos(1/√3)).
#[test]
fn info_counts_what_a_messy_mesh_holds_and_never_refuses_it() {
    use nalgebra::Vector3;
    let cube = defvol::mesh::generate::lattice(
        Vector3::zeros(),
        Vector3::repeat(1.0),
        [1, 1, 1],
        defvol::mesh::generate::CellSplit::Five,
    )
    .unwrap();
    let mut nodes: Vec<Vector3<f64>> = cube.nodes().to_vec();
    let mut tets: Vec<[u32; 4]> = cube.tets().to_vec();
    let add = |points: [[f64; 3]; 4], nodes: &mut Vec<Vector3<f64>>, positive: bool| -> [u32; 4] {
        let index = points.map(|p| match nodes.iter().position(|q| (q - Vector3::from(p)).norm() < 1e-12) {
            Some(i) => i as u32,
            None => {
                nodes.push(Vector3::from(p));
                nodes.len() as u32 - 1
            }
        });
        let mut t = index;
        if (defvol::mesh::signed_volume(nodes, &t) > 0.0) != positive {
            t.swap(2, 3);
        }
        t
    };
    tets.push(add([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.5, 0.5, -1.0], [2.0, 0.5, 0.0]], &mut nodes, true));
    tets.push(add([[5.0, 0.0, 0.0], [6.0, 0.0, 0.0], [5.0, 1.0, 0.0], [6.0, 1.0, 0.01]], &mut nodes, true));
    tets.push(add([[10.0, 0.0, 0.0], [11.0, 0.0, 0.0], [10.0, 1.0, 0.0], [10.0, 0.0, 1.0]], &mut nodes, false));
    tets.push([0, 0, 1, 2]);
    nodes.push(Vector3::repeat(20.0));
    let mut text =
        format!("# vtk DataFile Version 3.0\nmessy\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS {} double\n", nodes.len());
    for p in &nodes {
        text += &format!("{} {} {}\n", p.x, p.y, p.z);
    }
    text += &format!("CELLS {} {}\n", tets.len(), 5 * tets.len());
    for t in &tets {
        text += &format!("4 {} {} {} {}\n", t[0], t[1], t[2], t[3]);
    }
    text += &format!("CELL_TYPES {}\n{}", tets.len(), "10\n".repeat(tets.len()));
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("messy.vtk"), text).unwrap();
    let out = defvol().args(["info", "messy.vtk", "--json"]).current_dir(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let got: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let count = |key: &str| got[key].as_u64().unwrap_or_else(|| panic!("{key}: {got}"));
    let counts = [
        "nodes",
        "tets",
        "unused_nodes_dropped",
        "broken_tets",
        "flat_tets",
        "inverted_tets",
        "slivers",
        "boundary_triangles",
        "boundary_components",
        "non_manifold_edges",
        "non_manifold_vertices",
        "overfull_faces",
    ]
    .map(count);
    assert_eq!(counts, [18, 9, 1, 1, 0, 1, 1, 24, 3, 1, 0, 0], "{got}");
    let corner = (1.0 / 3f64.sqrt()).acos().to_degrees();
    let dihedral = &got["min_dihedral_deg"];
    assert!(dihedral["min"].as_f64().unwrap() < 5.0, "{got}");
    assert!((dihedral["median"].as_f64().unwrap() - corner).abs() < 1e-9, "{got}");
    assert_eq!(got["bounds"], serde_json::json!([[0.0, 0.0, -1.0], [11.0, 1.0, 1.0]]), "{got}");
    let text = defvol().args(["info", "messy.vtk"]).current_dir(dir.path()).output().unwrap();
    assert!(text.status.success() && String::from_utf8_lossy(&text.stdout).contains("inverted_tets: 1"));
}

/// A scene whose `fixed` holds no node (the phantom's plane under a user's organ) is warned
/// of at load, naming the fix; the run then says the organ fell, not that it diverged.
#[test]
fn a_scene_holding_no_node_is_warned_of_and_its_fall_named() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene.yaml");
    let text = "mesh: {kind: volume_lattice, target_tets: 200, split: five}\n\
                fixed: {kind: plane, normal: [0, 0, 1], offset: -5}\nstages: {solver: true}\ntools: []\n";
    std::fs::write(&scene, text).unwrap();
    let mut simulate = defvol();
    simulate.args(["simulate", "--scene"]).arg(&scene).args(["--steps", "100", "--out"]).arg(dir.path());
    let out = simulate.output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no node is held: `fixed` (below the plane [0.0, 0.0, 1.0] · x = -5) selects none"), "{err}");
    assert!(err.contains("`fixed: {kind: lowest}` rests it on its lowest layer"), "{err}");
    assert!(err.contains("the mesh fell freely") && !err.contains("diverged"), "{err}");
}
