//! The node over DDS. Every test here runs inside a private network namespace (only a
//! loopback interface): a test that finds a real interface re-runs itself through
//! `tests/netns-run`, so no run of the suite can put DDS traffic on a real network.

use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use nalgebra::Vector3;

use defvol::msgs::{
    self, DeformedMesh, DiagnosticArray, Header, Image, LoadSceneRequest, Marker, Pose, PoseStamped, Time,
    TriggerRequest, TriggerResponse, WarpedVolumeInfo, WrenchStamped,
};
use defvol::record::{bag, Qos};
use defvol::ros::dds::{self, Discovery};
use defvol::ros::node::qos;
use ros2_client::rcl_interfaces::{
    GetParametersRequest, GetParametersResponse, SetParametersRequest, SetParametersResponse,
};
use ros2_client::{
    MessageTypeName, Name, NodeName, NodeOptions, Parameter, ParameterValue, ServiceMapping, ServiceTypeName,
};

/// Runs `test` inside a private network namespace: directly when already in one, else by
/// re-running this test binary, filtered to `name`, through tests/netns-run.
fn isolated(name: &str, test: impl FnOnce()) {
    if dds::private_network() {
        test();
        return;
    }
    // Once re-run, the namespace must be private: never recurse.
    assert!(
        std::env::var_os("DEFVOL_NETNS_RERUN").is_none(),
        "{name}: still on a real interface after tests/netns-run"
    );
    rerun_in_a_namespace_of_its_own(name);
}

/// Re-runs this test binary, filtered to the test `name` of this module, through
/// tests/netns-run: a fresh private network namespace.
fn rerun_in_a_namespace_of_its_own(name: &str) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/netns-run");
    // The harness names a test by its path inside the test crate: `node_dds::<name>`.
    let path = module_path!().split_once("::").map_or(module_path!(), |(_crate, module)| module);
    let status = Command::new(script)
        .arg(std::env::current_exe().unwrap())
        .args(["--exact", &format!("{path}::{name}"), "--nocapture", "--test-threads", "1"])
        .env("DEFVOL_NETNS_RERUN", "1")
        .status()
        .unwrap();
    assert!(status.success(), "{name} failed inside its network namespace");
}

fn scene() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/small_scene.yaml")
}

/// A node on the small scene; its shared-memory service is its own (/dev/shm is shared by
/// every network namespace, and tests run side by side).
fn start_node(dir: &Path, seconds: u32, test: &str) -> Child {
    start_node_on(&scene(), dir, seconds, test)
}

fn start_node_on(scene: &Path, dir: &Path, seconds: u32, test: &str) -> Child {
    Command::new(env!("CARGO_BIN_EXE_defvol_node"))
        .args(["--backend", "cpu", "--seconds", &seconds.to_string(), "--record"])
        .arg(dir.join("node.mcap"))
        .args(["--ros-args", "-r", "__ns:=/robot", "-p"])
        .arg(format!("scene_file:={}", scene.display()))
        .arg("-p")
        .arg(format!("warp.service:=defvol/{test}_{}", std::process::id()))
        .env("ROS_DOMAIN_ID", "17")
        .env_remove("ROS_DISTRO")
        .env_remove("RUST_LOG")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
}

/// A reliable publisher of tool poses on `/robot/tool_pose`, as a device's driver makes one.
fn pose_publisher(peer: &mut ros2_client::Node) -> ros2_client::Publisher<PoseStamped> {
    let name = Name::parse("/robot/tool_pose").unwrap();
    let topic = peer.create_topic(&name, type_name::<PoseStamped>(), &qos(Qos::Reliable)).unwrap();
    peer.create_publisher::<PoseStamped>(&topic, Some(qos(Qos::Reliable))).unwrap()
}

/// A client of the node's `/robot/pause` (std_srvs/Trigger).
fn pause_client(peer: &mut ros2_client::Node) -> ros2_client::Client<TriggerRequest, TriggerResponse> {
    service_client(peer, "/robot/pause", "std_srvs", "Trigger")
}

/// A client of the service `name` of type `package/srv/ty`, as `ros2 service call` makes one.
fn service_client<Q: ros2_client::Message + Clone + 'static, A: ros2_client::Message + 'static>(
    peer: &mut ros2_client::Node,
    name: &str,
    package: &str,
    ty: &str,
) -> ros2_client::Client<Q, A> {
    let (name, ty) = (Name::parse(name).unwrap(), ServiceTypeName::new(package, ty));
    peer.create_client(ServiceMapping::Enhanced, &name, &ty, qos(Qos::Reliable), qos(Qos::Reliable)).unwrap()
}

/// The small scene in `dir` with one haptically coupled probe (a device's pose answered
/// from the local model), the solver alone or with the raycast `camera`.
fn coupled_scene(dir: &Path, camera: bool) -> PathBuf {
    let small = std::fs::read_to_string(scene()).unwrap();
    let (head, tail) = small.split_once("tools:").unwrap();
    let rest = &tail[tail.find("frame_id:").unwrap()..];
    let tool = "tools:\n  - name: probe\n    shape: { kind: sphere, radius: 0.002 }\n    contact: surface\n    \
                contact_stiffness: 20000.0\n    spread_radius: 0.01\n    \
                coupling: { stiffness: 1000.0, damping: 2.0, mass: 0.02, max_force: 10.0 }\n";
    let coupled = format!("{head}{tool}{rest}").replace(
        "stages: { solver: true, warp: true, dpcm: true, raycast: true }",
        &format!("stages: {{ solver: true, warp: false, dpcm: false, raycast: {camera} }}"),
    );
    let path = dir.join("coupled.yaml");
    std::fs::write(&path, coupled).unwrap();
    path
}

fn type_name<T: msgs::Message>() -> MessageTypeName {
    let parts: Vec<&str> = T::NAME.split('/').collect();
    MessageTypeName::new(parts[0], parts[2])
}

fn pose_at(z: f64) -> PoseStamped {
    let since = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap();
    let mut msg = PoseStamped {
        header: Header { stamp: Time::from_nanos(since.as_nanos() as u64), frame_id: "world".into() },
        pose: Pose::default(),
    };
    msg.pose.position.z = z;
    msg
}

#[test]
fn a_second_participant_drives_the_node_and_receives_every_output() {
    isolated("a_second_participant_drives_the_node_and_receives_every_output", || {
        let dir = tempfile::tempdir().unwrap();
        let node_process = start_node(dir.path(), 14, "second_participant");
        // A second context: in loopback-only mode a participant does not hear itself.
        let context = dds::context(17, Discovery::Localhost).unwrap();
        let mut peer = context.new_node(NodeName::new("/", "peer").unwrap(), NodeOptions::new()).unwrap();
        macro_rules! subscribe {
            ($ty:ty, $topic:expr, $kind:expr) => {{
                let t = peer.create_topic(&Name::parse($topic).unwrap(), type_name::<$ty>(), &qos($kind)).unwrap();
                peer.create_subscription::<$ty>(&t, Some(qos($kind))).unwrap()
            }};
        }
        let feedback = subscribe!(WrenchStamped, "/robot/tool_feedback", Qos::SensorData);
        let meshes = subscribe!(DeformedMesh, "/robot/deformed_mesh", Qos::Reliable);
        let markers = subscribe!(Marker, "/robot/surface_marker", Qos::Reliable);
        let raycast = subscribe!(Image, "/robot/raycast/image", Qos::SensorData);
        let heights = subscribe!(Image, "/robot/dpcm/height", Qos::SensorData);
        let dpcm_images = subscribe!(Image, "/robot/dpcm/image", Qos::SensorData);
        let warped = subscribe!(WarpedVolumeInfo, "/robot/warped_volume/info", Qos::Latched);
        let diagnostics = subscribe!(DiagnosticArray, "/robot/diagnostics", Qos::Reliable);
        let poses = pose_publisher(&mut peer);
        let pause = pause_client(&mut peer);

        let set_parameters = service_client::<SetParametersRequest, SetParametersResponse>(
            &mut peer,
            "/robot/defvol/set_parameters",
            "rcl_interfaces",
            "SetParameters",
        );
        let load_scene = service_client::<LoadSceneRequest, TriggerResponse>(
            &mut peer,
            "/robot/load_scene",
            "defvol_interfaces",
            "LoadScene",
        );
        let mut load_reply = None;
        let impossible = || SetParametersRequest {
            parameter: vec![
                Parameter { name: "solver.dt".into(), value: ParameterValue::Double(-1.0) }.into(),
                Parameter { name: "backend".into(), value: ParameterValue::String("gpu".into()) }.into(),
            ],
        };
        let mut parameter_reply = None;
        let mut counts = [0usize; 8];
        let (mut peak_force, mut peak_displacement, mut refused_nan) = (0.0f64, 0.0f32, false);
        let mut warped_info = None;
        let mut pause_reply = None;
        let start = Instant::now();
        let mut sent = 0;
        while start.elapsed() < Duration::from_secs(11) {
            // Down from 10 cm to 7 cm over two seconds, then held; one NaN pose on the way.
            let s = (start.elapsed().as_secs_f64() / 2.0).min(1.0);
            poses.publish(pose_at(0.10 - 0.03 * s)).unwrap();
            if sent % 100 == 50 {
                poses.publish(pose_at(f64::NAN)).unwrap();
            }
            sent += 1;
            while let Ok(Some((m, _))) = feedback.take() {
                counts[0] += 1;
                peak_force = peak_force.max(m.wrench.force.z);
            }
            while let Ok(Some((m, _))) = meshes.take() {
                counts[1] += 1;
                assert_eq!(m.positions.len(), 3 * m.scalars.len());
                peak_displacement = peak_displacement.max(m.scalars.iter().fold(0.0, |a, b| a.max(*b)));
            }
            while let Ok(Some((m, _))) = markers.take() {
                counts[2] += 1;
                assert_eq!((m.kind, m.points.len() % 3, m.colors.len()), (Marker::TRIANGLE_LIST, 0, m.points.len()));
            }
            while let Ok(Some((m, _))) = raycast.take() {
                counts[3] += 1;
                assert_eq!((m.width, m.height, m.encoding.as_str(), m.data.len()), (64, 48, "rgba8", 64 * 48 * 4));
            }
            while let Ok(Some((m, _))) = heights.take() {
                counts[4] += 1;
                assert_eq!((m.encoding.as_str(), m.data.len()), ("32FC1", 64 * 64 * 4));
            }
            while let Ok(Some((m, _))) = dpcm_images.take() {
                counts[5] += 1;
                assert_eq!(m.encoding, "rgb8");
            }
            while let Ok(Some((m, _))) = warped.take() {
                counts[6] += 1;
                warped_info = Some(m);
            }
            while let Ok(Some((m, _))) = diagnostics.take() {
                counts[7] += 1;
                refused_nan |= m
                    .status
                    .iter()
                    .any(|s| s.name == "defvol: inputs" && s.values.iter().any(|kv| kv.key == "rejected_not_finite"));
            }
            if start.elapsed() > Duration::from_secs(7) && parameter_reply.is_none() {
                if let Ok(Some((_, reply))) = set_parameters.receive_response() {
                    parameter_reply = Some(reply);
                } else if sent % 50 == 0 {
                    let _ = set_parameters.send_request(impossible());
                }
            }
            if start.elapsed() > Duration::from_secs(8) && load_reply.is_none() {
                if let Ok(Some((_, reply))) = load_scene.receive_response() {
                    load_reply = Some(reply);
                } else if sent % 50 == 25 {
                    let _ = load_scene.send_request(LoadSceneRequest { scene: "volume: [phantom\nmesh: {}".into() });
                }
            }
            if start.elapsed() > Duration::from_secs(9) && pause_reply.is_none() {
                if let Ok(Some((_, reply))) = pause.receive_response() {
                    pause_reply = Some(reply);
                } else if sent % 50 == 0 {
                    let _ = pause.send_request(TriggerRequest::default());
                }
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let exit = node_process.wait_with_output().unwrap();
        assert!(exit.status.success(), "the node exited with {}", exit.status);
        eprintln!("received {counts:?}; peak force {peak_force} N, displacement {peak_displacement} m");
        assert!(counts.iter().all(|c| *c > 0), "every output topic delivers: {counts:?}");
        assert!(
            peak_force > 1.0 && peak_displacement > 1e-3,
            "the probe pressed in: {peak_force} N, {peak_displacement} m"
        );
        assert!(refused_nan, "diagnostics report the NaN pose");
        let info = warped_info.unwrap();
        assert!(info.service_name.starts_with("defvol/second_participant_"), "{info:?}");
        assert_eq!(info.dims, [256, 160, 122]);
        assert_eq!(pause_reply.map(|r| (r.success, r.message)), Some((true, "paused".to_owned())));
        // A broken scene is refused by name and the running one kept.
        let load = load_reply.expect("load_scene answered");
        assert!(
            !load.success
                && load.message.contains("kept the running scene")
                && load.message.contains("load_scene request"),
            "{load:?}"
        );
        // The parameter services check a scene change before taking it.
        let results = parameter_reply.expect("set_parameters answered").results;
        assert_eq!(results.len(), 2);
        assert!(!results[0].successful && results[0].reason.contains("dt"), "{:?}", results[0]);
        // The backend is the run's: a running node refuses to change it.
        assert!(!results[1].successful && results[1].reason.contains("read-only"), "{:?}", results[1]);
        // The node's recording holds what went over the wire.
        let recorded =
            bag::read_messages(&dir.path().join("node.mcap"), &["/robot/tool_pose", "/robot/deformed_mesh"]).unwrap();
        assert!(recorded.iter().filter(|m| m.topic == "/robot/tool_pose").count() > 100);
        assert!(recorded.iter().any(|m| m.topic == "/robot/deformed_mesh"));
    });
}

/// A coupled thin tool is answered from its local model: each pose at once, stamped with
/// it, so answers come at the pose rate (500 Hz here), not the solver's (100 Hz), and the
/// surface holds the tool short of the coupling's largest force.
#[test]
fn a_coupled_tool_is_answered_at_the_pose_rate_not_the_solver_rate() {
    isolated("a_coupled_tool_is_answered_at_the_pose_rate_not_the_solver_rate", || {
        let dir = tempfile::tempdir().unwrap();
        let scene = coupled_scene(dir.path(), false);
        let node_process = start_node_on(&scene, dir.path(), 9, "coupled");
        let context = dds::context(17, Discovery::Localhost).unwrap();
        let mut peer = context.new_node(NodeName::new("/", "device").unwrap(), NodeOptions::new()).unwrap();
        let feedback_topic = peer
            .create_topic(
                &Name::parse("/robot/tool_feedback").unwrap(),
                type_name::<WrenchStamped>(),
                &qos(Qos::SensorData),
            )
            .unwrap();
        let feedback = peer.create_subscription::<WrenchStamped>(&feedback_topic, Some(qos(Qos::SensorData))).unwrap();
        let poses = pose_publisher(&mut peer);
        let (mut sent, mut answers, mut peak, mut strongest) = (Vec::new(), Vec::new(), 0.0f64, 0.0f64);
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(6) {
            // Down from 1 cm above the phantom's top (z = 0.06) to 2 mm into it, then held.
            let s = (start.elapsed().as_secs_f64() / 2.0).min(1.0);
            let pose = pose_at(0.072 - 0.014 * s);
            poses.publish(pose.clone()).unwrap();
            sent.push((pose.header.stamp, Instant::now()));
            while let Ok(Some((m, _))) = feedback.take() {
                let f = Vector3::new(m.wrench.force.x, m.wrench.force.y, m.wrench.force.z);
                (peak, strongest) = (peak.max(f.z), strongest.max(f.norm()));
                answers.push((m.header.stamp, Instant::now()));
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        let exit = node_process.wait_with_output().unwrap();
        assert!(exit.status.success(), "the node exited with {}", exit.status);
        // From the first answer on (the node up and matched), every pose is answered.
        let first = answers.first().map(|a| a.0).expect("the device got feedback");
        let expected: Vec<_> = sent.iter().filter(|(stamp, _)| stamp.as_secs() >= first.as_secs()).collect();
        let answered = expected.iter().filter(|(stamp, _)| answers.iter().any(|a| a.0 == *stamp)).count();
        let seconds = answers.last().unwrap().1.duration_since(answers[0].1).as_secs_f64();
        let rate = answers.len() as f64 / seconds;
        eprintln!("{answered} of {} poses answered, {rate:.0} Hz; peak {peak} N", expected.len());
        assert!(answered as f64 > 0.95 * expected.len() as f64, "{answered} of {} poses answered", expected.len());
        assert!(rate > 300.0, "answers come at {rate:.0} Hz, faster than the solver's 100 Hz");
        // Pressed, held by the surface short of the coupling's largest force.
        assert!(peak > 0.5 && strongest < 10.0, "the tool pressed with {peak} N, at most {strongest} N");
    });
}

#[test]
fn a_cyclone_dds_peer_sees_ros2_types() {
    isolated("a_cyclone_dds_peer_sees_ros2_types", || {
        if !python_has("cyclonedds.domain") {
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let node_process = start_node(dir.path(), 12, "cyclone");
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/cyclone_peer.py");
        let out = Command::new("python3").arg(script).args(["8", "/robot"]).env("ROS_DOMAIN_ID", "17").env("CYCLONEDDS_URI", "<CycloneDDS><Domain id=\"17\"><General><Interfaces><NetworkInterface name=\"lo\"/></Interfaces></General></Domain></CycloneDDS>").output().unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
        let exit = node_process.wait_with_output().unwrap();
        let log = String::from_utf8_lossy(&exit.stderr);
        assert!(exit.status.success(), "{log}");
        // A start and a shutdown say nothing alarming (no ROS_DISTRO nag, no DDS entity left
        // behind its participant); the peer's NaN poses are refused, each kind said at most
        // once a second.
        let warnings: Vec<&str> = log.lines().filter(|l| l.contains("WARN") || l.contains("ERROR")).collect();
        let refusals =
            warnings.iter().filter(|l| l.contains("WARN refused tool_pose: pose.position is not finite")).count();
        assert!(refusals == warnings.len() && refusals >= 1 && log.contains("node /robot/defvol up"), "{log}");
        let got: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
        eprintln!("{got}");
        assert!(
            got["feedback"].as_u64().unwrap() > 0
                && got["meshes"].as_u64().unwrap() > 0
                && got["diagnostics"].as_u64().unwrap() > 0,
            "{got}"
        );
        assert!(got["max_force_z"].as_f64().unwrap() > 1.0, "its poses reached the solver: {got}");
        assert_eq!(got["rejected_nan"], true, "{got}");
        // And the Cyclone peer's poses are in the node's recording, as it sent them.
        let poses = bag::read_messages(&dir.path().join("node.mcap"), &["/robot/tool_pose"]).unwrap();
        assert!(poses.len() > 50, "{} poses recorded", poses.len());
        let last = msgs::decode::<PoseStamped>(&poses.last().unwrap().data, "recorded").unwrap();
        assert!((last.pose.position.z - 0.07).abs() < 1e-9, "{last:?}");
    });
}

/// Whether `module` imports in the interop venv's python3; missing it fails the suite when
/// tests/run.sh runs it (it installs the module), and skips the test otherwise.
fn python_has(module: &str) -> bool {
    let have =
        Command::new("python3").args(["-c", &format!("import {module}")]).output().is_ok_and(|o| o.status.success());
    assert!(
        have || std::env::var_os("DEFVOL_REQUIRE_INTEROP").is_none(),
        "python3 {module} is missing (tests/run.sh installs it)"
    );
    if !have {
        eprintln!("skipped: python3 {module} is not installed");
    }
    have
}

#[test]
fn rclpy_sees_each_parameter_described_and_out_of_range_values_refused() {
    isolated("rclpy_sees_each_parameter_described_and_out_of_range_values_refused", || {
        if !python_has("rclpy") {
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let node_process = start_node(dir.path(), 20, "rclpy_parameters");
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/rclpy_parameters.py");
        let out = Command::new("python3").arg(script).arg("/robot/defvol").env("ROS_DOMAIN_ID", "17").output().unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
        let exit = node_process.wait_with_output().unwrap();
        assert!(exit.status.success(), "{}", String::from_utf8_lossy(&exit.stderr));
        let got: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
        eprintln!("{got}");
        let names: Vec<&str> = got["names"].as_array().unwrap().iter().filter_map(|n| n.as_str()).collect();
        for name in ["solver.dt", "camera.width", "tools.0.shape.radius", "backend", "record", "use_sim_time"] {
            assert!(names.contains(&name), "`ros2 param list` shows {name}: {names:?}");
        }
        // rclpy decodes the descriptors as ROS 2 defines them (ParameterType DOUBLE = 3, INTEGER = 2).
        let dt = &got["solver.dt"];
        assert_eq!((dt["type"].as_u64(), dt["read_only"].as_bool()), (Some(3), Some(false)), "{dt}");
        assert_eq!(dt["floating_point_range"], serde_json::json!([[1e-6, 0.1, 0.0]]));
        assert!(dt["description"].as_str().unwrap().contains("time step"), "{dt}");
        assert_eq!(got["camera.width"]["integer_range"], serde_json::json!([[1, 16384, 1]]));
        assert_eq!(got["backend"]["read_only"], true);
        assert_eq!(got["unknown"], 0, "an undeclared name is described by an empty reply, as rclcpp's");
        // 1e9 s, NaN, a negative step and a string are refused, each saying why; a good one is taken.
        let set = &got["set"];
        for case in ["huge", "nan", "negative"] {
            assert_eq!(set[case]["successful"], false, "{case}: {set}");
            assert!(set[case]["reason"].as_str().unwrap().contains("floating point range"), "{case}: {set}");
        }
        assert_eq!(set["string"]["successful"], false, "{set}");
        assert!(set["backend"]["reason"].as_str().unwrap().contains("read-only"), "{set}");
        assert_eq!(
            (&set["good"]["successful"], &got["dt_after"]),
            (&serde_json::json!(true), &serde_json::json!(0.005))
        );
        // All or none: a good height beside an impossible width leaves the height as it was.
        assert_eq!(got["atomically"]["successful"], false, "{got}");
        assert!(got["atomically"]["reason"].as_str().unwrap().contains("camera.width"), "{got}");
        assert_eq!(got["height_after"], 48);
    });
}

/// The events, states and answers of one node in one step of the rclpy script, the events'
/// stamps left out (rcl_lifecycle leaves them 0; defvol stamps them).
fn unstamped(answer: &serde_json::Value) -> serde_json::Value {
    let mut answer = answer.clone();
    for event in answer["events"].as_array_mut().unwrap() {
        event.as_object_mut().unwrap().remove("stamped");
    }
    answer
}

#[test]
fn a_managed_node_answers_every_lifecycle_request_as_rclpys_own_lifecycle_node() {
    isolated("a_managed_node_answers_every_lifecycle_request_as_rclpys_own_lifecycle_node", || {
        if !python_has("rclpy.lifecycle") || !python_has("diagnostic_msgs.msg") {
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        // A scene whose volume file is missing: it parses, so the node comes up; it does not load.
        let text = std::fs::read_to_string(scene()).unwrap().replace("volume: phantom", "volume: /nonexistent/ct.nii");
        let broken = dir.path().join("broken.yaml");
        std::fs::write(&broken, text).unwrap();
        let node_process = Command::new(env!("CARGO_BIN_EXE_defvol_node"))
            .args(["--backend", "cpu", "--managed", "--seconds", "90", "--record"])
            .arg(dir.path().join("node.mcap"))
            .args(["--ros-args", "-r", "__ns:=/robot", "-p"])
            .arg(format!("scene_file:={}", broken.display()))
            .arg("-p")
            .arg(format!("warp.service:=defvol/lifecycle_{}", std::process::id()))
            .env("ROS_DOMAIN_ID", "17")
            .env_remove("RUST_LOG")
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/rclpy_lifecycle.py");
        let out = Command::new("python3").arg(script).arg("/robot/defvol").env("ROS_DOMAIN_ID", "17").output().unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        // Ctrl-C: a finalized node stays up (as rclcpp's) until stopped.
        Command::new("kill").args(["-INT", &node_process.id().to_string()]).status().unwrap();
        let exit = node_process.wait_with_output().unwrap();
        let log = String::from_utf8_lossy(&exit.stderr);
        assert!(out.status.success(), "{text}{}{log}", String::from_utf8_lossy(&out.stderr));
        assert!(exit.status.success(), "{log}");
        let got: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
        let (reference, defvol) = ("/reference", "/robot/defvol");
        assert_eq!(got["states"][defvol], got["states"][reference], "get_available_states");
        assert_eq!(got["graph"][defvol], got["graph"][reference], "get_transition_graph");
        assert_eq!(got["graph"][defvol].as_array().unwrap().len(), 25);
        assert_eq!(got["initial"][defvol], got["initial"][reference]);
        // Each request, a refused one too, answered and evented as rcl_lifecycle does.
        for step in got["steps"].as_array().unwrap() {
            let (name, answers) = (&step[0], &step[1]);
            assert_eq!(unstamped(&answers[defvol]), unstamped(&answers[reference]), "{name}");
            let events = answers[defvol]["events"].as_array().unwrap();
            assert!(events.iter().all(|e| e["stamped"] == true), "{name}: {events:?}");
        }
        let step = |name: &str| &got["steps"].as_array().unwrap().iter().find(|s| s[0] == name).unwrap()[1][defvol];
        // A scene that does not load fails configure, names why, and leaves the node unconfigured.
        assert_eq!(step("configure a scene that does not load")["success"], false);
        assert_eq!(step("configure a scene that does not load")["state"], serde_json::json!([1, "unconfigured"]));
        assert!(log.contains("/nonexistent/ct.nii: No such file"), "{log}");
        assert_eq!(got["volume_set"], true);
        assert_eq!(step("configure")["state"], serde_json::json!([2, "inactive"]));
        assert_eq!(step("shutdown by its label")["state"], serde_json::json!([4, "finalized"]));
        // Outputs flow only while active.
        let outputs = &got["outputs"];
        for quiet in ["unconfigured", "inactive", "deactivated", "cleaned_up"] {
            assert_eq!(outputs[quiet], 0, "{quiet}: {outputs}");
        }
        assert!(
            outputs["active"].as_u64().unwrap() >= 2 && outputs["active_again"].as_u64().unwrap() >= 1,
            "{outputs}"
        );
        // The recording, closed at cleanup, holds what the active node published.
        let recorded = bag::read_messages(&dir.path().join("node.mcap"), &["/robot/diagnostics"]).unwrap();
        assert!(!recorded.is_empty());
    });
}

/// Builds defvol_interfaces with the ROS 2 generators of the interop venv (rosidl, ament_cmake
/// and CMake from PyPI) into `prefix`; the environment a Python node needs to import it.
fn build_interfaces(prefix: &Path) -> Vec<(String, String)> {
    let python = |code: &str| {
        let out = Command::new("python3").args(["-c", code]).output().unwrap();
        String::from_utf8(out.stdout).unwrap().trim().to_owned()
    };
    let (venv, executable) = (python("import sys; print(sys.prefix)"), python("import sys; print(sys.executable)"));
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("defvol_interfaces");
    let build = prefix.join("build");
    let install = prefix.join("install");
    let run = |args: &[&str]| {
        let out = Command::new("cmake").args(args).env("AMENT_PREFIX_PATH", &venv).output().unwrap();
        let log = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        assert!(out.status.success(), "cmake {args:?}:\n{log}");
    };
    run(&[
        "-S",
        source.to_str().unwrap(),
        "-B",
        build.to_str().unwrap(),
        &format!("-DCMAKE_PREFIX_PATH={venv}"),
        &format!("-DCMAKE_INSTALL_PREFIX={}", install.display()),
        &format!("-DPython3_EXECUTABLE={executable}"),
        "-DBUILD_TESTING=OFF",
    ]);
    run(&["--build", build.to_str().unwrap(), "-j2"]);
    run(&["--install", build.to_str().unwrap()]);
    let site = python("import sysconfig; print(sysconfig.get_path('purelib', vars={'base': ''}).lstrip('/'))");
    vec![
        ("PYTHONPATH".into(), install.join(site).display().to_string()),
        ("LD_LIBRARY_PATH".into(), install.join("lib").display().to_string()),
        ("AMENT_PREFIX_PATH".into(), format!("{}:{venv}", install.display())),
    ]
}

#[test]
fn a_python_node_built_against_defvol_interfaces_reads_what_the_node_publishes() {
    isolated("a_python_node_built_against_defvol_interfaces_reads_what_the_node_publishes", || {
        let have_cmake = Command::new("cmake").arg("--version").output().is_ok_and(|o| o.status.success());
        assert!(
            have_cmake || std::env::var_os("DEFVOL_REQUIRE_INTEROP").is_none(),
            "cmake is missing (tests/run.sh installs it)"
        );
        if !have_cmake || !python_has("rosidl_generator_py") {
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let environment = build_interfaces(dir.path());
        let node_process = start_node(dir.path(), 20, "interfaces");
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/rclpy_interfaces.py");
        let out = Command::new("python3")
            .arg(script)
            .arg("/robot")
            .env("ROS_DOMAIN_ID", "17")
            .envs(environment)
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
        let exit = node_process.wait_with_output().unwrap();
        assert!(exit.status.success(), "{}", String::from_utf8_lossy(&exit.stderr));
        let got: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
        // The mesh the Python node decoded is the one the node recorded at that step, value for value.
        let mesh = &got["mesh"];
        let recorded = bag::read_messages(&dir.path().join("node.mcap"), &["/robot/deformed_mesh"]).unwrap();
        let same = recorded
            .iter()
            .map(|m| msgs::decode::<DeformedMesh>(&m.data, "recorded").unwrap())
            .find(|m| {
                serde_json::json!([m.header.stamp.sec, m.header.stamp.nanosec]) == mesh["stamp"]
                    && serde_json::json!(m.step) == mesh["step"]
            })
            .expect("the mesh received is in the recording");
        let positions: Vec<f32> =
            mesh["positions"].as_array().unwrap().iter().map(|p| p.as_f64().unwrap() as f32).collect();
        let triangles: Vec<u32> =
            mesh["triangles"].as_array().unwrap().iter().map(|t| t.as_u64().unwrap() as u32).collect();
        assert_eq!((positions, triangles), (same.positions.clone(), same.triangles.clone()));
        assert_eq!(
            (mesh["frame_id"].as_str(), mesh["scalar_name"].as_str()),
            (Some("world"), Some(same.scalar_name.as_str()))
        );
        assert!(got["meshes"].as_u64().unwrap() >= 3, "{got}");
        let info = &got["info"];
        assert!(info["service_name"].as_str().unwrap().starts_with("defvol/interfaces_"), "{info}");
        assert_eq!(info["dims"], serde_json::json!([256, 160, 122]));
        assert_eq!(info["direction"], serde_json::json!([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]));
        // Its load_scene call is answered: a broken scene is refused by name, the running one kept.
        assert_eq!(got["load_scene"]["success"], false);
        assert!(got["load_scene"]["message"].as_str().unwrap().contains("kept the running scene"), "{got}");
    });
}

#[test]
fn the_node_records_a_rosbag2_bag_directory_split_by_duration_that_rosbags_opens_whole() {
    isolated("the_node_records_a_rosbag2_bag_directory_split_by_duration_that_rosbags_opens_whole", || {
        if !python_has("rosbags.rosbag2") {
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let bag = dir.path().join("organ");
        let exit = Command::new(env!("CARGO_BIN_EXE_defvol_node"))
            .args(["--backend", "cpu", "--seconds", "7", "--max-bag-duration", "2", "--record"])
            .arg(&bag)
            .args(["--ros-args", "-r", "__ns:=/robot", "-p"])
            .arg(format!("scene_file:={}", scene().display()))
            .arg("-p")
            .arg(format!("warp.service:=defvol/bag_dir_{}", std::process::id()))
            .env("ROS_DOMAIN_ID", "17")
            .output()
            .unwrap();
        assert!(exit.status.success(), "{}", String::from_utf8_lossy(&exit.stderr));
        let metadata: serde_yaml_ng::Value =
            serde_yaml_ng::from_str(&std::fs::read_to_string(bag.join("metadata.yaml")).unwrap()).unwrap();
        let info = &metadata["rosbag2_bagfile_information"];
        let files = info["files"].as_sequence().unwrap();
        // Seven seconds of outputs in splits of two: three closed at 2, 4 and 6 s, and the last.
        assert_eq!(files.len(), 4, "{info:?}");
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/read_bag_dir.py");
        let out = Command::new("python3").arg(script).arg(&bag).output().unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
        let got: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
        let total = info["message_count"].as_u64().unwrap();
        let rosbags = &got["rosbags"];
        assert_eq!((rosbags["message_count"].as_u64(), rosbags["decoded"].as_u64()), (Some(total), Some(total)));
        let names: Vec<String> = (0..4).map(|i| format!("organ_{i}.mcap")).collect();
        assert_eq!(info["relative_file_paths"], serde_yaml_ng::to_value(&names).unwrap());
        for file in files {
            let (name, count) = (file["path"].as_str().unwrap(), file["message_count"].as_u64().unwrap());
            // Each split alone: Foxglove's reader and defvol's agree with metadata.yaml.
            assert_eq!(got["splits"][name].as_u64(), Some(count), "{name}");
            let ours = bag::read_messages(&bag.join(name), &[]).unwrap();
            assert_eq!(ours.len() as u64, count, "{name}");
            let span = ours.last().unwrap().log_time_ns - ours[0].log_time_ns;
            assert!(span < 2_000_000_000, "{name} spans {span} ns");
        }
        let topics = info["topics_with_message_count"].as_sequence().unwrap();
        for topic in topics {
            let name = topic["topic_metadata"]["name"].as_str().unwrap();
            assert_eq!(rosbags["topics"][name].as_u64(), topic["message_count"].as_u64(), "{name}");
        }
    });
}

/// Nanoseconds since the epoch.
fn now_ns() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as u64
}

#[test]
fn a_node_killed_at_random_leaves_closed_splits_whole_and_the_open_one_recoverable() {
    isolated("a_node_killed_at_random_leaves_closed_splits_whole_and_the_open_one_recoverable", || {
        if !python_has("rosbags.rosbag2") {
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let context = dds::context(17, Discovery::Localhost).unwrap();
        let mut peer = context.new_node(NodeName::new("/", "killer").unwrap(), NodeOptions::new()).unwrap();
        let poses = pose_publisher(&mut peer);
        // A fixed seed: "random" moments that a failure can be re-run with.
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let mut figures = Vec::new();
        for kill in 0..5 {
            seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            let alive = Duration::from_millis(2_500 + (seed >> 33) % 2_500);
            let bag = dir.path().join(format!("kill_{kill}"));
            let mut node = Command::new(env!("CARGO_BIN_EXE_defvol_node"))
                .args(["--backend", "cpu", "--seconds", "60", "--max-bag-duration", "1", "--flush-interval", "0.2"])
                .arg("--record")
                .arg(&bag)
                .args(["--ros-args", "-r", "__ns:=/robot", "-p"])
                .arg(format!("scene_file:={}", scene().display()))
                .arg("-p")
                .arg(format!("warp.service:=defvol/kill_{kill}_{}", std::process::id()))
                .env("ROS_DOMAIN_ID", "17")
                .stderr(std::process::Stdio::null())
                .spawn()
                .unwrap();
            // Poses at 200 Hz, well above the organ, from the recording's start until the kill.
            let waiting = Instant::now();
            while !bag.join("metadata.yaml").exists() {
                assert!(waiting.elapsed() < Duration::from_secs(30), "kill {kill}: the recording never started");
                std::thread::sleep(Duration::from_millis(10));
            }
            let start = Instant::now();
            while start.elapsed() < alive {
                poses.publish(pose_at(0.2)).unwrap();
                std::thread::sleep(Duration::from_millis(5));
            }
            node.kill().unwrap();
            let killed_at = now_ns();
            node.wait().unwrap();
            let metadata = |bag: &Path| -> serde_yaml_ng::Value {
                serde_yaml_ng::from_str(&std::fs::read_to_string(bag.join("metadata.yaml")).unwrap()).unwrap()
            };
            let closed: Vec<(String, Vec<u8>)> = metadata(&bag)["rosbag2_bagfile_information"]["relative_file_paths"]
                .as_sequence()
                .unwrap()
                .iter()
                .map(|p| p.as_str().unwrap().to_owned())
                .map(|p| (p.clone(), std::fs::read(bag.join(&p)).unwrap()))
                .collect();
            assert!(!closed.is_empty(), "kill {kill} after {alive:?}: no closed split");
            let recovering = Instant::now();
            let out = Command::new(env!("CARGO_BIN_EXE_defvol")).args(["bag", "recover"]).arg(&bag).output().unwrap();
            let recover_time = recovering.elapsed();
            assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
            for (name, bytes) in &closed {
                assert_eq!(&std::fs::read(bag.join(name)).unwrap(), bytes, "kill {kill}: {name} untouched");
            }
            // The standard readers open the whole bag, the rebuilt split too.
            let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/read_bag_dir.py");
            let read = Command::new("python3").arg(script).arg(&bag).output().unwrap();
            let text = String::from_utf8_lossy(&read.stdout);
            assert!(read.status.success(), "kill {kill}: {text}{}", String::from_utf8_lossy(&read.stderr));
            let got: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
            let info = metadata(&bag);
            let info = &info["rosbag2_bagfile_information"];
            assert_eq!(got["rosbags"]["message_count"].as_u64(), info["message_count"].as_u64(), "kill {kill}");
            assert_eq!(got["splits"].as_object().unwrap().len(), closed.len() + 1, "kill {kill}: {got}");
            // mcap's own Rust reader reads each split as metadata.yaml counts it.
            for file in info["files"].as_sequence().unwrap() {
                let bytes = std::fs::read(bag.join(file["path"].as_str().unwrap())).unwrap();
                let read =
                    mcap::MessageStream::new(&bytes).unwrap().collect::<Result<Vec<_>, _>>().unwrap().len() as u64;
                assert_eq!(Some(read), file["message_count"].as_u64(), "kill {kill}: {file:?}");
            }
            // What was lost: the poses after the last one recorded, at most the flush interval's.
            let recorded: Vec<u64> = info["files"]
                .as_sequence()
                .unwrap()
                .iter()
                .flat_map(|f| {
                    bag::read_messages(&bag.join(f["path"].as_str().unwrap()), &["/robot/tool_pose"]).unwrap()
                })
                .map(|m| m.log_time_ns)
                .collect();
            let last = recorded.iter().max().copied().unwrap();
            let lost_ns = killed_at.saturating_sub(last);
            assert!(lost_ns < 600_000_000, "kill {kill}: the last pose recorded {lost_ns} ns before the kill");
            figures.push((alive, recorded.len(), lost_ns / 5_000_000, recover_time));
        }
        for (alive, recorded, lost, recover_time) in figures {
            eprintln!("killed after {alive:?}: {recorded} poses recorded, ~{lost} lost (5 ms apart); recovered in {recover_time:?}");
        }
    });
}

#[test]
fn a_full_disk_stops_the_recording_once_and_the_node_publishes_on() {
    isolated("a_full_disk_stops_the_recording_once_and_the_node_publishes_on", || {
        let work = tempfile::tempdir().unwrap();
        let (disk, kept) = (work.path().join("disk"), work.path().join("kept"));
        std::fs::create_dir_all(&disk).unwrap();
        std::fs::create_dir_all(&kept).unwrap();
        // A 192 KiB tmpfs in a mount namespace of the node's own (gone with it, so what it
        // holds is copied out first), filled in a few seconds by 200 poses a second.
        let script = r#"disk=$1 node=$2 kept=$3; shift 3
mount -t tmpfs -o size=192k defvol-full "$disk" || exit 97
"$node" "$@"; status=$?
cp -r "$disk/." "$kept/"
exit $status"#;
        let context = dds::context(17, Discovery::Localhost).unwrap();
        let mut peer = context.new_node(NodeName::new("/", "watcher").unwrap(), NodeOptions::new()).unwrap();
        let t = peer
            .create_topic(
                &Name::parse("/robot/diagnostics").unwrap(),
                type_name::<DiagnosticArray>(),
                &qos(Qos::Reliable),
            )
            .unwrap();
        let diagnostics = peer.create_subscription::<DiagnosticArray>(&t, Some(qos(Qos::Reliable))).unwrap();
        let poses = pose_publisher(&mut peer);
        let node = Command::new("unshare")
            .args(["--mount", "sh", "-c", script, "sh"])
            .arg(&disk)
            .arg(env!("CARGO_BIN_EXE_defvol_node"))
            .arg(&kept)
            .args(["--backend", "cpu", "--seconds", "60", "--flush-interval", "0.1", "--record"])
            .arg(disk.join("full.mcap"))
            .args(["--ros-args", "-r", "__ns:=/robot", "-p"])
            .arg(format!("scene_file:={}", scene().display()))
            .arg("-p")
            .arg(format!("warp.service:=defvol/full_disk_{}", std::process::id()))
            .env("ROS_DOMAIN_ID", "17")
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let (mut before, mut after, mut reported) = (0, 0, Vec::new());
        // Until three diagnostics have come since the failure (or 40 s, and the test fails).
        let start = Instant::now();
        while after < 3 && start.elapsed() < Duration::from_secs(40) {
            poses.publish(pose_at(0.2)).unwrap();
            while let Ok(Some((m, _))) = diagnostics.take() {
                let failed = m.status.iter().find(|s| s.name == "defvol: recording");
                match failed {
                    Some(status) => {
                        reported.push(status.message.clone());
                        after += 1;
                    }
                    None if after == 0 => before += 1,
                    None => panic!("the recording's failure was reported, then forgotten"),
                }
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        // Ctrl-C to the node (the shell's child: unshare became the shell), then the shell
        // copies the disk out.
        let children = Command::new("pgrep").args(["-P", &node.id().to_string()]).output().unwrap();
        for pid in String::from_utf8_lossy(&children.stdout).split_whitespace() {
            Command::new("kill").args(["-INT", pid]).status().unwrap();
        }
        let exit = node.wait_with_output().unwrap();
        let log = String::from_utf8_lossy(&exit.stderr);
        assert!(exit.status.success(), "{log}");
        assert!(reported.iter().all(|m| m.contains("No space left on device")), "{reported:?}\n{log}");
        // One error in the log, naming the file and the cause; diagnostics before and after it.
        let errors: Vec<&str> = log.lines().filter(|l| l.contains("MCAP recording stopped")).collect();
        assert_eq!(errors.len(), 1, "{log}");
        assert!(errors[0].contains("full.mcap") && errors[0].contains("No space left on device"), "{}", errors[0]);
        // The node publishes on, each diagnostics saying the recording stopped.
        assert!(after >= 3, "diagnostics before the failure: {before}, after: {after}");
        // What was recorded before the disk filled is there, and whole once recovered.
        let bag_file = kept.join("full.mcap");
        let cut = bag::read_messages(&bag_file, &[]).unwrap();
        assert!(!cut.is_empty());
        let out = Command::new(env!("CARGO_BIN_EXE_defvol")).args(["bag", "recover"]).arg(&bag_file).output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let bytes = std::fs::read(&bag_file).unwrap();
        let read_by_mcap = mcap::MessageStream::new(&bytes).unwrap().count();
        assert_eq!(read_by_mcap, cut.len(), "mcap's own reader reads every message kept");
        if python_has("mcap_ros2.decoder") {
            let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/read_bag.py");
            let read = Command::new("python3").arg(script).arg(&bag_file).output().unwrap();
            assert!(read.status.success(), "{}", String::from_utf8_lossy(&read.stderr));
            let got: serde_json::Value = serde_json::from_str(String::from_utf8_lossy(&read.stdout).trim()).unwrap();
            let total: u64 = got["topics"].as_object().unwrap().values().map(|c| c.as_u64().unwrap()).sum();
            assert_eq!(total as usize, cut.len());
        }
    });
}

/// Two hosts on one machine: this test's network namespace and a second one joined to it by
/// a veth pair (192.0.2.0/24, a documentation range; both made here and gone with the test).
/// With default settings the node puts no RTPS datagram on the link (counted by a raw
/// capture on the far end) and a Cyclone DDS peer there hears nothing; with `ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET` its discovery
/// reaches the other host (the same capture, the positive control), and a Cyclone DDS peer
/// there, bound to its end of the link, exchanges poses and feedback with the node.
#[test]
fn dds_stays_off_a_second_host_by_default_and_reaches_it_when_opened() {
    let Some(other) = OtherHost::for_test("dds_stays_off_a_second_host_by_default_and_reaches_it_when_opened") else {
        return;
    };
    let its = other.ns.clone();
    let capture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/rtps_capture.py");
    let mut counted = Vec::new();
    let mut peers = Vec::new();
    for open in [false, true] {
        let mut listener = Command::new("nsenter")
            .arg(format!("--net={its}"))
            .arg("python3")
            .arg(&capture)
            .args(["dv1", "5"])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        // The capture is bound once it says so.
        let mut ready = String::new();
        std::io::BufRead::read_line(&mut std::io::BufReader::new(listener.stderr.as_mut().unwrap()), &mut ready)
            .unwrap();
        assert_eq!(ready.trim(), "ready");
        let dir = tempfile::tempdir().unwrap();
        let mut node = Command::new(env!("CARGO_BIN_EXE_defvol_node"));
        let seconds = "12";
        node.args(["--backend", "cpu", "--seconds", seconds, "--ros-args", "-r", "__ns:=/robot", "-p"])
            .arg(format!("scene_file:={}", scene().display()))
            .arg("-p")
            .arg(format!("warp.service:=defvol/two_hosts_{open}_{}", std::process::id()))
            .env("ROS_DOMAIN_ID", "17")
            .env_remove("ROS_DISTRO")
            .current_dir(dir.path());
        if open {
            node.env("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET");
        }
        let node = node.stderr(std::process::Stdio::piped()).spawn().unwrap();
        if python_has("cyclonedds.domain") {
            peers.push(cyclone_peer_at(&its, "dv1"));
        }
        let out = node.wait_with_output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let seen = listener.wait_with_output().unwrap();
        let text = String::from_utf8_lossy(&seen.stdout);
        assert!(seen.status.success(), "{text}");
        counted.push(serde_json::from_str::<serde_json::Value>(text.lines().last().unwrap()).unwrap());
    }
    drop(other);
    let (closed, opened) = (&counted[0], &counted[1]);
    // Counted from the node's host (the peer's own discovery goes out from the other end).
    let from_node = |seen: &serde_json::Value| seen["sources"]["192.0.2.1"].as_u64().unwrap_or(0);
    assert_eq!(from_node(closed), 0, "RTPS from the node on the link by default: {closed}");
    assert!(from_node(opened) > 0, "opened, discovery reaches the other host: {opened}");
    eprintln!(
        "RTPS datagrams from the node on the link: {} by default, {} opened",
        from_node(closed),
        from_node(opened)
    );
    if let [closed, opened] = &peers[..] {
        let heard = |got: &serde_json::Value| got["feedback"].as_u64().unwrap() + got["meshes"].as_u64().unwrap();
        assert_eq!(heard(closed), 0, "by default the peer on the other host hears nothing: {closed}");
        assert!(opened["feedback"].as_u64().unwrap() > 0 && opened["meshes"].as_u64().unwrap() > 0, "{opened}");
        assert!(opened["max_force_z"].as_f64().unwrap() > 1.0, "its poses reached the solver: {opened}");
        eprintln!("the peer on the other host: {closed} by default, {opened} opened");
    }
}

/// A Cyclone DDS configuration (`CYCLONEDDS_URI`) for domain 17 on `interface` alone.
fn cyclone_bound_to(interface: &str) -> String {
    format!(
        "<CycloneDDS><Domain id=\"17\"><General><Interfaces><NetworkInterface name=\"{interface}\"/></Interfaces></General></Domain></CycloneDDS>"
    )
}

/// A second host on this machine: a network namespace held by a process of its own, joined
/// to this test's namespace by a veth pair (this end dv0, 192.0.2.1; its end dv1, 192.0.2.2;
/// 192.0.2.0/24 is a documentation range). Gone with the value.
struct OtherHost {
    holder: Child,
    /// Its network namespace, for `nsenter --net=`.
    ns: String,
}

impl OtherHost {
    /// The other host of the test `name`, which always runs in a namespace of its own (the
    /// veth and its routes must not meet other tests): none where this process only re-ran
    /// the test there.
    fn for_test(name: &str) -> Option<OtherHost> {
        if std::env::var_os("DEFVOL_NETNS_RERUN").is_none() {
            rerun_in_a_namespace_of_its_own(name);
            return None;
        }
        assert!(dds::private_network(), "the first host must be a private network namespace");
        Some(OtherHost::join())
    }

    fn join() -> OtherHost {
        let shell = |script: &str| {
            let out = Command::new("sh").args(["-c", script]).output().unwrap();
            assert!(out.status.success(), "{script}: {}", String::from_utf8_lossy(&out.stderr));
        };
        let holder = Command::new("unshare").args(["--net", "sleep", "300"]).spawn().unwrap();
        let own = std::fs::read_link("/proc/self/ns/net").unwrap();
        let ns = format!("/proc/{}/ns/net", holder.id());
        let deadline = Instant::now() + Duration::from_secs(10);
        while std::fs::read_link(&ns).map_or(true, |its| its == own) {
            assert!(Instant::now() < deadline, "the second namespace never came");
            std::thread::sleep(Duration::from_millis(10));
        }
        shell(&format!(
            "ip link add dv0 type veth peer name dv1 netns {} && ip addr add 192.0.2.1/24 dev dv0 && ip link set dv0 up",
            holder.id()
        ));
        shell(&format!(
            "nsenter --net={ns} sh -c 'ip link set lo up && ip addr add 192.0.2.2/24 dev dv1 && ip link set dv1 up \\
             && ip route add 224.0.0.0/4 dev dv1'"
        ));
        OtherHost { holder, ns }
    }
}

impl Drop for OtherHost {
    fn drop(&mut self) {
        let _ = self.holder.kill();
        let _ = self.holder.wait();
    }
}

/// Runs tests/interop/cyclone_peer.py for 8 s in the network namespace `ns`, Cyclone DDS
/// bound to `interface`, under the node's namespace /robot; what it received.
fn cyclone_peer_at(ns: &str, interface: &str) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/cyclone_peer.py");
    let uri = cyclone_bound_to(interface);
    let out = Command::new("nsenter")
        .arg(format!("--net={ns}"))
        .arg("python3")
        .arg(script)
        .args(["8", "/robot"])
        .env("ROS_DOMAIN_ID", "17")
        .env("CYCLONEDDS_URI", uri)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_str(text.lines().last().unwrap()).unwrap()
}

/// A /dev/shm too small for the warped volumes (a 1 MiB tmpfs in a private mount namespace,
/// the network one private too): the node names the room there and the room needed, and
/// runs on without shared volumes: meshes, images and `warped_volume/info` still come.
#[test]
fn a_node_with_a_tiny_dev_shm_names_the_room_and_runs_on_without_shared_volumes() {
    let name = "node_dds::a_node_with_a_tiny_dev_shm_names_the_room_and_runs_on_without_shared_volumes";
    let netns_run = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/netns-run");
    if crate::rerun_under_tiny_dev_shm(name, Some(&netns_run)) {
        return;
    }
    assert!(dds::private_network(), "the node must run in a private network namespace");
    let dir = tempfile::tempdir().unwrap();
    let out = start_node(dir.path(), 4, "tiny_shm").wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{log}");
    assert!(log.contains("/dev/shm has 1.0 MiB free") && log.contains("MiB (raise the size of /dev/shm"), "{log}");
    let count = |topic: &str| bag::read_messages(&dir.path().join("node.mcap"), &[topic]).unwrap().len();
    for topic in ["/robot/warped_volume/info", "/robot/deformed_mesh", "/robot/raycast/image"] {
        assert!(count(topic) > 0, "no {topic} without shared volumes:\n{log}");
    }
}

/// SIGTERM (what docker, systemd and `ros2 launch` send) shuts a recording node down as
/// Ctrl-C does: the log says so, the process exits cleanly, and the bag opens in
/// Foxglove's reader (which refuses an unfinished one) with no `bag recover`.
#[test]
fn sigterm_finalises_the_recording_as_ctrl_c_does() {
    isolated("sigterm_finalises_the_recording_as_ctrl_c_does", || {
        let dir = tempfile::tempdir().unwrap();
        let node = start_node(dir.path(), 60, "sigterm");
        let bag_file = dir.path().join("node.mcap");
        // Until the recording holds something (or 30 s).
        let start = Instant::now();
        while std::fs::metadata(&bag_file).map_or(0, |m| m.len()) < 4096 && start.elapsed() < Duration::from_secs(30) {
            std::thread::sleep(Duration::from_millis(100));
        }
        std::thread::sleep(Duration::from_millis(500));
        Command::new("kill").args(["-TERM", &node.id().to_string()]).status().unwrap();
        let exit = node.wait_with_output().unwrap();
        let log = String::from_utf8_lossy(&exit.stderr);
        assert!(exit.status.success(), "{log}");
        assert!(log.contains("stop signal (SIGINT, SIGTERM or SIGHUP): shutting down"), "{log}");
        let bytes = std::fs::read(&bag_file).unwrap();
        let messages = mcap::MessageStream::new(&bytes).unwrap().count();
        assert!(messages > 0, "the bag holds {messages} messages");
        if python_has("mcap_ros2.decoder") {
            let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/read_bag.py");
            let read = Command::new("python3").arg(script).arg(&bag_file).output().unwrap();
            assert!(read.status.success(), "Foxglove's reader: {}", String::from_utf8_lossy(&read.stderr));
            let got: serde_json::Value = serde_json::from_str(String::from_utf8_lossy(&read.stdout).trim()).unwrap();
            let total: u64 = got["topics"].as_object().unwrap().values().map(|c| c.as_u64().unwrap()).sum();
            assert_eq!(total as usize, messages, "{got}");
        }
    });
}

/// A `-p` value outside its descriptor's range is refused in rclcpp's words before anything
/// is built: no recording is started, no participant made, and the error is one line.
#[test]
fn a_bad_command_line_parameter_is_refused_before_anything_is_built() {
    isolated("a_bad_command_line_parameter_is_refused_before_anything_is_built", || {
        let dir = tempfile::tempdir().unwrap();
        for (parameter, said) in [
            ("solver.dt:=10", "parameter 'solver.dt' could not be set: Parameter {solver.dt} doesn't comply with floating point range [0.000001, 0.1]"),
            ("camera.width:=0", "parameter 'camera.width' could not be set: Parameter {camera.width} doesn't comply with integer range [1, 16384]"),
        ] {
            let out = Command::new(env!("CARGO_BIN_EXE_defvol_node"))
                .args(["--backend", "cpu", "--record"])
                .arg(dir.path().join("never.mcap"))
                .args(["--ros-args", "-p", parameter])
                .env("ROS_DOMAIN_ID", "17")
                .env("RUST_LOG", "info")
                .output()
                .unwrap();
            let log = String::from_utf8_lossy(&out.stderr);
            assert!(!out.status.success(), "{parameter}: {log}");
            assert!(log.trim_end().ends_with(said) && !log.contains("up: tools on"), "{parameter}: {log}");
            assert!(!dir.path().join("never.mcap").exists(), "{parameter}: a recording was started");
        }
    });
}

/// A subscriber that joins `deformed_mesh` and `surface_marker` while the node is paused
/// (RViz opened after the node, the organ at rest) gets the current state at once from the
/// publishers' durable history (transient local, depth 1), as `robot_description` and maps
/// serve late joiners; nothing new is published while paused.
#[test]
fn a_late_joiner_gets_the_organ_as_it_rests() {
    isolated("a_late_joiner_gets_the_organ_as_it_rests", || {
        let dir = tempfile::tempdir().unwrap();
        let node_process = start_node(dir.path(), 12, "late_joiner");
        let context = dds::context(17, Discovery::Localhost).unwrap();
        let mut peer = context.new_node(NodeName::new("/", "late").unwrap(), NodeOptions::new()).unwrap();
        let poses = pose_publisher(&mut peer);
        let pause = pause_client(&mut peer);
        // Touch the organ for three seconds, then pause the node.
        let start = Instant::now();
        let mut paused = None;
        let mut sent = 0;
        while paused.is_none() && start.elapsed() < Duration::from_secs(8) {
            poses.publish(pose_at(0.08)).unwrap();
            if start.elapsed() > Duration::from_secs(3) {
                match pause.receive_response() {
                    Ok(Some((_, reply))) => paused = Some(reply),
                    _ if sent % 50 == 0 => drop(pause.send_request(TriggerRequest::default())),
                    _ => {}
                }
            }
            sent += 1;
            std::thread::sleep(Duration::from_millis(10));
        }
        assert!(paused.is_some_and(|r: TriggerResponse| r.success), "the node did not pause");
        std::thread::sleep(Duration::from_secs(1));
        // Now join, as a viewer opened late would (asking for the durable history).
        let latched =
            |topic: &str, ty| peer.create_topic(&Name::parse(topic).unwrap(), ty, &qos(Qos::Latched)).unwrap();
        let mesh_topic = latched("/robot/deformed_mesh", type_name::<DeformedMesh>());
        let marker_topic = latched("/robot/surface_marker", type_name::<Marker>());
        let meshes = peer.create_subscription::<DeformedMesh>(&mesh_topic, Some(qos(Qos::Latched))).unwrap();
        let markers = peer.create_subscription::<Marker>(&marker_topic, Some(qos(Qos::Latched))).unwrap();
        let (mut got_mesh, mut got_marker) = (0, 0);
        let joined = Instant::now();
        while (got_mesh == 0 || got_marker == 0) && joined.elapsed() < Duration::from_secs(3) {
            while let Ok(Some((m, _))) = meshes.take() {
                assert!(!m.positions.is_empty());
                got_mesh += 1;
            }
            while let Ok(Some(_)) = markers.take() {
                got_marker += 1;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let exit = node_process.wait_with_output().unwrap();
        assert!(exit.status.success(), "{}", String::from_utf8_lossy(&exit.stderr));
        // (A step already under way when the pause came may publish one more mesh.)
        assert!(got_mesh >= 1 && got_marker >= 1, "the late joiner got {got_mesh} meshes, {got_marker} markers");
    });
}

/// What a remote participant names is read only inside the allowed directories (by default
/// the start scene's folder): rclpy setting `scene_file` as `ros2 param set` does, and a
/// `load_scene` client, naming a file with a known secret line by its path, by `..` from an
/// allowed folder, through a symlink, and as a scene's volume; a device and a FIFO. Each
/// refusal says why, and no answer, log line, `/diagnostics` or `/rosout` message, nor the
/// recording, holds a byte of the secret; a scene inside the allowed folder still loads.
#[test]
fn nothing_outside_the_allowed_directories_reaches_a_caller() {
    isolated("nothing_outside_the_allowed_directories_reaches_a_caller", || {
        if !python_has("rclpy") {
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let (allowed, outside) = (dir.path().join("allowed"), dir.path().join("outside"));
        std::fs::create_dir_all(&allowed).unwrap();
        std::fs::create_dir_all(&outside).unwrap();
        const SECRET: &str = "k7Qz9-secret";
        let secret = outside.join("shadow");
        std::fs::write(&secret, format!("root:{SECRET}:20228:0:99999:7:::\ndaemon:*:20228:0:99999:7:::\n")).unwrap();
        let scene_text = std::fs::read_to_string(scene()).unwrap();
        std::fs::write(allowed.join("scene.yaml"), &scene_text).unwrap();
        std::fs::write(allowed.join("other.yaml"), scene_text.replace("target_tets: 600", "target_tets: 400")).unwrap();
        std::os::unix::fs::symlink(&secret, allowed.join("link.yaml")).unwrap();
        let fifo = allowed.join("fifo.yaml");
        assert!(Command::new("mkfifo").arg(&fifo).status().unwrap().success());
        let node_process = Command::new(env!("CARGO_BIN_EXE_defvol_node"))
            .args(["--backend", "cpu", "--seconds", "30", "--record"])
            .arg(dir.path().join("node.mcap"))
            .args(["--ros-args", "-r", "__ns:=/robot", "-p"])
            .arg(format!("scene_file:={}", allowed.join("scene.yaml").display()))
            .arg("-p")
            .arg(format!("warp.service:=defvol/files_{}", std::process::id()))
            .env("ROS_DOMAIN_ID", "17")
            .env("RUST_LOG", "info")
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let show = |p: &Path| p.display().to_string();
        let up = format!("{}/../outside/shadow", allowed.display());
        let refused = [
            (show(&secret), "outside the allowed directories"),
            (up.clone(), "outside the allowed directories"),
            (show(&allowed.join("link.yaml")), "outside the allowed directories"),
            ("/dev/zero".to_owned(), "outside the allowed directories"),
            (show(&fifo), "unsupported: a FIFO, where a regular file is expected"),
        ];
        let good = show(&allowed.join("other.yaml"));
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/rclpy_files.py");
        let out = Command::new("python3")
            .arg(script)
            .arg("/robot/defvol")
            .args(refused.iter().map(|(path, _)| path))
            .arg(&good)
            .env("ROS_DOMAIN_ID", "17")
            .output()
            .unwrap();
        let said = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(out.status.success(), "{said}{}", String::from_utf8_lossy(&out.stderr));
        let got: serde_json::Value = serde_json::from_str(said.lines().last().unwrap()).unwrap();
        for (path, why) in &refused {
            let answer = &got["answers"][path];
            assert_eq!(answer["successful"], false, "{path}: {answer}");
            assert!(answer["reason"].as_str().unwrap().contains(why), "{path}: {answer}");
        }
        assert_eq!(got["answers"][&good]["successful"], true, "{got}");
        assert!(got["heard"].as_array().is_some_and(|heard| !heard.is_empty()), "rclpy heard the node: {got}");
        // load_scene: by path, and as YAML text naming the secret as its volume.
        let context = dds::context(17, Discovery::Localhost).unwrap();
        let mut peer = context.new_node(NodeName::new("/", "files").unwrap(), NodeOptions::new()).unwrap();
        let client = service_client::<LoadSceneRequest, TriggerResponse>(
            &mut peer,
            "/robot/load_scene",
            "defvol_interfaces",
            "LoadScene",
        );
        let as_volume = scene_text.replace("volume: phantom", &format!("volume: {}", secret.display()));
        let requests = [
            (show(&secret), "outside the allowed directories"),
            (up, "outside the allowed directories"),
            (as_volume, "volume: "),
            (show(&allowed.join("scene.yaml")), "scene loaded"),
        ];
        let mut answers = String::new();
        for (scene, why) in &requests {
            let reply = call(&client, LoadSceneRequest { scene: scene.clone() });
            assert_eq!(reply.success, *why == "scene loaded", "{scene}: {reply:?}");
            assert!(reply.message.contains(why), "{scene}: {reply:?}");
            answers += &reply.message;
        }
        let exit = node_process.wait_with_output().unwrap();
        let log = String::from_utf8_lossy(&exit.stderr);
        assert!(exit.status.success(), "{log}");
        let recording = std::fs::read(dir.path().join("node.mcap")).unwrap();
        let in_recording = recording.windows(SECRET.len()).any(|w| w == SECRET.as_bytes());
        for (what, text) in [("rclpy", said.as_str()), ("load_scene", &answers), ("the node's log", &log)] {
            assert!(!text.contains(SECRET) && !text.contains("20228"), "{what} holds the secret: {text}");
        }
        assert!(!in_recording, "the recording holds the secret");
    });
}

/// The reply to one request, sent again each second until one comes (discovery takes a while).
fn call<Q: ros2_client::Message + Clone + 'static, A: ros2_client::Message + 'static>(
    client: &ros2_client::Client<Q, A>,
    request: Q,
) -> A {
    let start = Instant::now();
    let mut sent_at = None::<Instant>;
    let mut sent = Vec::new();
    while start.elapsed() < Duration::from_secs(15) {
        if sent_at.is_none_or(|t| t.elapsed() > Duration::from_secs(1)) {
            sent.extend(client.send_request(request.clone()));
            sent_at = Some(Instant::now());
        }
        // Only a reply to this call's requests: an earlier call's late one is not this one's.
        if let Ok(Some((id, reply))) = client.receive_response() {
            if sent.contains(&id) {
                return reply;
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    panic!("no reply in 15 s");
}

/// Images and meshes reach viewers on the two DDS implementations ROS 2 users run, with every
/// socket's buffer at the kernel's default: rclpy on Fast DDS (Jazzy's default middleware,
/// as RViz and rqt_image_view are) and Eclipse Cyclone DDS, counted against what the node
/// recorded while they listened (docs/perf/journal.md). RustDDS paces a large sample's
/// datagrams (vendor/README.md); before that, Fast DDS received 0 of 72 raycasts.
#[test]
fn images_reach_fast_dds_and_cyclone_dds_viewers_on_this_host() {
    isolated("images_reach_fast_dds_and_cyclone_dds_viewers_on_this_host", || {
        for viewer in [Viewer::Cyclone, Viewer::Rclpy] {
            if viewer.available() {
                let (delivery, warned) = image_delivery(viewer, None);
                assert_delivered(viewer, "this host", &delivery);
                let rmem_default: usize =
                    std::fs::read_to_string("/proc/sys/net/core/rmem_default").unwrap().trim().parse().unwrap();
                assert_eq!(warned, rmem_default < 130 * 1024, "the node warns only where a paced burst overflows");
            }
        }
    });
}

/// The same across a veth pair to a second host (path MTU 1,500 bytes: a raycast is about
/// 240 datagrams), the node's discovery opened to the subnet.
#[test]
fn images_reach_fast_dds_and_cyclone_dds_viewers_on_another_host() {
    let Some(other) = OtherHost::for_test("images_reach_fast_dds_and_cyclone_dds_viewers_on_another_host") else {
        return;
    };
    for viewer in [Viewer::Cyclone, Viewer::Rclpy] {
        if viewer.available() {
            let (delivery, _) = image_delivery(viewer, Some(&other));
            assert_delivered(viewer, "another host", &delivery);
        }
    }
}

/// At least 95 % of the images published while the viewer listened, and 90 % on each topic
/// (a DPCM topic has about 11 in the window: one loss is 9 %).
fn assert_delivered(viewer: Viewer, host: &str, delivery: &[(String, usize, usize)]) {
    eprintln!("{viewer:?} on {host} (topic, received, published): {delivery:?}");
    for (topic, received, published) in delivery {
        assert!(*published >= 5, "{viewer:?}, {topic}: {published} published while it listened");
        assert!(
            *received as f64 >= 0.9 * *published as f64,
            "{viewer:?} on {host}, {topic}: {received} of {published}"
        );
    }
    let images = delivery.iter().filter(|(topic, ..)| topic != "deformed_mesh");
    let (received, published) = images.fold((0, 0), |(r, p), (_, received, published)| (r + received, p + published));
    assert!(received as f64 >= 0.95 * published as f64, "{viewer:?} on {host}: {received} of {published} images");
}

/// A subscriber to the node's images: ROS 2's rclpy on Fast DDS or Eclipse Cyclone DDS.
#[derive(Clone, Copy, Debug)]
enum Viewer {
    Rclpy,
    Cyclone,
}

impl Viewer {
    fn available(self) -> bool {
        python_has(match self {
            Viewer::Rclpy => "rclpy",
            Viewer::Cyclone => "cyclonedds.domain",
        })
    }

    /// Its script listening 15 s under /robot, on `other` host if given.
    fn command(self, other: Option<&OtherHost>) -> Command {
        let script = match self {
            Viewer::Rclpy => "tests/interop/rclpy_images.py",
            Viewer::Cyclone => "tests/interop/cyclone_images.py",
        };
        let mut command = match other {
            Some(host) => {
                let mut command = Command::new("nsenter");
                command.arg(format!("--net={}", host.ns)).arg("python3");
                command
            }
            None => Command::new("python3"),
        };
        command.arg(Path::new(env!("CARGO_MANIFEST_DIR")).join(script)).args(["15", "/robot"]);
        command.env("ROS_DOMAIN_ID", "17");
        if let (Viewer::Cyclone, Some(_)) = (self, other) {
            command.env("CYCLONEDDS_URI", cyclone_bound_to("dv1"));
        }
        command
    }
}

/// `(topic, received, published while the viewer listened)` for each topic `viewer` counts
/// (the default scene's images with raycast and DPCM on: a 320x240 rgba8 raycast, 256x256
/// DPCM images; Cyclone DDS its meshes too), on `other` host if given; and whether the node
/// warned of the receive buffer.
fn image_delivery(viewer: Viewer, other: Option<&OtherHost>) -> (Vec<(String, usize, usize)>, bool) {
    let dir = tempfile::tempdir().unwrap();
    let subscriber = viewer
        .command(other)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut node = Command::new(env!("CARGO_BIN_EXE_defvol_node"));
    node.args(["--backend", "cpu", "--seconds", "12", "--record"])
        .arg(dir.path().join("node.mcap"))
        .args(["--ros-args", "-r", "__ns:=/robot", "-p", "stages.raycast:=true", "-p", "stages.dpcm:=true", "-p"])
        .arg(format!("warp.service:=defvol/images_{viewer:?}_{}", std::process::id()))
        .env("ROS_DOMAIN_ID", "17")
        .env("RUST_LOG", "warn");
    if other.is_some() {
        node.env("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET");
    }
    let exit = node.stderr(std::process::Stdio::piped()).spawn().unwrap().wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&exit.stderr);
    assert!(exit.status.success(), "{log}");
    let out = subscriber.wait_with_output().unwrap();
    assert!(out.status.success(), "{viewer:?}: {}", String::from_utf8_lossy(&out.stderr));
    let got: serde_json::Map<String, serde_json::Value> = serde_json::from_slice(&out.stdout).unwrap();
    let received: Vec<(String, Vec<u64>)> = got
        .into_iter()
        .map(|(topic, stamps)| (topic, stamps.as_array().unwrap().iter().map(|s| s.as_u64().unwrap()).collect()))
        .collect();
    // Published while the subscriber listened: from the first sample of the topic it got to
    // the last (of any topic, where it got fewer than two of this one).
    let window = |stamps: &[u64]| stamps.iter().min().copied().unwrap_or(0)..=stamps.iter().max().copied().unwrap_or(0);
    let all = window(&received.iter().flat_map(|(_, stamps)| stamps.clone()).collect::<Vec<_>>());
    let delivery = received.into_iter().map(|(topic, received)| {
        let recorded = bag::read_messages(&dir.path().join("node.mcap"), &[&format!("/robot/{topic}")]).unwrap();
        let stamp = |data: &[u8]| match topic.as_str() {
            "deformed_mesh" => msgs::decode::<DeformedMesh>(data, &topic).unwrap().header.stamp,
            _ => msgs::decode::<Image>(data, &topic).unwrap().header.stamp,
        };
        let listened = if received.len() >= 2 { window(&received) } else { all.clone() };
        let published = recorded.iter().filter(|m| listened.contains(&stamp(&m.data).as_nanos())).count();
        (topic, received.len(), published)
    });
    (delivery.collect(), log.contains("exceed what a subscriber's default socket receive buffer takes"))
}

/// A parameter rebuilds only what it touches while a device drives a coupled tool at about
/// 500 Hz: `camera.width` set live rebuilds the camera, the next images are wider, the
/// solver's step counter never goes back and every pose is still answered; `solver.dt`
/// restarts the simulation from rest, and the log says why. The longest pause in the
/// feedback around each change is reported (docs/perf/journal.md).
#[test]
fn a_live_camera_change_leaves_the_simulation_and_the_force_loop_running() {
    isolated("a_live_camera_change_leaves_the_simulation_and_the_force_loop_running", || {
        let dir = tempfile::tempdir().unwrap();
        let scene = coupled_scene(dir.path(), true);
        let node_process = start_node_on(&scene, dir.path(), 14, "live_camera");
        let context = dds::context(17, Discovery::Localhost).unwrap();
        let mut peer = context.new_node(NodeName::new("/", "device").unwrap(), NodeOptions::new()).unwrap();
        let feedback_name = Name::parse("/robot/tool_feedback").unwrap();
        let feedback_topic = peer.create_topic(&feedback_name, type_name::<WrenchStamped>(), &qos(Qos::SensorData));
        let feedback =
            peer.create_subscription::<WrenchStamped>(&feedback_topic.unwrap(), Some(qos(Qos::SensorData))).unwrap();
        let poses = pose_publisher(&mut peer);
        let reset = service_client::<TriggerRequest, TriggerResponse>(&mut peer, "/robot/reset", "std_srvs", "Trigger");
        let set_parameters = service_client::<SetParametersRequest, SetParametersResponse>(
            &mut peer,
            "/robot/defvol/set_parameters",
            "rcl_interfaces",
            "SetParameters",
        );
        let get_parameters = service_client::<GetParametersRequest, GetParametersResponse>(
            &mut peer,
            "/robot/defvol/get_parameters",
            "rcl_interfaces",
            "GetParameters",
        );
        let set =
            |name: &str, value| SetParametersRequest { parameter: vec![Parameter { name: name.into(), value }.into()] };
        let changes = [
            (4.0, set("camera.width", ParameterValue::Integer(96))),
            (8.0, set("solver.dt", ParameterValue::Double(0.005))),
        ];
        let (mut answers, mut replies, mut pending) = (Vec::new(), Vec::new(), None);
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(10) {
            let s = (start.elapsed().as_secs_f64() / 2.0).min(1.0);
            poses.publish(pose_at(0.072 - 0.014 * s)).unwrap();
            while let Ok(Some((_, _))) = feedback.take() {
                answers.push(start.elapsed().as_secs_f64());
            }
            let due = changes.iter().filter(|(at, _)| start.elapsed().as_secs_f64() >= *at).count();
            if replies.len() < due && pending.is_none() {
                let asked = start.elapsed().as_secs_f64();
                pending = set_parameters.send_request(changes[replies.len()].1.clone()).ok().map(|id| (id, asked));
            }
            if let (Ok(Some((id, reply))), Some((sent, asked))) = (set_parameters.receive_response(), pending) {
                if id == sent {
                    replies.push((asked, start.elapsed().as_secs_f64(), reply));
                    pending = None;
                }
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        // `reset`, timed from the request to its reply (which comes once the reset is done).
        let asked = Instant::now();
        let reply = call(&reset, TriggerRequest::default());
        eprintln!("reset answered in {:.1} ms", asked.elapsed().as_secs_f64() * 1e3);
        assert!(reply.success, "{reply:?}");
        // A volume that passes the checks but does not read (the scene file itself) is
        // refused once the loop tried it, and set back: the parameter tells the value in force.
        let not_a_volume = ParameterValue::String(scene.display().to_string());
        let reply = call(&set_parameters, set("volume", not_a_volume));
        assert!(!reply.results[0].successful, "{reply:?}");
        assert!(reply.results[0].reason.ends_with("the running scene is kept"), "{reply:?}");
        let request = GetParametersRequest { names: vec!["volume".into()] };
        let got = call(&get_parameters, request).values.into_iter().map(ParameterValue::from).collect::<Vec<_>>();
        assert_eq!(got, [ParameterValue::String("phantom".into())]);
        let exit = node_process.wait_with_output().unwrap();
        let log = String::from_utf8_lossy(&exit.stderr);
        assert!(exit.status.success(), "{log}");
        assert_eq!(replies.len(), 2, "both sets answered: {replies:?}");
        for (asked, answered, reply) in &replies {
            assert!(reply.results.iter().all(|r| r.successful), "{reply:?}");
            // The longest pause of the feedback from a second before the set to a second after.
            let around: Vec<f64> =
                answers.iter().copied().filter(|t| (asked - 1.0..answered + 1.0).contains(t)).collect();
            let pause = around.windows(2).map(|w| w[1] - w[0]).fold(0.0, f64::max);
            eprintln!(
                "set at {asked:.3} s, answered in {:.1} ms; {} answers around it, longest pause {:.1} ms",
                (answered - asked) * 1e3,
                around.len(),
                pause * 1e3
            );
            assert!(around.len() > 200, "the force loop answered on: {} answers", around.len());
        }
        assert!(log.contains("parameter camera.width set: its stages rebuilt, the simulation running on"), "{log}");
        assert!(log.contains("the simulation restarted from rest: solver changed"), "{log}");
        assert!(log.contains("kept the running scene and set the parameter back"), "{log}");
        // The step counter goes back twice: at the solver's change and the reset, not the
        // camera's.
        let recorded =
            bag::read_messages(&dir.path().join("node.mcap"), &["/robot/deformed_mesh", "/robot/raycast/image"])
                .unwrap();
        let steps: Vec<u64> = recorded
            .iter()
            .filter(|m| m.topic.ends_with("deformed_mesh"))
            .map(|m| msgs::decode::<DeformedMesh>(&m.data, "mesh").unwrap().step)
            .collect();
        assert_eq!(steps.windows(2).filter(|w| w[1] < w[0]).count(), 2, "{steps:?}");
        let widths: Vec<u32> = recorded
            .iter()
            .filter(|m| m.topic.ends_with("image"))
            .map(|m| msgs::decode::<Image>(&m.data, "image").unwrap().width)
            .collect();
        assert!(widths.first() == Some(&64) && widths.last() == Some(&96), "{widths:?}");
    });
}
