//! `defvol demo` and `defvol replay` end to end: the bag is rosbag2-compatible (read back
//! by Foxglove's independent ROS 2 MCAP reader), the rerun log verifies with rerun's own
//! CLI, and a CPU replay is deterministic to the bit on every topic and thread count.

use std::path::{Path, PathBuf};
use std::process::Command;

use defvol::msgs::{self, DeformedMesh, WrenchStamped};
use defvol::record::bag;

fn defvol() -> Command {
    Command::new(env!("CARGO_BIN_EXE_defvol"))
}

fn scene() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/small_scene.yaml")
}

fn run(cmd: &mut Command) -> String {
    let out = cmd.output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{cmd:?} failed:\n{text}");
    text
}

/// Whether an interop tool exists; under tests/run.sh (DEFVOL_REQUIRE_INTEROP=1) it must.
fn have(what: &str, check: &mut Command) -> bool {
    let ok = check.output().is_ok_and(|o| o.status.success());
    if !ok {
        assert!(std::env::var_os("DEFVOL_REQUIRE_INTEROP").is_none(), "{what} is missing (tests/run.sh installs it)");
        eprintln!("skipped: {what} is not installed (tests/run.sh installs it)");
    }
    ok
}

fn demo(dir: &Path, rerun: bool) -> PathBuf {
    let mut cmd = defvol();
    cmd.args(["demo", "--seconds", "0.6", "--backend", "cpu", "--scene"]).arg(scene()).arg("--out").arg(dir);
    if !rerun {
        cmd.arg("--no-rerun");
    }
    run(&mut cmd);
    dir.join("demo.mcap")
}

fn decoded<T: msgs::Message>(path: &Path, topic: &str) -> Vec<(u64, T, Vec<u8>)> {
    bag::read_messages(path, &[topic])
        .unwrap()
        .into_iter()
        .map(|m| (m.log_time_ns, msgs::decode::<T>(&m.data, topic).unwrap(), m.data))
        .collect()
}

/// Every recorded topic of a CPU replay, by stamp and bytes, as the demo wrote it: meshes,
/// feedback, surface, images and the warped volume's descriptions; on rayon's default
/// threads and on one. `/diagnostics` alone differs by design: it reports wall-clock time.
#[test]
fn a_cpu_replay_repeats_every_topic_of_the_demo_bit_for_bit_on_any_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    let demo_bag = demo(dir.path(), false);
    let replays: Vec<PathBuf> = [None, Some("1")]
        .into_iter()
        .enumerate()
        .map(|(i, threads)| {
            let out = dir.path().join(format!("replay{i}.mcap"));
            let mut cmd = defvol();
            cmd.arg("replay").arg(&demo_bag).arg("--scene").arg(scene()).arg("--out").arg(&out);
            if let Some(threads) = threads {
                cmd.env("RAYON_NUM_THREADS", threads);
            }
            run(&mut cmd);
            out
        })
        .collect();
    let by_topic = |path: &Path| {
        let mut topics: std::collections::BTreeMap<String, Vec<(u64, Vec<u8>)>> = Default::default();
        for m in bag::read_messages(path, &[]).unwrap() {
            if m.topic != "/diagnostics" {
                topics.entry(m.topic.clone()).or_default().push((m.log_time_ns, m.data));
            }
        }
        topics
    };
    let recorded = by_topic(&demo_bag);
    let names: Vec<&str> = recorded.keys().map(String::as_str).collect();
    for topic in ["/deformed_mesh", "/tool_feedback", "/raycast/image", "/dpcm/image", "/warped_volume/info"] {
        assert!(names.contains(&topic), "{topic} is not recorded: {names:?}");
    }
    for (replay, threads) in replays.iter().zip(["default", "1"]) {
        let replayed = by_topic(replay);
        assert_eq!(replayed.keys().collect::<Vec<_>>(), recorded.keys().collect::<Vec<_>>());
        for (topic, messages) in &recorded {
            let other = &replayed[topic];
            assert_eq!(other.len(), messages.len(), "{topic} on {threads} threads");
            let first = messages.iter().zip(other).position(|(a, b)| a != b);
            assert!(first.is_none(), "{topic} on {threads} threads: message {first:?} differs");
        }
    }
    let meshes = decoded::<DeformedMesh>(&demo_bag, "/deformed_mesh");
    assert_eq!(meshes.len(), 60, "one mesh per solver step");
    assert!(meshes.last().unwrap().1.scalars.iter().any(|d| *d > 1e-3), "the probe deformed the mesh");
    let feedback = decoded::<WrenchStamped>(&demo_bag, "/tool_feedback");
    assert!(feedback.last().unwrap().1.wrench.force.z > 1.0, "the organ pushes back on the probe");
    // The replay's bag holds its inputs too: it replays in turn.
    assert_eq!(bag::read_messages(&replays[0], &["/tool_pose"]).unwrap().len(), 60);
}

#[test]
fn replay_names_a_bag_without_tool_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let demo_bag = demo(dir.path(), false);
    let out = defvol()
        .arg("replay")
        .arg(&demo_bag)
        .arg("--scene")
        .arg(scene())
        .args(["--namespace", "/robot"])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stderr);
    let present = text.split("the bag's topics are ").nth(1).unwrap_or_default();
    assert!(!out.status.success() && text.contains("/robot/tool_pose"), "{text}");
    assert_eq!(present.matches("/tool_pose,").count(), 1, "each topic once: {text}");
    let broken = dir.path().join("broken.mcap");
    std::fs::write(&broken, b"not an mcap file").unwrap();
    let out = defvol().arg("replay").arg(&broken).output().unwrap();
    let text = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && text.contains("broken.mcap"), "{text}");
}

#[test]
fn the_bag_reads_back_with_a_rosbag2_reader() {
    if !have("python3 with mcap-ros2-support", Command::new("python3").args(["-c", "import mcap_ros2.decoder"])) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let bag_path = demo(dir.path(), false);
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/read_bag.py");
    let text = run(Command::new("python3").arg(script).arg(&bag_path));
    let read: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
    assert_eq!(read["profile"], "ros2");
    for topic in [
        "/tool_pose",
        "/tool_feedback",
        "/deformed_mesh",
        "/surface_marker",
        "/raycast/image",
        "/dpcm/height",
        "/dpcm/image",
        "/warped_volume/info",
        "/diagnostics",
    ] {
        assert!(read["topics"][topic].as_u64().unwrap_or(0) > 0, "{topic} missing from {}", read["topics"]);
        assert_eq!(read["qos"][topic], true, "{topic} has offered_qos_profiles");
    }
    assert_eq!(read["schemas"]["/surface_marker"], "visualization_msgs/msg/Marker");
    // The values it decodes are the ones written, field for field.
    let ours = decoded::<DeformedMesh>(&bag_path, "/deformed_mesh");
    let theirs = read["meshes"].as_array().unwrap();
    assert_eq!(theirs.len(), ours.len());
    for (t, (_, o, _)) in theirs.iter().zip(&ours) {
        assert_eq!(t["step"].as_u64().unwrap(), o.step);
        assert_eq!(t["nodes"].as_u64().unwrap() as usize, o.positions.len() / 3);
        let first: Vec<f32> = t["first"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
        assert_eq!(first, o.positions[..3]);
        assert_eq!(t["peak"].as_f64().unwrap() as f32, o.scalars.iter().fold(f32::MIN, |m, v| m.max(*v)));
    }
    let feedback = decoded::<WrenchStamped>(&bag_path, "/tool_feedback");
    let z: Vec<f64> = read["feedback_z"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert_eq!(z, feedback.iter().map(|f| f.1.wrench.force.z).collect::<Vec<_>>());
    assert_eq!(read["images"]["/raycast/image"], serde_json::json!([64, 48, "rgba8", 64 * 48 * 4]));
    assert_eq!(read["images"]["/dpcm/height"], serde_json::json!([64, 64, "32FC1", 64 * 64 * 4]));
}

/// The demo's rerun log passes `rerun rrd verify` and holds what a medical viewer shows.
#[cfg(feature = "rerun")]
#[test]
fn the_rerun_log_passes_rerun_verify() {
    if !have("the rerun CLI (rerun-sdk)", Command::new("rerun").arg("--version")) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    demo(dir.path(), true);
    let rrd = dir.path().join("demo.rrd");
    assert!(std::fs::metadata(&rrd).unwrap().len() > 10_000);
    let text = run(Command::new("rerun").args(["rrd", "verify"]).arg(&rrd));
    assert!(text.contains("1 file verified without error"), "{text}");
    // The patient as a viewer shows one: the camera as a pinhole placed in the world with its
    // image in its frustum, and the warped volume's three slices.
    let printed = run(Command::new("rerun").args(["rrd", "print"]).arg(&rrd));
    for (entity, columns) in [
        ("/world/camera", "[Pinhole:image_from_camera Pinhole:resolution]"),
        ("/world/camera", "[Transform3D:mat3x3 Transform3D:translation]"),
        ("/world/camera/image", "[Image:buffer Image:format]"),
        ("/slices/axial", "[Image:buffer Image:format]"),
        ("/slices/coronal", "[Image:buffer Image:format]"),
        ("/slices/sagittal", "[Image:buffer Image:format]"),
    ] {
        let line = format!(" - {entity} - data columns: {columns}");
        assert!(printed.lines().any(|l| l.ends_with(&line)), "no {entity} {columns} in:\n{printed}");
    }
}

/// `defvol demo` on the GPU backend (the suite's software adapter allowed) runs every stage
/// on the GPU, and its bag's diagnostics say so, stage by stage; without the software
/// adapter allowed, `--backend gpu` on a machine with no hardware GPU is an error saying why.
#[cfg(feature = "gpu")]
#[test]
fn a_gpu_demo_reports_every_stage_on_the_gpu() {
    use defvol::msgs::{DiagnosticArray, WarpedVolumeInfo};
    let dir = tempfile::tempdir().unwrap();
    let out = defvol()
        .args(["demo", "--seconds", "0.3", "--backend", "gpu", "--allow-software-gpu", "--no-rerun", "--scene"])
        .arg(scene())
        .arg("--out")
        .arg(dir.path())
        .output()
        .unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    if !out.status.success() && text.contains("no GPU adapter") && std::env::var_os("DEFVOL_REQUIRE_GPU").is_none() {
        eprintln!("skipped: no GPU adapter ({text})");
        return;
    }
    assert!(out.status.success(), "{text}");
    let bag_path = dir.path().join("demo.mcap");
    let diagnostics = decoded::<DiagnosticArray>(&bag_path, "/diagnostics");
    assert!(!diagnostics.is_empty());
    let mut round_trips = Vec::new();
    for (_, array, _) in &diagnostics {
        let status = array.status.iter().find(|s| s.name == "defvol: backend").expect("a backend status");
        let pairs = status.values.iter().map(|kv| (kv.key.as_str(), kv.value.as_str()));
        let (stages, gpu): (Vec<_>, Vec<_>) = pairs.partition(|(key, _)| key.starts_with("backend."));
        assert_eq!(
            stages,
            [("backend.solver", "gpu"), ("backend.warp", "gpu"), ("backend.dpcm", "gpu"), ("backend.raycast", "gpu")]
        );
        let count = |key: &str| gpu.iter().find(|(k, _)| *k == key).and_then(|(_, v)| v.parse::<u64>().ok());
        round_trips.push([count("gpu.submissions"), count("gpu.readbacks"), count("gpu.bytes_read_back")]);
    }
    // The GPU's round trips since the start, counted by the plumbing: they only grow.
    let first = round_trips[0].map(|c| c.expect("the GPU's counters in the backend status"));
    assert!(first.iter().all(|c| *c > 0), "{round_trips:?}");
    assert!(round_trips.windows(2).all(|w| (0..3).all(|k| w[0][k] <= w[1][k])), "{round_trips:?}");
    // The warped volume's geometry is whole: the phantom's identity direction, row major.
    let info = decoded::<WarpedVolumeInfo>(&bag_path, "/warped_volume/info");
    assert_eq!(info.last().unwrap().1.direction, [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
    // No hardware GPU and the software one not allowed: an error naming why.
    let hardware = defvol()
        .args(["demo", "--seconds", "0.01", "--backend", "gpu", "--no-rerun", "--out"])
        .arg(dir.path().join("hw"))
        .output()
        .unwrap();
    if !hardware.status.success() {
        let text = String::from_utf8_lossy(&hardware.stderr);
        assert!(text.contains("backend gpu") && text.contains("software adapters, not allowed"), "{text}");
    }
}

#[test]
fn the_recording_names_topics_as_the_node_does_remaps_applied() {
    use defvol::backend::Backend;
    use defvol::msgs::{PoseStamped, Time};
    use defvol::pipeline::inputs::InputLimits;
    use defvol::pipeline::{Demand, FrameMode, Pipeline};
    use defvol::scene::Scene;
    use defvol::session::{RecordOptions, Session, TopicNames};
    let dir = tempfile::tempdir().unwrap();
    let bag_path = dir.path().join("remapped.mcap");
    let scene = Scene::from_file(&scene()).unwrap();
    let mut pipeline = Pipeline::new(scene, &Backend::cpu(), InputLimits::default(), FrameMode::Lockstep).unwrap();
    let names = TopicNames {
        namespace: "/robot".into(),
        remaps: [("deformed_mesh", "mesh_out"), ("/robot/tool_pose", "probe_pose")]
            .map(|(a, b)| (a.to_owned(), b.to_owned()))
            .into(),
    };
    let records = RecordOptions { mcap: Some(bag_path.clone()), ..Default::default() };
    let mut session = Session::open(&names, &records, &pipeline).unwrap();
    let stamp = Time::from_nanos(1_000_000);
    session.record_pose("tool_pose", &PoseStamped::default(), None);
    let out = pipeline.tick(stamp, &Demand { deformed_mesh: true, ..Demand::NONE }).unwrap();
    session.record_outputs(&out, &pipeline, stamp);
    session.finish().unwrap();
    let topics: std::collections::BTreeSet<String> =
        bag::read_messages(&bag_path, &[]).unwrap().into_iter().map(|m| m.topic).collect();
    assert!(topics.contains("/robot/mesh_out") && topics.contains("/robot/probe_pose"), "{topics:?}");
    assert!(!topics.contains("/robot/deformed_mesh") && !topics.contains("/robot/tool_pose"), "{topics:?}");
}

/// The warped volumes themselves, which leave by shared memory and not through the bag,
/// repeat bit for bit from the same poses on rayon's default threads and on one, while a
/// probe presses in and changes them.
#[test]
fn the_warped_volumes_repeat_bit_for_bit_on_any_thread_count() {
    use std::sync::{Arc, Mutex};

    use defvol::backend::Backend;
    use defvol::msgs::{Header, PoseStamped, Time};
    use defvol::pipeline::inputs::InputLimits;
    use defvol::pipeline::{Demand, FrameMode, Pipeline, VolumeSink, WarpedVolume, WriteVolume};
    use defvol::scene::Scene;

    /// Every volume published, as the warp wrote it into memory lent to it.
    struct Capture(Mutex<Vec<(u64, Vec<u32>)>>);
    impl VolumeSink for Capture {
        fn has_subscribers(&self) -> bool {
            true
        }
        fn publish(&self, volume: &WarpedVolume, write: &mut WriteVolume<'_>) -> Result<(), String> {
            let mut samples = vec![0f32; volume.grid.len()];
            write(&mut samples, None)?;
            let bits = samples.iter().map(|v| v.to_bits()).collect();
            self.0.lock().map_err(|e| e.to_string())?.push((volume.sequence, bits));
            Ok(())
        }
    }
    let run = || {
        let mut scene = Scene::from_file(&scene()).unwrap();
        scene.tools[0].path = None;
        let limits = InputLimits { max_age: None, ..Default::default() };
        let mut pipeline = Pipeline::new(scene, &Backend::cpu(), limits, FrameMode::Lockstep).unwrap();
        let capture = Arc::new(Capture(Mutex::new(Vec::new())));
        pipeline.set_volume_sink(Some(capture.clone() as Arc<dyn VolumeSink>));
        let demand = Demand { warped_volume: true, ..Demand::NONE };
        for tick in 1..=60u32 {
            let stamp = Time::from_secs(f64::from(tick) * 0.01);
            let mut pose = PoseStamped { header: Header { stamp, frame_id: "world".into() }, ..Default::default() };
            // Down from 12 cm to 7 cm over the first half second, then held.
            pose.pose.position.z = 0.12 - 0.05 * (f64::from(tick) / 50.0).min(1.0);
            pipeline.apply_pose("tool_pose", &pose, stamp).unwrap();
            pipeline.tick(stamp, &demand).unwrap();
        }
        let volumes = std::mem::take(&mut *capture.0.lock().unwrap());
        volumes
    };
    let default_threads = run();
    let one_thread = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap().install(run);
    assert!(default_threads.len() >= 3, "{} volumes published", default_threads.len());
    let (first, last) = (&default_threads[0].1, &default_threads.last().unwrap().1);
    let moved = first.iter().zip(last).filter(|(a, b)| a != b).count();
    assert!(moved > 1000, "the press changed {moved} voxels");
    assert_eq!(one_thread.len(), default_threads.len());
    for ((s1, a), (s2, b)) in default_threads.iter().zip(&one_thread) {
        let differ = a.iter().zip(b).filter(|(x, y)| x != y).count();
        assert_eq!((s1, differ), (s2, 0), "volume {s1}: {differ} voxels differ on one thread");
    }
}
