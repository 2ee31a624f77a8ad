//! Mutation fuzzing of every loader, in the suite: valid seed files of every format (written
//! by defvol's writers, or built here where defvol writes no such format), mutated 10^5
//! times per loader (bit flips, extreme numbers, cut, grown and spliced bytes). No input
//! may panic or abort the process: each is read, or refused with an error. The longer runs
//! are the `cargo fuzz` targets in `fuzz/`.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;

use defvol::io::{self, MeshFormat};
use defvol::mesh::generate::{self, CellSplit};
use defvol::volume::Volume;
use nalgebra::Vector3;

const ITERATIONS: usize = 100_000;

/// xorshift64*: fixed seeds, the same run every time.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

const EXTREME_TEXT: [&str; 10] = [
    "0",
    "-1",
    "4294967295",
    "4294967296",
    "99999999999999999999",
    "18446744073709551615",
    "1e308",
    "nan",
    "-2147483648",
    "65536",
];
const EXTREME_WORDS: [u64; 6] = [0, u64::MAX, 0x7FFF_FFFF, 0x8000_0000, 0xFFFF_FFFF, 1 << 40];

/// One to four mutations of `seed`.
fn mutate(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut out = seed.to_vec();
    for _ in 0..1 + rng.below(4) {
        let len = out.len().max(1);
        match rng.below(8) {
            0 if !out.is_empty() => {
                let at = rng.below(out.len());
                out[at] ^= 1 << rng.below(8);
            }
            1 if !out.is_empty() => {
                let at = rng.below(out.len());
                let interesting = b"\x00\xff\x7f\x80 \n-=9_<>";
                out[at] = interesting[rng.below(interesting.len())];
            }
            2 => {
                let at = rng.below(len);
                let insert: Vec<u8> = (0..1 + rng.below(8)).map(|_| rng.next() as u8).collect();
                out.splice(at.min(out.len())..at.min(out.len()), insert);
            }
            3 if !out.is_empty() => {
                let at = rng.below(out.len());
                let end = (at + 1 + rng.below(16)).min(out.len());
                out.drain(at..end);
            }
            4 => out.truncate(rng.below(len)),
            5 if !out.is_empty() => {
                let at = rng.below(out.len());
                let end = (at + 1 + rng.below(64)).min(out.len());
                let chunk = out[at..end].to_vec();
                let to = rng.below(out.len());
                out.splice(to..to, chunk);
            }
            6 => {
                // A decimal number in the text becomes an extreme one.
                let starts: Vec<usize> = (0..out.len())
                    .filter(|i| out[*i].is_ascii_digit() && (*i == 0 || !out[*i - 1].is_ascii_digit()))
                    .collect();
                if let Some(&at) = starts.get(rng.below(starts.len())) {
                    let end =
                        (at..out.len()).find(|i| !out[*i].is_ascii_digit() && out[*i] != b'.').unwrap_or(out.len());
                    out.splice(at..end, EXTREME_TEXT[rng.below(EXTREME_TEXT.len())].bytes());
                }
            }
            _ if out.len() >= 8 => {
                let at = rng.below(out.len() - 7);
                let word = EXTREME_WORDS[rng.below(EXTREME_WORDS.len())];
                let bytes = if rng.below(2) == 0 { word.to_le_bytes() } else { word.to_be_bytes() };
                let width = if rng.below(2) == 0 { 4 } else { 8 };
                out[at..at + width].copy_from_slice(&bytes[..width]);
            }
            _ => {}
        }
    }
    out
}

thread_local! {
    /// Set while this thread fuzzes: its panics are kept here instead of printed.
    static CAUGHT: std::cell::RefCell<Option<String>> = const { std::cell::RefCell::new(None) };
}

/// Runs `f`, keeping quiet about a panic on this thread and returning its message and place.
/// The panic hook is process-wide and tests run side by side, so it is installed once and
/// speaks for every other thread exactly as the hook before it did.
fn quiet_catch(f: impl FnOnce()) -> Result<(), String> {
    static INSTALL: std::sync::Once = std::sync::Once::new();
    INSTALL.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let quiet = CAUGHT.with(|caught| caught.borrow_mut().as_mut().map(|last| *last = info.to_string()));
            if quiet.is_none() {
                previous(info);
            }
        }));
    });
    CAUGHT.with(|caught| *caught.borrow_mut() = Some(String::new()));
    let result = catch_unwind(AssertUnwindSafe(f));
    let why = CAUGHT.with(|caught| caught.borrow_mut().take()).unwrap_or_default();
    result.map_err(|_| why)
}

/// Runs `load` on `iterations` mutations of the seeds; a panic fails with the input.
fn fuzz(what: &str, seeds: &[(String, Vec<u8>)], iterations: usize, mut load: impl FnMut(&str, &[u8])) {
    // DEFVOL_FUZZ_SEED explores other mutations than the suite's fixed ones.
    let seed =
        std::env::var("DEFVOL_FUZZ_SEED").ok().and_then(|s| s.parse::<u64>().ok()).unwrap_or(0x9E37_79B9_7F4A_7C15);
    let mut rng = Rng(seed ^ what.len() as u64 | 1);
    // The seeds themselves load.
    for (name, seed) in seeds {
        load(name, seed);
    }
    let mut failure = None;
    for iteration in 0..iterations {
        let (name, seed) = &seeds[rng.below(seeds.len())];
        let input = mutate(seed, &mut rng);
        if let Err(why) = quiet_catch(|| load(name, &input)) {
            failure = Some((iteration, name.clone(), input, why));
            break;
        }
    }
    if let Some((iteration, name, input, why)) = failure {
        let head: String =
            input.iter().take(400).map(|b| if b.is_ascii_graphic() || *b == b' ' { *b as char } else { '.' }).collect();
        panic!("{what}: input {iteration} (from {name}, {} bytes) panicked ({why}): `{head}`", input.len());
    }
}

fn small_mesh() -> defvol::mesh::TetMesh {
    let mut mesh =
        generate::lattice(Vector3::zeros(), Vector3::new(0.2, 0.1, 0.1), [2, 1, 1], CellSplit::Five).unwrap();
    mesh.set_scalars((0..mesh.nodes().len()).map(|i| i as f32 * 0.5).collect()).unwrap();
    mesh
}

/// Gmsh binary files, built here (defvol writes Gmsh as 4.1 ASCII): 2.2 and 4.1.
fn gmsh_binary(mesh: &defvol::mesh::TetMesh) -> (Vec<u8>, Vec<u8>) {
    let (nodes, tets) = (mesh.nodes(), mesh.tets());
    let mut v2 = b"$MeshFormat\n2.2 1 8\n".to_vec();
    v2.extend_from_slice(&1i32.to_le_bytes());
    v2.extend_from_slice(format!("\n$EndMeshFormat\n$Nodes\n{}\n", nodes.len()).as_bytes());
    for (i, p) in nodes.iter().enumerate() {
        v2.extend_from_slice(&(i as i32 + 1).to_le_bytes());
        for c in [p.x, p.y, p.z] {
            v2.extend_from_slice(&c.to_le_bytes());
        }
    }
    v2.extend_from_slice(format!("\n$EndNodes\n$Elements\n{}\n", tets.len()).as_bytes());
    for w in [4i32, tets.len() as i32, 2] {
        v2.extend_from_slice(&w.to_le_bytes());
    }
    for (e, t) in tets.iter().enumerate() {
        for w in [e as i32 + 1, 0, 1].into_iter().chain(t.iter().map(|v| *v as i32 + 1)) {
            v2.extend_from_slice(&w.to_le_bytes());
        }
    }
    v2.extend_from_slice(b"\n$EndElements\n");
    let mut v4 = b"$MeshFormat\n4.1 1 8\n".to_vec();
    v4.extend_from_slice(&1i32.to_le_bytes());
    v4.extend_from_slice(b"\n$EndMeshFormat\n$Nodes\n");
    let size = |v: &mut Vec<u8>, x: usize| v.extend_from_slice(&(x as u64).to_le_bytes());
    for x in [1, nodes.len(), 1, nodes.len()] {
        size(&mut v4, x);
    }
    for w in [3i32, 1, 0] {
        v4.extend_from_slice(&w.to_le_bytes());
    }
    size(&mut v4, nodes.len());
    for i in 0..nodes.len() {
        size(&mut v4, i + 1);
    }
    for p in nodes {
        for c in [p.x, p.y, p.z] {
            v4.extend_from_slice(&c.to_le_bytes());
        }
    }
    v4.extend_from_slice(b"\n$EndNodes\n$Elements\n");
    for x in [1, tets.len(), 1, tets.len()] {
        size(&mut v4, x);
    }
    for w in [3i32, 1, 4] {
        v4.extend_from_slice(&w.to_le_bytes());
    }
    size(&mut v4, tets.len());
    for (e, t) in tets.iter().enumerate() {
        size(&mut v4, e + 1);
        for v in t {
            size(&mut v4, *v as usize + 1);
        }
    }
    v4.extend_from_slice(b"\n$EndElements\n");
    (v2, v4)
}

#[test]
fn gmsh_binary_files_read_as_their_mesh() {
    let mesh = small_mesh();
    let (v2, v4) = gmsh_binary(&mesh);
    for (what, bytes) in [("2.2", v2), ("4.1", v4)] {
        let back =
            io::parse_mesh(Path::new("m.msh"), &bytes, MeshFormat::Gmsh).unwrap_or_else(|e| panic!("{what}: {e}"));
        assert_eq!(back.tets(), mesh.tets(), "{what}");
        assert_eq!(back.nodes(), mesh.nodes(), "{what}");
    }
}

#[test]
fn no_mesh_file_crashes_the_mesh_loaders() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = small_mesh();
    let mut seeds = Vec::new();
    for name in ["m.vtu", "m.vtk", "m.msh", "m.node"] {
        let path = dir.path().join(name);
        io::write_mesh(&path, &mesh, None, None).unwrap();
        seeds.push((name.to_owned(), std::fs::read(&path).unwrap()));
    }
    let ele = std::fs::read(dir.path().join("m.ele")).unwrap();
    seeds.push(("m.ele".to_owned(), ele.clone()));
    let (v2, v4) = gmsh_binary(&mesh);
    seeds.push(("v2.msh".to_owned(), v2));
    seeds.push(("v4.msh".to_owned(), v4));
    seeds.push(("v1.msh".to_owned(), GMSH_1.as_bytes().to_vec()));
    // An ascii VTK XML grid with appended raw data, and a legacy 5.1 ascii file.
    seeds.push((
        "ascii.vtu".to_owned(),
        b"<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\"><UnstructuredGrid><Piece NumberOfPoints=\"4\" NumberOfCells=\"2\"><PointData Scalars=\"s\"><DataArray type=\"Float32\" Name=\"s\" format=\"ascii\">1 2 3 4</DataArray></PointData><Points><DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">0 0 0 1 0 0 0 1 0 0 0 1</DataArray></Points><Cells><DataArray type=\"Int64\" Name=\"connectivity\" format=\"ascii\">0 1 2 3 0 1</DataArray><DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">4 6</DataArray><DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">10 3</DataArray></Cells></Piece></UnstructuredGrid></VTKFile>".to_vec(),
    ));
    let mut appended = b"<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt32\"><UnstructuredGrid><Piece NumberOfPoints=\"4\" NumberOfCells=\"1\"><Points><DataArray type=\"Float32\" NumberOfComponents=\"3\" format=\"appended\" offset=\"0\"/></Points><Cells><DataArray type=\"Int32\" Name=\"connectivity\" format=\"appended\" offset=\"52\"/><DataArray type=\"Int32\" Name=\"offsets\" format=\"appended\" offset=\"72\"/><DataArray type=\"UInt8\" Name=\"types\" format=\"appended\" offset=\"80\"/></Cells></Piece></UnstructuredGrid><AppendedData encoding=\"raw\">_".to_vec();
    appended.extend_from_slice(&48u32.to_le_bytes());
    for v in [0f32, 0., 0., 1., 0., 0., 0., 1., 0., 0., 0., 1.] {
        appended.extend_from_slice(&v.to_le_bytes());
    }
    for block in [&[16u32, 0, 1, 2, 3][..], &[4, 4]] {
        for v in block {
            appended.extend_from_slice(&v.to_le_bytes());
        }
    }
    appended.extend_from_slice(&1u32.to_le_bytes());
    appended.push(10);
    appended.extend_from_slice(b"\n</AppendedData></VTKFile>\n");
    seeds.push(("appended.vtu".to_owned(), appended));
    seeds.push((
        "legacy51.vtk".to_owned(),
        b"# vtk DataFile Version 5.1\nvtk output\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS 4 float\n0 0 0 1 0 0 0 1 0 0 0 1\nCELLS 3 6\nOFFSETS vtktypeint64\n0 4 6\nCONNECTIVITY vtktypeint64\n0 1 2 3 0 1\nCELL_TYPES 2\n10\n3\nPOINT_DATA 4\nFIELD FieldData 1\ndose 1 4 float\n1 2 3 4\n".to_vec(),
    ));
    let node = seeds[3].1.clone();
    fuzz("mesh loaders", &seeds, ITERATIONS, |name, bytes| {
        let path = Path::new(name);
        let _ = match name {
            "m.node" => io::parse_tetgen(path, bytes, &ele),
            "m.ele" => io::parse_tetgen(path, &node, bytes),
            _ if name.ends_with(".vtu") => io::parse_mesh(path, bytes, MeshFormat::VtkXml),
            _ if name.ends_with(".vtk") => io::parse_mesh(path, bytes, MeshFormat::VtkLegacy),
            _ => io::parse_mesh(path, bytes, MeshFormat::Gmsh),
        };
    });
}

#[test]
fn no_volume_file_crashes_the_volume_loaders() {
    let dir = tempfile::tempdir().unwrap();
    let data: Vec<f32> = (0..4 * 3 * 2).map(|i| i as f32 - 7.5).collect();
    let rotation = nalgebra::Rotation3::from_euler_angles(0.2, 0.0, 1.0).into_inner();
    let volume = Volume::new([4, 3, 2], [0.5, 1.0, 2.0], [1.0, -2.0, 3.0], rotation, data, "seed").unwrap();
    let mut seeds = Vec::new();
    for name in ["v.nii", "v.nii.gz", "v.nrrd", "v.mha"] {
        let path = dir.path().join(name);
        io::write_volume(&path, &volume).unwrap();
        seeds.push((name.to_owned(), std::fs::read(&path).unwrap()));
    }
    io::write_volume(&dir.path().join("v.mhd"), &volume).unwrap();
    let zraw = std::fs::read(dir.path().join("v.zraw")).unwrap();
    seeds.push(("v.mhd".to_owned(), std::fs::read(dir.path().join("v.mhd")).unwrap()));
    let raw: Vec<u8> = volume.data().iter().flat_map(|v| v.to_le_bytes()).collect();
    let mut attached = b"NRRD0004\ntype: float\ndimension: 3\nsizes: 4 3 2\nspace: RAS\nspace directions: (0.5,0,0) (0,1,0) (0,0,2)\nendian: little\nencoding: raw\nbyte skip: -1\nspace origin: (1,2,3)\n\n".to_vec();
    attached.extend_from_slice(&raw);
    seeds.push(("raw.nrrd".to_owned(), attached));
    seeds.push(("v.nhdr".to_owned(), b"NRRD0004\ntype: float\ndimension: 3\nsizes: 4 3 2\nspacings: 1 1 1\nencoding: raw\nline skip: 0\ndata file: v.raw\n".to_vec()));
    let mut mha = b"ObjectType = Image\nNDims = 3\nDimSize = 4 3 2\nElementType = MET_FLOAT\nHeaderSize = -1\nElementDataFile = LOCAL\n".to_vec();
    mha.extend_from_slice(&raw);
    seeds.push(("raw.mha".to_owned(), mha));
    fuzz("volume loaders", &seeds, ITERATIONS, |name, bytes| {
        let sidecar = |file: &str| match file {
            "v.zraw" => Some(zraw.clone()),
            "v.raw" => Some(raw.clone()),
            _ => None,
        };
        let _ = io::parse_volume(Path::new(name), bytes, &sidecar);
    });
}

#[cfg(feature = "mcap")]
#[test]
fn no_bag_crashes_the_bag_reader() {
    use defvol::msgs::{self, Header, Pose, PoseStamped, Time};
    use defvol::record::{bag, Qos};
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("seed.mcap");
    let recorder = defvol::record::bag_thread::BagThread::create(&path, defvol::record::BagOptions::default()).unwrap();
    for k in 0..6u64 {
        let mut pose = PoseStamped {
            header: Header { stamp: Time::from_nanos(k * 1000), frame_id: "world".into() },
            pose: Pose::default(),
        };
        pose.pose.position.z = k as f64 * 0.01;
        recorder.write("/tool_pose", Qos::SensorData, &pose, k * 1000).unwrap();
    }
    recorder.finish().unwrap();
    let seeds = vec![("seed.mcap".to_owned(), std::fs::read(&path).unwrap())];
    fuzz("bag reader", &seeds, ITERATIONS, |name, bytes| {
        if let Ok(messages) = bag::parse_messages(Path::new(name), bytes, &[]) {
            for m in messages {
                let _ = msgs::decode::<PoseStamped>(&m.data, &m.topic);
            }
        }
    });
}

#[test]
fn no_datagram_crashes_the_udp_frame_parser() {
    let mut frame = Vec::new();
    for w in [
        defvol::dpcm::markers::FRAME_FLAG,
        2,
        7,
        0,
        3.5f32.to_bits(),
        4.0f32.to_bits(),
        1,
        10.0f32.to_bits(),
        11.5f32.to_bits(),
    ] {
        frame.extend_from_slice(&w.to_le_bytes());
    }
    let twice = [frame.clone(), frame.clone()].concat();
    let seeds = vec![("frame".to_owned(), frame), ("two frames".to_owned(), twice)];
    let mut parser = defvol::dpcm::markers::FrameParser::default();
    fuzz("UDP frame parser", &seeds, ITERATIONS, |_, bytes| {
        parser.parse(bytes);
    });
}

#[test]
fn no_dicom_file_crashes_the_dicom_loader() {
    let stored: Vec<i16> = (0..12).map(|k| k * 91 - 500).collect();
    let seeds = vec![
        ("slice.dcm".to_owned(), crate::dicom::synthetic_slice(2.5, [4, 3], &stored, None, None)),
        ("frames.dcm".to_owned(), crate::dicom::synthetic_slice(0.0, [2, 3], &stored, Some("2"), None)),
    ];
    fuzz("DICOM loader", &seeds, ITERATIONS, |name, bytes| {
        let _ = io::parse_dicom(Path::new(name), bytes);
    });
}

/// Two tets sharing a face, a boundary triangle and a line, in Gmsh's first format
/// (physical regions 7 and 8, elementary 1 and 2).
const GMSH_1: &str = "$NOD\n6\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n5 1 1 1\n9 3 3 3\n$ENDNOD\n$ELM\n4\n\
1 4 7 1 4 1 2 3 4\n2 4 8 2 4 2 3 4 5\n3 2 9 3 3 1 2 3\n4 1 9 4 2 1 2\n$ENDELM\n";

/// Gmsh 1: the tets, their regions as cell arrays, the stray node 9 dropped; and each kind
/// of damage refused by name.
#[test]
fn a_gmsh_1_file_reads_with_its_regions_and_its_damage_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("old.msh");
    std::fs::write(&path, GMSH_1).unwrap();
    let read = io::read_mesh_with_metadata(&path).unwrap();
    assert_eq!(read.mesh.tets(), &[[0, 1, 2, 3], [1, 2, 3, 4]]);
    assert_eq!(read.mesh.nodes().len(), 5);
    assert_eq!((read.unused_nodes, read.skipped.values().sum::<usize>()), (1, 2));
    let arrays: Vec<(&str, &[f32])> = read.cell_arrays.iter().map(|a| (a.name.as_str(), a.values.as_slice())).collect();
    assert_eq!(arrays, [("gmsh:physical", &[7.0, 8.0][..]), ("gmsh:geometrical", &[1.0, 2.0][..])]);

    let damaged = [
        (GMSH_1.replace("$ENDELM\n", ""), "the file ends where `$ENDELM` should be"),
        (GMSH_1.replace("1 4 7 1 4 1 2 3 4", "1 4 7 1 3 1 2 3"), "element 1: 3 nodes listed where type 4 has 4"),
        (GMSH_1.replace("3 2 9 3 3", "3 99 9 3 3"), "element 3: type 99 is not known"),
        (GMSH_1.replace("2 4 8 2 4 2 3 4 5", "2 4 8 2 4 2 3 4 77"), "element 2 references unknown node 77"),
        (GMSH_1.replace("$NOD\n6", "$NOD\n60"), "60 nodes announced"),
        ("$MeshFormat\n3.0 0 8\n$EndMeshFormat\n".to_owned(), "version 3.0: only 1, 2.2 and 4.1 are read"),
    ];
    for (text, expected) in damaged {
        let error = io::parse_mesh(Path::new("old.msh"), text.as_bytes(), MeshFormat::Gmsh).unwrap_err().to_string();
        assert!(error.contains("old.msh") && error.contains(expected), "`{expected}` not in: {error}");
    }
}

/// A VTK XML grid saved as `.vtk` and a legacy file saved as `.vtu` read by what they hold.
#[test]
fn the_content_not_the_extension_picks_the_mesh_parser() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = generate::lattice(Vector3::zeros(), Vector3::repeat(1.0), [2, 1, 1], CellSplit::Five).unwrap();
    for (written, named) in [("a.vtu", "xml_named.vtk"), ("b.vtk", "legacy_named.vtu"), ("c.msh", "gmsh_named.vtu")] {
        io::write_mesh(&dir.path().join(written), &mesh, None, None).unwrap();
        std::fs::rename(dir.path().join(written), dir.path().join(named)).unwrap();
        let read = io::read_mesh(&dir.path().join(named)).unwrap_or_else(|e| panic!("{named}: {e}"));
        assert_eq!((read.nodes().len(), read.tets()), (mesh.nodes().len(), mesh.tets()), "{named}");
    }
}
