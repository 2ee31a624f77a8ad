//! The warped volume reaches a subscriber in another language: iceoryx2's Python binding
//! reads the header and the samples the pipeline's warp wrote into shared memory, and an
//! oblique volume ITK wrote arrives where ITK puts it.

use std::path::Path;
use std::process::{Command, Output};
use std::sync::Arc;

use defvol::backend::Backend;
use defvol::msgs::{Header, Pose, PoseStamped, Time};
use defvol::pipeline::inputs::InputLimits;
use defvol::pipeline::{Demand, FrameMode, Pipeline, WarpedVolume};
use defvol::scene::{MeshSource, Scene, Stages};
use defvol::shm::WarpedVolumePublisher;
use defvol::volume::Grid;

/// Whether python3 has `modules`; under tests/run.sh (DEFVOL_REQUIRE_INTEROP=1) it must.
fn have_python(modules: &str) -> bool {
    let have =
        Command::new("python3").args(["-c", &format!("import {modules}")]).output().is_ok_and(|o| o.status.success());
    if !have {
        assert!(
            std::env::var_os("DEFVOL_REQUIRE_INTEROP").is_none(),
            "python3 {modules} is missing (tests/run.sh installs it)"
        );
        eprintln!("skipped: python3 {modules} is not installed");
    }
    have
}

fn script(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop").join(name)
}

/// Runs `publish` until the subscriber started with `args` has printed its one JSON line.
fn subscribe(args: &[&str], mut publish: impl FnMut()) -> serde_json::Value {
    let mut child = Command::new("python3")
        .arg(script("shm_subscriber.py"))
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Volumes keep coming, as from the node, until the subscriber has one.
    while child.try_wait().unwrap().is_none() {
        publish();
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let Output { status, stdout, stderr } = child.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&stdout);
    assert!(status.success(), "{text}{}", String::from_utf8_lossy(&stderr));
    serde_json::from_str(text.lines().last().unwrap()).unwrap()
}

#[test]
fn a_python_iceoryx2_subscriber_receives_the_warped_volume() {
    if !have_python("iceoryx2") {
        return;
    }
    let grid = Grid {
        dims: [64, 40, 30],
        spacing: [1.0, 1.0, 1.5],
        origin: [-32.0, -20.0, -22.0],
        direction: nalgebra::Matrix3::identity(),
    };
    let data: Vec<f32> = (0..64 * 40 * 30).map(|i| (i % 977) as f32 * 0.5).collect();
    let service = format!("defvol/test_python_{}", std::process::id());
    let publisher = WarpedVolumePublisher::new(&service, &grid).unwrap();
    let volume = WarpedVolume {
        grid: grid.clone(),
        sequence: 42,
        stamp: Time { sec: 5, nanosec: 6 },
        stats: Default::default(),
        published: false,
    };
    let got = subscribe(&[&service], || {
        publisher.publish_slice(&volume, &data).unwrap();
    });
    assert_eq!(got["sequence"], 42);
    assert_eq!(got["dims"], serde_json::json!([64, 40, 30]));
    assert_eq!(got["spacing"], serde_json::json!([1.0, 1.0, 1.5]));
    assert_eq!(got["origin"], serde_json::json!([-32.0, -20.0, -22.0]));
    assert_eq!(got["direction"], serde_json::json!([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]));
    assert_eq!(got["elements"].as_u64().unwrap() as usize, data.len());
    let sum: f64 = data.iter().map(|v| f64::from(*v)).sum();
    assert!((got["sum"].as_f64().unwrap() - sum).abs() < 1e-6 * sum, "{} vs {sum}", got["sum"]);
    assert_eq!(
        (got["first"].as_f64().unwrap() as f32, got["last"].as_f64().unwrap() as f32),
        (data[0], data[data.len() - 1])
    );
}

/// An oblique volume SimpleITK wrote goes through the pipeline's warp (the mesh at rest)
/// into shared memory; the Python subscriber places voxels by the header's origin, spacing
/// and direction, and finds ITK's physical points and values for the same voxels of the
/// file.
#[test]
fn an_oblique_volume_lands_where_itk_puts_it() {
    if !have_python("iceoryx2, SimpleITK") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("oblique.nrrd");
    let made = Command::new("python3").arg(script("oblique_volume.py")).arg(&file).output().unwrap();
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let mut scene = Scene::default_scene().unwrap();
    scene.volume = file.display().to_string();
    scene.mesh = MeshSource::VolumeLattice { target_tets: 800, split: defvol::mesh::generate::CellSplit::Five };
    scene.stages = Stages { solver: true, warp: true, dpcm: false, raycast: false };
    scene.solver.gravity = [0.0; 3];
    scene.tools[0].path = None;
    let mut pipeline =
        Pipeline::new(scene, &Backend::cpu(), InputLimits { max_age: None, ..Default::default() }, FrameMode::Lockstep)
            .unwrap();
    let grid = pipeline.warped_grid().unwrap().clone();
    assert!(
        (grid.direction - nalgebra::Matrix3::identity()).norm() > 0.5,
        "the file's direction is oblique: {:?}",
        grid.direction
    );
    let service = format!("defvol/test_oblique_{}", std::process::id());
    let publisher = Arc::new(WarpedVolumePublisher::new(&service, &grid).unwrap());
    pipeline.set_volume_sink(Some(publisher));
    let demand = Demand { warped_volume: true, ..Demand::NONE };
    let mut tick = 0;
    let file_arg = file.display().to_string();
    let got = subscribe(&[&service, "--check-against", &file_arg], || {
        tick += 1;
        // The probe moves far from the organ: the solver stays awake, the mesh at rest,
        // and a warp is published whenever one is due.
        let stamp = Time::from_secs(tick as f64 * 0.2);
        let mut pose = PoseStamped { header: Header { stamp, frame_id: "world".into() }, pose: Pose::default() };
        pose.pose.position.z = 5.0 + 0.01 * tick as f64;
        pipeline.apply_pose("tool_pose", &pose, stamp).unwrap();
        pipeline.tick(stamp, &demand).unwrap();
    });
    assert_eq!(got["dims"], serde_json::json!(grid.dims));
    let (points, distance) = (got["checked"].as_u64().unwrap(), got["max_point_error_mm"].as_f64().unwrap());
    assert!(points >= 500, "{got}");
    assert!(distance < 1e-9, "voxels placed {distance} mm from where ITK puts them: {got}");
    // At rest the warp reads each voxel back through trilinear sampling: within f32
    // rounding of the largest value (a few ulp).
    let (value_error, largest) = (got["max_value_error"].as_f64().unwrap(), got["last"].as_f64().unwrap());
    assert!(value_error <= 1e-6 * largest, "warped values differ from the file's by up to {value_error}: {got}");
}

/// A /dev/shm of 1 MiB, a real tmpfs in a private mount namespace (`unshare --mount`): a
/// service whose samples cannot fit is refused naming the room there and the room needed,
/// before iceoryx2 maps anything; one that fits opens and publishes there.
#[test]
fn a_tiny_dev_shm_refuses_a_service_naming_its_size_and_takes_one_that_fits() {
    let name = "shm_interop::a_tiny_dev_shm_refuses_a_service_naming_its_size_and_takes_one_that_fits";
    if crate::rerun_under_tiny_dev_shm(name, None) {
        return;
    }
    let stat = nix::sys::statvfs::statvfs("/dev/shm").unwrap();
    assert_eq!(stat.blocks() as u64 * stat.fragment_size() as u64, 1 << 20, "the tmpfs is 1 MiB");
    let grid =
        |n: usize| Grid { dims: [n; 3], spacing: [1.0; 3], origin: [0.0; 3], direction: nalgebra::Matrix3::identity() };
    let Err(refused) = WarpedVolumePublisher::new("defvol/test_tiny_shm_big", &grid(64)) else {
        panic!("a 1 MiB volume was taken into a 1 MiB /dev/shm")
    };
    let message = refused.to_string();
    let needed = defvol::shm::bytes_needed(64 * 64 * 64) as f64 / 1048576.0;
    assert!(
        message.contains("/dev/shm has 1.0 MiB free") && message.contains(&format!("needs {needed:.1} MiB")),
        "{message}"
    );
    let small = grid(8);
    assert!(defvol::shm::bytes_needed(8 * 8 * 8) < 1 << 19, "the small service fits with room to spare");
    let publisher = WarpedVolumePublisher::new("defvol/test_tiny_shm_small", &small).unwrap();
    let volume = WarpedVolume {
        grid: small.clone(),
        sequence: 1,
        stamp: Time::default(),
        stats: Default::default(),
        published: false,
    };
    publisher.publish_slice(&volume, &vec![1.5; 512]).unwrap();
}

/// A subscriber that borrows every sample it can and never lets go, then is killed with
/// SIGKILL while holding them: publishing never blocks or fails meanwhile, and afterwards a
/// new subscriber receives the volumes that followed.
#[test]
fn a_subscriber_hoarding_samples_then_killed_never_blocks_the_publisher() {
    use std::io::BufRead;
    if !have_python("iceoryx2") {
        return;
    }
    let grid =
        Grid { dims: [16, 12, 8], spacing: [1.0; 3], origin: [0.0; 3], direction: nalgebra::Matrix3::identity() };
    let service = format!("defvol/test_hoard_{}", std::process::id());
    let publisher = WarpedVolumePublisher::new(&service, &grid).unwrap();
    let sequence = std::cell::Cell::new(0u64);
    let publish = || {
        sequence.set(sequence.get() + 1);
        let volume = WarpedVolume {
            grid: grid.clone(),
            sequence: sequence.get(),
            stamp: Time::default(),
            stats: Default::default(),
            published: false,
        };
        publisher.publish_slice(&volume, &vec![sequence.get() as f32; grid.len()]).unwrap();
    };
    let mut hoarder = Command::new("python3")
        .arg(script("shm_subscriber.py"))
        .args([service.as_str(), "--hoard"])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let (told, heard) = std::sync::mpsc::channel();
    let stdout = hoarder.stdout.take().unwrap();
    std::thread::spawn(move || {
        let line = std::io::BufReader::new(stdout).lines().next().and_then(Result::ok).unwrap_or_default();
        let _ = told.send(line);
    });
    // Volumes keep coming until the hoarder holds all it may.
    let holding = loop {
        publish();
        if let Ok(line) = heard.try_recv() {
            break serde_json::from_str::<serde_json::Value>(&line).unwrap()["holding"].as_u64().unwrap();
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    };
    assert!(holding >= 1, "the hoarder holds {holding} samples");
    // What the node's diagnostics report as `shared_subscribers`.
    assert_eq!(defvol::pipeline::VolumeSink::subscribers(&publisher), 1);
    let started = std::time::Instant::now();
    for _ in 0..200 {
        publish();
    }
    hoarder.kill().unwrap();
    hoarder.wait().unwrap();
    for _ in 0..200 {
        publish();
    }
    let since = sequence.get();
    let received = subscribe(&[service.as_str()], publish);
    assert!(received["sequence"].as_u64().unwrap() > since, "{received}");
    assert_eq!(received["first"].as_f64().unwrap(), received["sequence"].as_f64().unwrap(), "{received}");
    eprintln!("{holding} samples hoarded; 400 volumes published past them in {:?}", started.elapsed());
}
