//! DICOM series written by SimpleITK (GDCM) as a scanner writes them (tests/interop/dicom.py):
//! defvol reads each as ITK's ImageSeriesReader does, voxel for voxel and to 1e-4 mm in
//! origin, spacing and direction, and refuses what is not one regular volume by its reason.

use std::path::Path;
use std::process::Command;

use defvol::io;
use serde_json::Value;

/// SimpleITK; under tests/run.sh (DEFVOL_REQUIRE_INTEROP=1) it must be there.
fn have_simpleitk() -> bool {
    let ok = Command::new("python3").args(["-c", "import SimpleITK"]).output().is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var_os("DEFVOL_REQUIRE_INTEROP").is_none(),
            "SimpleITK is missing (tests/run.sh installs it)"
        );
        eprintln!("skipped: SimpleITK is not installed");
    }
    ok
}

/// Writes the cases into `dir`; what each holds.
fn write_cases(dir: &Path) -> Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/dicom.py");
    let out = Command::new("python3").arg(script).arg("write").arg(dir).output().unwrap();
    assert!(out.status.success(), "dicom.py: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

/// defvol's read of `case` (series `uid`) against ITK's, written beside it as `.mha`.
fn matches_itk(dir: &Path, case: &str, uid: &str, ours: &defvol::volume::Volume) -> Result<(), String> {
    let itk = io::read_volume(&dir.join(format!("{case}.{uid}.mha"))).map_err(|e| e.to_string())?;
    if ours.dims() != itk.dims() {
        return Err(format!("dims {:?}, ITK {:?}", ours.dims(), itk.dims()));
    }
    let far = |a: [f64; 3], b: [f64; 3]| (0..3).any(|k| (a[k] - b[k]).abs() > 1e-4);
    if far(ours.origin(), itk.origin()) || far(ours.spacing(), itk.spacing()) {
        return Err(format!(
            "origin {:?} spacing {:?}, ITK {:?} {:?}",
            ours.origin(),
            ours.spacing(),
            itk.origin(),
            itk.spacing()
        ));
    }
    if (ours.direction() - itk.direction()).abs().max() > 1e-6 {
        return Err(format!("direction {}, ITK {}", ours.direction(), itk.direction()));
    }
    let differ = ours.data().iter().zip(itk.data()).position(|(a, b)| a != b);
    if let Some(at) = differ {
        return Err(format!("voxel {at} is {}, ITK reads {}", ours.data()[at], itk.data()[at]));
    }
    Ok(())
}

#[test]
fn dicom_series_read_as_itk_reads_them_and_irregular_ones_are_refused_by_their_reason() {
    if !have_simpleitk() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let cases = write_cases(dir.path());
    let mut failures = Vec::new();
    for (case, entry) in cases.as_object().unwrap() {
        let folder = dir.path().join(case);
        let read = io::read_dicom(&folder, None);
        match (entry["readable"].as_bool().unwrap(), read) {
            (true, Ok(read)) => {
                let uid = entry["series"][0].as_str().unwrap();
                if read.series.uid != uid {
                    failures.push(format!("{case}: read series {}, the largest is {uid}", read.series.uid));
                }
                if let Err(why) = matches_itk(dir.path(), case, uid, &read.volume) {
                    failures.push(format!("{case}: {why}"));
                }
            }
            (true, Err(e)) => failures.push(format!("{case}: refused: {e}")),
            (false, Ok(_)) => failures.push(format!("{case}: read, but it is not one regular volume")),
            (false, Err(e)) => {
                let reason = match case.as_str() {
                    "missing_slice" => "a slice is missing",
                    "uneven" => "uneven slice spacing",
                    _ => "gantry tilt",
                };
                let text = e.to_string();
                if !(text.contains(reason) && text.contains(".dcm")) {
                    failures.push(format!("{case}: refused without naming the files and `{reason}`: {text}"));
                }
            }
        }
    }
    assert!(cases.as_object().unwrap().len() >= 8, "{cases}");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// A folder of two series: the larger is read and the other listed; `read_volume_series`
/// picks either by its UID; an unknown UID is refused naming the ones there; a stray file is
/// skipped and counted.
#[test]
fn a_folder_of_several_series_reads_the_largest_or_the_one_asked_for() {
    if !have_simpleitk() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    write_cases(dir.path());
    let folder = dir.path().join("two_series");
    let read = io::read_dicom(&folder, None).unwrap();
    assert_eq!((read.series.uid.as_str(), read.series.files), ("1.2.3.4.1", 9));
    let others: Vec<(&str, &str, usize)> =
        read.others.iter().map(|s| (s.uid.as_str(), s.description.as_str(), s.files)).collect();
    assert_eq!(others, [("1.2.3.4.2", "CT scout", 4)]);
    let scout = io::read_volume_series(&folder, Some("1.2.3.4.2")).unwrap();
    matches_itk(dir.path(), "two_series", "1.2.3.4.2", &scout).unwrap();
    let unknown = io::read_volume_series(&folder, Some("9.9")).unwrap_err().to_string();
    assert!(
        unknown.contains("no series 9.9") && unknown.contains("1.2.3.4.2") && unknown.contains("CT scout"),
        "{unknown}"
    );
    let stray = io::read_dicom(&dir.path().join("with_a_stray_file"), None).unwrap();
    assert_eq!(stray.skipped.len(), 1, "{:?}", stray.skipped);
    assert!(stray.skipped[0].0.ends_with("README.txt"));
}

/// The commands take a DICOM folder as `--volume` and a series by `--series`: `defvol warp`
/// through a zero displacement writes the series' geometry, and an unknown series is an
/// error naming the ones there.
#[test]
fn warp_takes_a_dicom_folder_and_a_series_by_its_uid() {
    if !have_simpleitk() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    write_cases(dir.path());
    let folder = dir.path().join("two_series");
    let out = dir.path().join("scout.nrrd");
    let run = |series: &str| {
        Command::new(env!("CARGO_BIN_EXE_defvol"))
            .args(["warp", "--backend", "cpu", "--volume"])
            .arg(&folder)
            .args(["--series", series, "--displace", "0,0,0:0,0,0:1", "--out"])
            .arg(&out)
            .output()
            .unwrap()
    };
    let done = run("1.2.3.4.2");
    assert!(done.status.success(), "{}", String::from_utf8_lossy(&done.stderr));
    let (warped, itk) = (io::read_volume(&out).unwrap(), io::read_volume_series(&folder, Some("1.2.3.4.2")).unwrap());
    assert_eq!((warped.dims(), warped.origin(), warped.spacing()), (itk.dims(), itk.origin(), itk.spacing()));
    let refused = run("1.2.3.4.9");
    let text = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && text.contains("no series 1.2.3.4.9") && text.contains("1.2.3.4.1"), "{text}");
}

/// A CT in Hounsfield units bent by `defvol warp` with no `--background`: the voxels no tet
/// covers are the source's minimum (air, -1000 HU), not 0 (soft tissue).
#[test]
fn a_warped_ct_is_air_where_no_tet_covers_it() {
    if !have_simpleitk() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    write_cases(dir.path());
    let out = dir.path().join("bent.nrrd");
    let done = Command::new(env!("CARGO_BIN_EXE_defvol"))
        .args(["warp", "--backend", "cpu", "--volume"])
        .arg(dir.path().join("axial"))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(done.status.success(), "{}", String::from_utf8_lossy(&done.stderr));
    let bent = io::read_volume(&out).unwrap();
    let air = bent.data().iter().filter(|v| **v == -1000.0).count();
    let zeros = bent.data().iter().filter(|v| **v == 0.0).count();
    assert!(air > bent.len() / 10 && zeros == 0, "{air} voxels of air, {zeros} of 0 HU in {}", bent.len());
}

/// `defvol info --json`: a DICOM folder's geometry and range as ITK reads them, its series
/// and the values' unit; a mesh's counts, bounds and dihedral angles (a corner tet's are
/// 54.74° and 90°, analytically).
#[test]
fn info_describes_a_dicom_folder_as_itk_reads_it_and_a_mesh_by_its_quality() {
    if !have_simpleitk() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    write_cases(dir.path());
    let info = |path: &Path| -> Value {
        let out = Command::new(env!("CARGO_BIN_EXE_defvol")).arg("info").arg(path).arg("--json").output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        serde_json::from_slice(&out.stdout).unwrap()
    };
    let got = info(&dir.path().join("two_series"));
    let itk = io::read_volume(&dir.path().join("two_series.1.2.3.4.1.mha")).unwrap();
    let numbers = |v: &Value| -> Vec<f64> { v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect() };
    let d = itk.direction();
    let row_major: Vec<f64> = (0..3).flat_map(|r| (0..3).map(move |c| d[(r, c)])).collect();
    let (low, high) = itk.range();
    let expected = [
        itk.dims().map(|n| n as f64).to_vec(),
        itk.spacing().to_vec(),
        itk.origin().to_vec(),
        row_major,
        vec![f64::from(low), f64::from(high)],
    ];
    for (key, want) in ["dims", "spacing", "origin", "direction", "range"].iter().zip(expected) {
        let have = numbers(&got[key]);
        assert!(have.len() == want.len() && have.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-4), "{key}: {got}");
    }
    assert_eq!((got["series"]["uid"].as_str(), got["units"].as_str()), (Some("1.2.3.4.1"), Some("HU")), "{got}");
    assert_eq!(got["other_series"][0]["description"], "CT scout", "{got}");
    let corner = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]].map(nalgebra::Vector3::from);
    let mesh = defvol::mesh::TetMesh::new(corner.to_vec(), vec![[0, 1, 2, 3]], None, "corner").unwrap();
    let path = dir.path().join("corner.vtu");
    io::write_mesh(&path, &mesh, None, None).unwrap();
    let got = info(&path);
    assert_eq!(
        (got["nodes"].as_u64(), got["tets"].as_u64(), got["inverted_tets"].as_u64()),
        (Some(4), Some(1), Some(0))
    );
    let (min, max) = (got["min_dihedral_deg"].as_f64().unwrap(), got["max_dihedral_deg"].as_f64().unwrap());
    assert!((min - 54.735_610_317).abs() < 1e-6 && (max - 90.0).abs() < 1e-9, "{got}");
    assert_eq!(numbers(&got["bounds"][1]), [1.0, 1.0, 1.0]);
}
