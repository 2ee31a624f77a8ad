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
    let out = defvol().args(["simulate", "--steps", "12", "--tets", "800", "--backend", "cpu", "--out"]).arg(dir.path()).output().unwrap();
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
