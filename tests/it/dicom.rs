//! DICOM series written by SimpleITK (GDCM) as a scanner writes them (native and JPEG
//! lossless, 1.2.840.10008.1.2.4.70) and multi-frame files written by pydicom (an enhanced
//! CT, native and deflated, and a classic MR in RLE), by tests/interop/dicom.py: defvol reads
//! each as SimpleITK does, voxel for voxel and to 1e-4 mm in origin, spacing and direction,
//! and refuses what is not one regular volume by its reason.

use std::path::Path;
use std::process::Command;

use defvol::io;
use serde_json::Value;

/// SimpleITK and pydicom; under tests/run.sh (DEFVOL_REQUIRE_INTEROP=1) they must be there.
fn have_dicom_writers() -> bool {
    let ok =
        Command::new("python3").args(["-c", "import SimpleITK, pydicom"]).output().is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var_os("DEFVOL_REQUIRE_INTEROP").is_none(),
            "SimpleITK or pydicom is missing (tests/run.sh installs them)"
        );
        eprintln!("skipped: SimpleITK or pydicom is not installed");
    }
    ok
}

/// The cases written into a fresh folder, and what each holds; none without SimpleITK.
fn written_cases() -> Option<(tempfile::TempDir, Value)> {
    if !have_dicom_writers() {
        return None;
    }
    let dir = tempfile::tempdir().unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/dicom.py");
    let out = Command::new("python3").arg(script).arg("write").arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "dicom.py: {}", String::from_utf8_lossy(&out.stderr));
    let cases = serde_json::from_slice(&out.stdout).unwrap();
    Some((dir, cases))
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
    let Some((dir, cases)) = written_cases() else { return };
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
    assert!(cases.as_object().unwrap().len() >= 11, "{cases}");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// A multi-frame file reads the same given as itself, as its folder, or as bytes (the fuzz
/// path); its frames count as slices of one file.
#[test]
fn a_multi_frame_file_reads_alike_by_its_path_its_folder_and_its_bytes() {
    let Some((dir, _)) = written_cases() else { return };
    for case in ["enhanced_ct", "enhanced_ct_deflated", "multiframe_mr_rle"] {
        let file = dir.path().join(case).join("volume.dcm");
        let read = io::read_dicom(&file, None).unwrap();
        assert_eq!((read.series.files, read.series.slices), (1, 9), "{case}");
        matches_itk(dir.path(), case, "1.2.3.4.7", &read.volume).unwrap();
        let parsed = io::parse_dicom(&file, &std::fs::read(&file).unwrap()).unwrap();
        matches_itk(dir.path(), case, "1.2.3.4.7", &parsed).unwrap();
        assert_eq!(read.units.as_deref(), case.starts_with("enhanced_ct").then_some("HU"), "{case}");
    }
}

/// A folder of two series: the larger is read and the other listed; `read_volume_series`
/// picks either by its UID; an unknown UID is refused naming the ones there; a stray file is
/// skipped and counted.
#[test]
fn a_folder_of_several_series_reads_the_largest_or_the_one_asked_for() {
    let Some((dir, _)) = written_cases() else { return };
    let folder = dir.path().join("two_series");
    let read = io::read_dicom(&folder, None).unwrap();
    assert_eq!((read.series.uid.as_str(), read.series.files, read.series.slices), ("1.2.3.4.1", 9, 9));
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
    let Some((dir, _)) = written_cases() else { return };
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
    let Some((dir, _)) = written_cases() else { return };
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
    let Some((dir, _)) = written_cases() else { return };
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
    let (min, max) = (got["min_dihedral_deg"]["min"].as_f64().unwrap(), got["max_dihedral_deg"].as_f64().unwrap());
    assert!((min - 54.735_610_317).abs() < 1e-6 && (max - 90.0).abs() < 1e-9, "{got}");
    assert_eq!(numbers(&got["bounds"][1]), [1.0, 1.0, 1.0]);
}

/// A CT slice as dicom-rs writes it (explicit VR little endian): `cols` x `rows` signed
/// 16-bit values stored through slope 2 and intercept -1024, axial at height `z`, 0.5 by
/// 0.75 mm pixels. `frames` overrides NumberOfFrames and `rows_claimed` Rows (damage).
pub(crate) fn synthetic_slice(
    z: f64,
    size: [u16; 2],
    stored: &[i16],
    frames: Option<&str>,
    rows_claimed: Option<u16>,
) -> Vec<u8> {
    use dicom_core::{dicom_value, DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::tags;
    use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
    let [cols, rows] = size;
    let mut elements = vec![
        DataElement::new(tags::SOP_CLASS_UID, VR::UI, "1.2.840.10008.5.1.4.1.1.2"),
        DataElement::new(tags::SOP_INSTANCE_UID, VR::UI, format!("1.2.3.9.{}", (z * 10.0) as i64)),
        DataElement::new(tags::MODALITY, VR::CS, "CT"),
        DataElement::new(tags::SERIES_INSTANCE_UID, VR::UI, "1.2.3.9"),
        DataElement::new(tags::IMAGE_POSITION_PATIENT, VR::DS, dicom_value!(Strs, ["-10", "20", z.to_string()])),
        DataElement::new(tags::IMAGE_ORIENTATION_PATIENT, VR::DS, dicom_value!(Strs, ["1", "0", "0", "0", "1", "0"])),
        DataElement::new(tags::SAMPLES_PER_PIXEL, VR::US, dicom_value!(U16, 1)),
        DataElement::new(tags::PHOTOMETRIC_INTERPRETATION, VR::CS, "MONOCHROME2"),
        DataElement::new(tags::ROWS, VR::US, dicom_value!(U16, rows_claimed.unwrap_or(rows))),
        DataElement::new(tags::COLUMNS, VR::US, dicom_value!(U16, cols)),
        DataElement::new(tags::PIXEL_SPACING, VR::DS, dicom_value!(Strs, ["0.75", "0.5"])),
        DataElement::new(tags::BITS_ALLOCATED, VR::US, dicom_value!(U16, 16)),
        DataElement::new(tags::BITS_STORED, VR::US, dicom_value!(U16, 16)),
        DataElement::new(tags::HIGH_BIT, VR::US, dicom_value!(U16, 15)),
        DataElement::new(tags::PIXEL_REPRESENTATION, VR::US, dicom_value!(U16, 1)),
        DataElement::new(tags::RESCALE_INTERCEPT, VR::DS, "-1024"),
        DataElement::new(tags::RESCALE_SLOPE, VR::DS, "2"),
        DataElement::new(tags::PIXEL_DATA, VR::OW, PrimitiveValue::I16(stored.iter().copied().collect())),
    ];
    if let Some(frames) = frames {
        elements.push(DataElement::new(tags::NUMBER_OF_FRAMES, VR::IS, frames));
    }
    let object = InMemDicomObject::from_element_iter(elements)
        .with_meta(FileMetaTableBuilder::new().transfer_syntax("1.2.840.10008.1.2.1"))
        .unwrap();
    let mut bytes = Vec::new();
    object.write_all(&mut bytes).unwrap();
    bytes
}

/// A slice's values are its stored ones through slope and intercept, its geometry its
/// position, orientation and PixelSpacing (columns first); damaged files are refused by
/// their reason: cut short, Rows beyond the pixel data, 10^6 frames, and a cut slice in a
/// folder names that file while a text file there is skipped.
#[test]
fn a_slice_reads_through_its_rescale_and_damaged_files_are_refused_by_their_reason() {
    let stored: Vec<i16> = (0..12).map(|k| k * 37 - 200).collect();
    let bytes = synthetic_slice(7.5, [4, 3], &stored, None, None);
    let v = io::parse_dicom(Path::new("s.dcm"), &bytes).unwrap();
    let hu: Vec<f32> = stored.iter().map(|s| f32::from(*s) * 2.0 - 1024.0).collect();
    assert_eq!((v.dims(), v.origin(), v.spacing()), ([4, 3, 1], [-10.0, 20.0, 7.5], [0.5, 0.75, 1.0]));
    assert_eq!((v.data(), *v.direction()), (&hu[..], nalgebra::Matrix3::identity()));
    let refusal = |bytes: &[u8]| io::parse_dicom(Path::new("bad.dcm"), bytes).unwrap_err().to_string();
    let cut = refusal(&bytes[..bytes.len() - 10]);
    assert!(cut.starts_with("bad.dcm:") && cut.contains("truncated or damaged"), "{cut}");
    let tall = refusal(&synthetic_slice(0.0, [4, 3], &stored, None, Some(60_000)));
    assert!(tall.contains("declares 480000 bytes of pixel data") && tall.contains("header is wrong"), "{tall}");
    let million = refusal(&synthetic_slice(0.0, [4, 3], &stored, Some("1000000"), None));
    assert!(million.contains("declares 24000000 bytes"), "{million}");
    let huge = refusal(&synthetic_slice(0.0, [4000, 3], &stored, Some("1000000"), Some(4000)));
    assert!(huge.contains("4000x4000 pixels x 1000000 frames x 16 bits") && huge.contains("beyond"), "{huge}");
    let unplaced = refusal(&synthetic_slice(0.0, [2, 3], &stored, Some("2"), None));
    assert!(unplaced.contains("neither per-frame positions nor a positive SpacingBetweenSlices"), "{unplaced}");
    let dir = tempfile::tempdir().unwrap();
    for k in 0..3 {
        std::fs::write(dir.path().join(format!("{k}.dcm")), synthetic_slice(f64::from(k), [4, 3], &stored, None, None))
            .unwrap();
    }
    std::fs::write(dir.path().join("notes.txt"), "not DICOM").unwrap();
    let read = io::read_dicom(dir.path(), None).unwrap();
    assert_eq!((read.volume.dims(), read.skipped.len(), read.units.as_deref()), ([4, 3, 3], 1, Some("HU")));
    std::fs::write(dir.path().join("1.dcm"), &bytes[..200]).unwrap();
    let damaged = io::read_dicom(dir.path(), None).unwrap_err().to_string();
    assert!(damaged.contains("1.dcm") && damaged.contains("truncated or damaged"), "{damaged}");
}
