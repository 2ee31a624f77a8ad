//! The warped volume reaches a subscriber in another language: iceoryx2's Python binding
//! reads the header and the samples the node's publisher wrote into shared memory.
#![cfg(feature = "shm")]

use std::path::Path;
use std::process::Command;

use defvol::msgs::Time;
use defvol::shm::WarpedVolumePublisher;
use defvol::volume::Grid;

#[test]
fn a_python_iceoryx2_subscriber_receives_the_warped_volume() {
    let have = Command::new("python3").args(["-c", "import iceoryx2"]).output().is_ok_and(|o| o.status.success());
    if !have {
        assert!(std::env::var_os("DEFVOL_REQUIRE_INTEROP").is_none(), "python3 iceoryx2 is missing (tests/run.sh installs it)");
        eprintln!("skipped: python3 iceoryx2 is not installed");
        return;
    }
    let grid = Grid { dims: [64, 40, 30], spacing: [1.0, 1.0, 1.5], origin: [-32.0, -20.0, -22.0], direction: nalgebra::Matrix3::identity() };
    let data: Vec<f32> = (0..64 * 40 * 30).map(|i| (i % 977) as f32 * 0.5).collect();
    let service = format!("defvol/test_python_{}", std::process::id());
    let mut publisher = WarpedVolumePublisher::new(&service, &grid).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/shm_subscriber.py");
    let mut child = Command::new("python3").arg(script).arg(&service).stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped()).spawn().unwrap();
    // Volumes keep coming, as from the node, until the subscriber has one.
    while child.try_wait().unwrap().is_none() {
        publisher.publish(&grid, &data, 42, Time { sec: 5, nanosec: 6 }).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
    let got: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
    assert_eq!(got["sequence"], 42);
    assert_eq!(got["dims"], serde_json::json!([64, 40, 30]));
    assert_eq!(got["spacing"], serde_json::json!([1.0, 1.0, 1.5]));
    assert_eq!(got["origin"], serde_json::json!([-32.0, -20.0, -22.0]));
    assert_eq!(got["elements"].as_u64().unwrap() as usize, data.len());
    let sum: f64 = data.iter().map(|v| f64::from(*v)).sum();
    assert!((got["sum"].as_f64().unwrap() - sum).abs() < 1e-6 * sum, "{} vs {sum}", got["sum"]);
    assert_eq!((got["first"].as_f64().unwrap() as f32, got["last"].as_f64().unwrap() as f32), (data[0], data[data.len() - 1]));
}
