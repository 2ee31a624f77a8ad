//! Files from the field's own tools, and defvol's files in them: meshio, VTK and Gmsh write
//! meshes in every encoding they offer and SimpleITK, nibabel and pynrrd write volumes
//! (tests/interop/files.py), defvol reads each and must find what was written (meshes: the
//! points, the tets, the point array and how many other cells were skipped; volumes: where
//! SimpleITK puts every voxel, and the values); then defvol writes volumes and meshes and
//! every tool reads them back with the same values and geometry.

use std::path::Path;
use std::process::Command;

use defvol::io;
use defvol::volume::Volume;
use nalgebra::{Matrix3, Vector3};
use serde_json::Value;

/// The tools' Python; under tests/run.sh (DEFVOL_REQUIRE_INTEROP=1) it must be there.
fn have_tools() -> bool {
    let ok = Command::new("python3")
        .args(["-c", "import meshio, vtk, gmsh, SimpleITK, nibabel, nrrd"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var_os("DEFVOL_REQUIRE_INTEROP").is_none(),
            "the Python file tools are missing (tests/run.sh installs them)"
        );
        eprintln!("skipped: meshio, vtk, gmsh, SimpleITK, nibabel or pynrrd is not installed");
    }
    ok
}

fn files_py(command: &str, folder: &Path) -> Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/files.py");
    let out = Command::new("python3").arg(script).arg(command).arg(folder).output().unwrap();
    assert!(out.status.success(), "files.py {command}: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()
}

fn close(a: f64, b: f64, tolerance: f64) -> bool {
    (a - b).abs() <= tolerance * (1.0 + a.abs().max(b.abs()))
}

#[test]
fn every_file_the_tools_write_reads_as_written() {
    if !have_tools() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let manifest = files_py("write", dir.path());
    let mut checked = 0;
    let mut failures = Vec::new();
    for (name, expected) in manifest.as_object().unwrap() {
        let path = dir.path().join(name);
        let result = match expected["kind"].as_str() {
            Some("mesh") => check_mesh(&path, expected),
            _ => check_volume(&path, expected),
        };
        if let Err(why) = result {
            failures.push(format!("{name} ({}): {why}", expected["tool"]));
        }
        checked += 1;
    }
    assert!(checked >= 80, "{checked} files");
    assert!(failures.is_empty(), "{} of {checked} files read wrong:\n{}", failures.len(), failures.join("\n"));
}

fn check_mesh(path: &Path, expected: &Value) -> Result<(), String> {
    let io::MeshRead { mesh, skipped, .. } = io::read_mesh_with_metadata(path).map_err(|e| e.to_string())?;
    let points = expected["points"].as_array().unwrap();
    if mesh.nodes().len() != points.len() {
        return Err(format!("{} nodes, {} written", mesh.nodes().len(), points.len()));
    }
    for (k, (got, want)) in mesh.nodes().iter().zip(points).enumerate() {
        let want = floats(want);
        if !(0..3).all(|a| close(got[a], want[a], 1e-9)) {
            return Err(format!("node {k} at {got:?}, written at {want:?}"));
        }
    }
    let mut tets: Vec<[u32; 4]> = mesh.tets().to_vec();
    let mut want: Vec<[u32; 4]> = expected["tets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| {
            let v: Vec<u32> = t.as_array().unwrap().iter().map(|x| x.as_u64().unwrap() as u32).collect();
            [v[0], v[1], v[2], v[3]]
        })
        .collect();
    tets.sort();
    want.sort();
    if tets != want {
        return Err(format!("tets {tets:?}, written {want:?}"));
    }
    let skipped: usize = skipped.values().sum();
    if skipped != expected["skipped"].as_u64().unwrap() as usize {
        return Err(format!("{skipped} other cells skipped, {} written", expected["skipped"]));
    }
    if expected["has_array"].as_bool().unwrap() {
        let values = io::read_mesh_point_array(path, expected["array"].as_str().unwrap()).map_err(|e| e.to_string())?;
        let want = floats(&expected["values"]);
        if values.len() != want.len() || values.iter().zip(&want).any(|(a, b)| !close(f64::from(*a), *b, 1e-6)) {
            return Err(format!("point array {values:?}, written {want:?}"));
        }
    }
    Ok(())
}

fn check_volume(path: &Path, itk: &Value) -> Result<(), String> {
    let v = io::read_volume(path).map_err(|e| e.to_string())?;
    compare_geometry(&v, itk)
}

/// `v` against what SimpleITK read (dims, origin, spacing, direction, checksum, voxels).
fn compare_geometry(v: &Volume, itk: &Value) -> Result<(), String> {
    let dims: Vec<usize> = itk["dims"].as_array().unwrap().iter().map(|d| d.as_u64().unwrap() as usize).collect();
    if v.dims().to_vec() != dims {
        return Err(format!("dims {:?}, ITK {dims:?}", v.dims()));
    }
    let (origin, spacing, direction) = (floats(&itk["origin"]), floats(&itk["spacing"]), floats(&itk["direction"]));
    if !(0..3).all(|a| close(v.origin()[a], origin[a], 1e-5) && close(v.spacing()[a], spacing[a], 1e-5)) {
        return Err(format!("origin {:?} spacing {:?}, ITK {origin:?} {spacing:?}", v.origin(), v.spacing()));
    }
    let itk_direction = Matrix3::from_row_slice(&direction);
    if (v.direction() - itk_direction).norm() > 1e-5 {
        return Err(format!("direction {}, ITK {itk_direction}", v.direction()));
    }
    let sum: f64 = v.data().iter().map(|x| f64::from(*x)).sum();
    let itk_sum = itk["sum"].as_f64().unwrap();
    if !close(sum, itk_sum, 1e-6) {
        return Err(format!("values sum to {sum}, ITK's to {itk_sum}"));
    }
    for (index, value) in itk["picks"].as_object().unwrap() {
        let got = v.data()[index.parse::<usize>().unwrap()];
        if !close(f64::from(got), value.as_f64().unwrap(), 1e-6) {
            return Err(format!("voxel {index} is {got}, ITK reads {value}"));
        }
    }
    Ok(())
}

#[test]
fn every_file_defvol_writes_opens_in_the_tools() {
    if !have_tools() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let rotation = nalgebra::Rotation3::from_euler_angles(0.3, -0.2, 1.1).into_inner();
    let data: Vec<f32> = (0..9 * 7 * 5).map(|i| (i as f32 * 0.37).sin() * 100.0).collect();
    let volume = Volume::new([9, 7, 5], [0.7, 1.3, 2.1], [-4.5, 10.25, 33.0], rotation, data, "written").unwrap();
    for name in ["out.nii", "out.nii.gz", "out.nrrd", "out.mha", "out.mhd"] {
        io::write_volume(&dir.path().join(name), &volume).unwrap();
    }
    let mut mesh = defvol::mesh::generate::lattice(
        Vector3::zeros(),
        Vector3::new(0.3, 0.2, 0.1),
        [3, 2, 2],
        defvol::mesh::generate::CellSplit::Five,
    )
    .unwrap();
    mesh.set_scalars((0..mesh.nodes().len()).map(|i| i as f32).collect()).unwrap();
    for name in ["out.vtu", "out.vtk", "out.msh"] {
        io::write_mesh(&dir.path().join(name), &mesh, None, Some(0.001)).unwrap();
    }
    let found = files_py("read", dir.path());
    let mut failures = Vec::new();
    let sum: f64 = volume.data().iter().map(|x| f64::from(*x)).sum();
    for name in ["out.nii", "out.nii.gz", "out.nrrd", "out.mha", "out.mhd"] {
        let entry = &found[name];
        if let Some(e) = entry.get("error") {
            failures.push(format!("{name}: {e}"));
            continue;
        }
        if let Err(why) = compare_geometry(&volume, &entry["SimpleITK"]) {
            failures.push(format!("{name} in SimpleITK: {why}"));
        }
        if let Some(nib) = entry.get("nibabel") {
            // nibabel's affine is RAS: x and y of ours negated.
            let affine: Vec<Vec<f64>> = nib["affine"].as_array().unwrap().iter().map(floats).collect();
            for r in 0..3 {
                let flip = if r < 2 { -1.0 } else { 1.0 };
                for c in 0..3 {
                    let want = flip * volume.direction()[(r, c)] * volume.spacing()[c];
                    if !close(affine[r][c], want, 1e-5) {
                        failures
                            .push(format!("{name} in nibabel: affine[{r}][{c}] = {}, expected {want}", affine[r][c]));
                    }
                }
                if !close(affine[r][3], flip * volume.origin()[r], 1e-5) {
                    failures.push(format!(
                        "{name} in nibabel: offset {r} = {}, expected {}",
                        affine[r][3],
                        flip * volume.origin()[r]
                    ));
                }
            }
            if !close(nib["sum"].as_f64().unwrap(), sum, 1e-6) {
                failures.push(format!("{name} in nibabel: values sum to {}", nib["sum"]));
            }
        }
        if let Some(nrrd) = entry.get("pynrrd") {
            let origin = floats(&nrrd["space origin"]);
            if nrrd["space"] != "left-posterior-superior"
                || !(0..3).all(|a| close(origin[a], volume.origin()[a], 1e-6))
                || !close(nrrd["sum"].as_f64().unwrap(), sum, 1e-6)
            {
                failures.push(format!("{name} in pynrrd: {nrrd}"));
            }
        }
    }
    for name in ["out.vtu", "out.vtk", "out.msh"] {
        let entry = &found[name];
        if let Some(e) = entry.get("error") {
            failures.push(format!("{name}: {e}"));
            continue;
        }
        let meshio = &entry["meshio"];
        let tets = meshio["tets"].as_array().unwrap().len();
        let points = meshio["points"].as_array().unwrap();
        let first = floats(&points[1]);
        if tets != mesh.tets().len()
            || points.len() != mesh.nodes().len()
            || !(0..3).all(|a| close(first[a], mesh.nodes()[1][a], 1e-12))
        {
            failures.push(format!("{name} in meshio: {tets} tets, {} points", points.len()));
        }
        // The unit travels as field data that both tools read (Gmsh files have no place for it).
        let unit = serde_json::json!({"metres_per_unit": [0.001]});
        if name != "out.msh" && meshio["field_data"] != unit {
            failures.push(format!("{name} in meshio: field data {}", meshio["field_data"]));
        }
        if let Some(vtk) = entry.get("vtk") {
            if vtk["points"].as_u64() != Some(mesh.nodes().len() as u64)
                || vtk["cells"].as_u64() != Some(mesh.tets().len() as u64)
                || vtk["field_data"] != unit
            {
                failures.push(format!("{name} in VTK: {vtk}"));
            }
        }
        if let Some(gmsh) = entry.get("gmsh") {
            if gmsh["tets"].as_u64() != Some(mesh.tets().len() as u64) {
                failures.push(format!("{name} in Gmsh: {gmsh}"));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// The newcomer's path (docs/scenes.md, "Your own CT and organ"): a CT written by SimpleITK
/// and an organ mesh written by meshio, both in millimetres, and the page's own scene beside
/// them; `defvol simulate` presses the probe into that organ: it is held (nothing falls), the
/// probe meets it and pushes back, and no step turns a tet inside out.
#[test]
fn the_documented_scene_presses_a_newcomers_ct_and_organ() {
    if !have_tools() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let page = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/scenes.md")).unwrap();
    let section = page.split("## Your own CT and organ").nth(1).unwrap();
    let yaml = section.split("```yaml\n").nth(1).and_then(|rest| rest.split("```").next()).unwrap();
    std::fs::write(dir.path().join("scene.yaml"), yaml).unwrap();
    let organ = defvol::mesh::generate::ellipsoid(Vector3::zeros(), Vector3::new(50.0, 40.0, 60.0), 8).unwrap();
    let mesh = serde_json::json!({
        "points": organ.nodes().iter().map(|p| [p.x, p.y, p.z]).collect::<Vec<_>>(),
        "tets": organ.tets(),
    });
    std::fs::write(dir.path().join("organ.json"), mesh.to_string()).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/newcomer.py");
    let out = Command::new("python3").arg(script).arg(dir.path()).arg(dir.path().join("organ.json")).output().unwrap();
    assert!(out.status.success(), "newcomer.py: {}", String::from_utf8_lossy(&out.stderr));
    // From another folder: the scene's paths are its own folder's.
    let run = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_defvol"))
        .args(["simulate", "--backend", "cpu", "--scene"])
        .arg(dir.path().join("scene.yaml"))
        .args(["--steps", "80", "--out", "out"])
        .current_dir(run.path())
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{log}");
    assert!(!log.contains("WARN"), "a newcomer's run warns of nothing: {log}");
    let steps = std::fs::read_to_string(run.path().join("out/steps.csv")).unwrap();
    let mut rows = csv::Reader::from_reader(steps.as_bytes());
    let headers = rows.headers().unwrap().clone();
    let column = |name: &str| headers.iter().position(|h| h == name).unwrap();
    let rows: Vec<csv::StringRecord> = rows.records().map(Result::unwrap).collect();
    let value = |row: &csv::StringRecord, name: &str| row[column(name)].parse::<f64>().unwrap();
    let last = rows.last().unwrap();
    eprintln!("last step: {:?} = {:?}", headers, last);
    assert_eq!(rows.len(), 80);
    assert!(value(last, "reaction_fz").abs() > 0.1, "the probe pushes the organ: {:?}", last);
    assert!(value(last, "max_displacement") < 0.02, "held, it does not fall: {:?}", last);
    assert!(rows.iter().all(|row| value(row, "inverted_tets") == 0.0), "no tet inside out");
}
