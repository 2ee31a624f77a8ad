//! Marker sources (the seed's UDP frames, motion files, tool poses) and renderings.

use std::io::Write;
use std::net::UdpSocket;
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Point3, Vector3};

use defvol::dpcm::markers::{Calibration, FrameParser, MotionFile, UdpFrame, UdpSource, FRAME_FLAG};
use defvol::dpcm::render::{self, RenderConfig};
use defvol::dpcm::{DpcmConfig, ParamTexture, Surface, TexturedParameter};

fn frame(number: u32, markers: &[(u32, f32, f32)]) -> UdpFrame {
    UdpFrame { frame: number, markers: markers.to_vec() }
}

#[test]
fn the_seeds_frame_layout_is_parsed_word_for_word() {
    // Figure 7: flag, number of masses, frame number, then (mass, posX, posY)...
    let bytes = frame(245, &[(0, 12.5, 3.3), (1, 7.0, 8.0), (2, 1.0, 2.0)]).encode();
    let words: Vec<u32> = bytes.chunks_exact(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
    assert_eq!(&words[..4], &[FRAME_FLAG, 3, 245, 0]);
    assert_eq!(f32::from_bits(words[4]), 12.5);
    assert_eq!(f32::from_bits(words[5]), 3.3);
    assert_eq!(words.len(), 3 + 3 * 3);
    let mut parser = FrameParser::default();
    assert_eq!(parser.parse(&bytes), vec![frame(245, &[(0, 12.5, 3.3), (1, 7.0, 8.0), (2, 1.0, 2.0)])]);
    assert_eq!(parser.counts.received, 1);
}

#[test]
fn damaged_frames_are_dropped_and_counted_and_the_parser_resynchronises() {
    let mut parser = FrameParser::default();
    let good1 = frame(1, &[(0, 1.0, 2.0)]).encode();
    let good4 = frame(4, &[(0, 3.0, 4.0), (1, 5.0, 6.0)]).encode();
    // Garbage, a good frame, a truncated frame, a good one: both good frames survive.
    let mut datagram = vec![0xAB, 0xCD, 0xEF, 0x01];
    datagram.extend(&good1);
    datagram.extend(&frame(2, &[(0, 1.0, 1.0), (1, 2.0, 2.0)]).encode()[..20]);
    datagram.extend(&good4);
    let frames = parser.parse(&datagram);
    assert_eq!(frames.iter().map(|f| f.frame).collect::<Vec<_>>(), vec![1, 4]);
    assert_eq!(parser.counts.lost, 2, "frames 2 and 3 never arrived whole");
    assert!(parser.counts.malformed >= 2, "{:?}", parser.counts);
    // NaN position, index beyond the count, repeated index: each frame dropped.
    for bad in [frame(5, &[(0, f32::NAN, 1.0)]), frame(6, &[(3, 1.0, 1.0)]), frame(7, &[(0, 1.0, 1.0), (0, 2.0, 2.0)])]
    {
        let before = parser.counts.malformed;
        assert!(parser.parse(&bad.encode()).is_empty());
        assert_eq!(parser.counts.malformed, before + 1);
    }
    // An old frame is out of order; a sender restarting at 0 starts a new sequence.
    assert!(parser.parse(&good1).is_empty());
    assert_eq!(parser.counts.out_of_order, 1);
    assert_eq!(parser.parse(&frame(0, &[]).encode()).len(), 1);
    assert_eq!(parser.parse(&frame(1, &[]).encode()).len(), 1);
    // A ragged length is reported, the whole words in it still read.
    let mut ragged = frame(2, &[(0, 9.0, 9.0)]).encode();
    ragged.push(0);
    assert_eq!(parser.parse(&ragged).len(), 1);
}

#[test]
fn udp_frames_arrive_over_loopback_without_blocking_a_step() {
    let mut source = UdpSource::bind("127.0.0.1:0".parse().unwrap()).unwrap();
    let addr = source.local_addr().unwrap();
    // Nothing sent yet: a poll returns at once with nothing.
    let start = Instant::now();
    assert!(source.poll().unwrap().is_none());
    assert!(start.elapsed() < Duration::from_millis(100));
    let sender = UdpSocket::bind("127.0.0.1:0").unwrap();
    for n in 1..=3 {
        sender.send_to(&frame(n, &[(0, n as f32, 2.0 * n as f32)]).encode(), addr).unwrap();
    }
    sender.send_to(b"not a frame", addr).unwrap();
    // Datagrams on loopback arrive promptly; poll until the newest is in.
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        let latest = source.poll().unwrap().map(|f| f.frame);
        if latest == Some(3) || Instant::now() > deadline {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let latest = source.poll().unwrap().cloned().unwrap();
    assert_eq!(latest, frame(3, &[(0, 3.0, 6.0)]));
    let markers = latest.markers(0.002);
    assert_eq!((markers[0].col, markers[0].row, markers[0].height), (3.0, 6.0, 0.002));
    assert_eq!(source.parser.counts.received, 3);
    assert_eq!(source.parser.counts.malformed, 1);
}

#[test]
fn motion_files_interpolate_in_time_and_map_through_the_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("motion.csv");
    let mut f = std::fs::File::create(&path).unwrap();
    writeln!(f, "# a marker crossing, another appearing later\ntime,marker,x,y,z\n0.0,0,0.0,0.0,0.01\n1.0,0,0.1,0.0,0.0\n0.5,1,0.05,0.05,0.0\n0.7,1,0.05,0.07,0.0").unwrap();
    drop(f);
    let motion = MotionFile::load(&path).unwrap();
    assert_eq!(motion.duration(), 1.0);
    let water = DpcmConfig::preset("water").unwrap();
    let calibration = Calibration::new(Isometry3::translation(-0.01, 0.0, 0.0), 0.001).at_tips(&water);
    let at = motion.markers_at(&calibration, 0.25);
    assert_eq!(at.len(), 1, "marker 1 has not appeared yet");
    let m = at[0];
    // x = 0.025 m world, 0.035 m from the grid origin = 35 phyxels; the tip's z interpolated,
    // the centre water's 4 mm reach above it.
    assert!((m.col - 35.0).abs() < 1e-9 && m.row.abs() < 1e-9 && (m.height - 0.0115).abs() < 1e-12, "{m:?}");
    assert!((motion.lowest_centre(&calibration) - 0.004).abs() < 1e-12);
    let at = motion.markers_at(&calibration, 0.6);
    assert_eq!(at.len(), 2);
    assert!((at[1].row - 60.0).abs() < 1e-9);
    assert!(motion.markers_at(&calibration, 1.5).is_empty(), "markers leave after their last sample");
    // Bad files name the row and the problem.
    for (text, needle) in [
        ("time,marker,x,y,z\n0,0,1,1,nan\n", "non-finite"),
        ("time,marker,x,y,z\n1,0,1,1,1\n0.5,0,1,1,1\n", "back in time"),
        ("t,m\n1,2\n", "row 1"),
    ] {
        std::fs::write(&path, text).unwrap();
        let err = MotionFile::load(&path).unwrap_err().to_string();
        assert!(err.contains(needle) && err.contains("motion.csv"), "{err}");
    }
}

#[test]
fn a_tool_point_becomes_a_marker_through_the_calibration_pose() {
    let c = DpcmConfig::preset("water").unwrap();
    // Grid rotated 90° about z and lifted 0.1 m: world +y runs along the grid's columns.
    let pose = Isometry3::new(Vector3::new(0.0, 0.0, 0.1), Vector3::z() * std::f64::consts::FRAC_PI_2);
    let calibration = Calibration::new(pose, c.spacing);
    let m = calibration.marker(7, Point3::new(-0.020, 0.030, 0.103));
    assert_eq!(m.id, 7);
    assert!((m.col - 30.0).abs() < 1e-9 && (m.row - 20.0).abs() < 1e-9 && (m.height - 0.003).abs() < 1e-12, "{m:?}");
    // The same point as a tip: water's 4 mm sphere has its centre 7 mm above the grid.
    let m = calibration.at_tips(&c).marker(7, Point3::new(-0.020, 0.030, 0.103));
    assert!((m.height - 0.007).abs() < 1e-12, "{m:?}");
    let centred = Calibration::centred(&c);
    let m = centred.marker(0, Point3::origin());
    assert!((m.col - 255.5).abs() < 1e-9 && (m.row - 255.5).abs() < 1e-9);
}

#[test]
fn the_bump_map_lights_a_tilted_plane_as_lambert_says() {
    let (w, h, spacing) = (16, 8, 0.001);
    // A plane rising 0.5 mm per phyxel along x: slope 0.5, normal (-0.5, 0, 1)/|.|.
    let d: Vec<f32> = (0..w * h).map(|i| (i % w) as f32 * 0.0005).collect();
    let config = RenderConfig {
        colormap: render::ColorMap::Greys,
        range: Some([0.0, 0.0]),
        light: [-1.0, 0.0, 1.0],
        bump_scale: 1.0,
        ambient: 0.2,
    };
    let image = render::bump_map(&d, w, h, spacing, &config);
    let normal = Vector3::new(-0.5, 0.0, 1.0).normalize();
    let light = Vector3::new(-1.0, 0.0, 1.0).normalize();
    let shade = 0.2 + 0.8 * normal.dot(&light);
    let base = render::colour_map(&d, w, h, &config).rgb[(3 * w + 5) * 3];
    let pixel = image.rgb[(3 * w + 5) * 3];
    assert_eq!(pixel, (f64::from(base) * shade).round() as u8);
    // The colour map's ends: the configured range's low and high colours.
    let ramp: Vec<f32> = vec![-1.0, 0.0, 1.0];
    let config = RenderConfig { colormap: render::ColorMap::Greys, range: Some([-1.0, 1.0]), ..Default::default() };
    let img = render::colour_map(&ramp, 3, 1, &config);
    let greys = colorous::GREYS;
    assert_eq!(
        img.rgb[..3],
        [greys.eval_continuous(0.0).r, greys.eval_continuous(0.0).g, greys.eval_continuous(0.0).b]
    );
    assert_eq!(
        img.rgb[6..9],
        [greys.eval_continuous(1.0).r, greys.eval_continuous(1.0).g, greys.eval_continuous(1.0).b]
    );
}

#[test]
fn the_displacement_mesh_is_the_height_field_with_upward_triangles() {
    let (w, h) = (5, 4);
    let z: Vec<f32> = (0..w * h).map(|i| i as f32 * 1e-4).collect();
    let mesh = render::displacement_mesh(&z, &z, w, h, 0.002, 2);
    assert_eq!(mesh.positions.len(), 3 * 2);
    assert_eq!(mesh.triangles.len(), 2 * 2);
    assert_eq!(mesh.positions[4], [0.002 * 2.0, 0.002 * 2.0, z[2 * w + 2]]);
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| Vector3::from(mesh.positions[i as usize].map(f64::from)));
        assert!((b - a).cross(&(c - a)).z > 0.0, "triangle {t:?} faces down");
    }
}

#[test]
fn textures_set_parameters_per_phyxel_and_heights_write_as_float_images() {
    let dir = tempfile::tempdir().unwrap();
    // A PNG whose left half is black and right half white: soft and hard ground.
    let (w, h) = (32usize, 32usize);
    let rgb: Vec<u8> = (0..w * h).flat_map(|i| if i % w < w / 2 { [0u8; 3] } else { [255u8; 3] }).collect();
    let png = dir.path().join("hardness.png");
    render::Image { width: w, height: h, rgb }.write_png(&png).unwrap();
    let mut c = DpcmConfig::preset("loose_soil").unwrap();
    (c.width, c.height) = (64, 64);
    c.textures =
        vec![ParamTexture { file: png.clone(), parameter: TexturedParameter::GroundStiffness, range: [0.5, 2.0] }];
    let surface = Surface::new(&c).unwrap();
    let k = c.dt * c.dt / c.mass * 10.0; // the preset's ground stiffness, scaled
    assert!((f64::from(surface.ground_coeffs(5).0) - 0.5 * k).abs() < 1e-6 * k);
    assert!((f64::from(surface.ground_coeffs(60).0) - 2.0 * k).abs() < 1e-6 * k);
    // A texture past the stability limit is refused, naming the step.
    c.textures[0].range = [0.5, 200.0];
    assert!(matches!(Surface::new(&c), Err(defvol::dpcm::DpcmError::Unstable { .. })));
    c.textures[0] = ParamTexture {
        file: dir.path().join("missing.png"),
        parameter: TexturedParameter::GroundStiffness,
        range: [0.5, 2.0],
    };
    assert!(Surface::new(&c).unwrap_err().to_string().contains("missing.png"));
    // Heights as a float image, read back through the volume readers.
    let heights: Vec<f32> = (0..64 * 64).map(|i| i as f32 * 1e-6).collect();
    let path = dir.path().join("height.mha");
    render::write_height(&path, &heights, 64, 64, 0.001).unwrap();
    let volume = defvol::io::read_volume(&path).unwrap();
    assert_eq!(volume.dims(), [64, 64, 1]);
    assert_eq!(volume.data(), &heights[..]);
    assert_eq!(volume.spacing()[0], 0.001);
}

#[cfg(feature = "mcap")]
#[test]
fn tool_poses_recorded_in_an_mcap_bag_drive_markers() {
    use defvol::msgs::{self, Header, Pose, PoseStamped, Quaternion, Time};
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("session.mcap");
    let mut writer = mcap::Writer::new(std::io::BufWriter::new(std::fs::File::create(&path).unwrap())).unwrap();
    let schema = writer
        .add_schema(
            "geometry_msgs/msg/PoseStamped",
            "ros2msg",
            msgs::ros2msg_schema("geometry_msgs/msg/PoseStamped").unwrap().as_bytes(),
        )
        .unwrap();
    let left = writer.add_channel(schema, "/left/tool_pose", "cdr", &Default::default()).unwrap();
    let right = writer.add_channel(schema, "/right/tool_pose", "cdr", &Default::default()).unwrap();
    let other = writer.add_channel(0, "/chatter", "json", &Default::default()).unwrap();
    let t0 = 1_700_000_000_000_000_000u64;
    let pose = |x: f64, y: f64, z: f64| PoseStamped {
        header: Header { stamp: Time::default(), frame_id: "world".into() },
        pose: Pose { position: msgs::Point { x, y, z }, orientation: Quaternion::default() },
    };
    let mut write = |channel_id: u16, dt_ms: u64, data: &[u8]| {
        writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id,
                    sequence: 0,
                    log_time: t0 + dt_ms * 1_000_000,
                    publish_time: t0,
                },
                data,
            )
            .unwrap();
    };
    write(left, 0, &msgs::encode(&pose(0.0, 0.0, 0.01)).unwrap());
    write(other, 5, b"{}");
    write(right, 100, &msgs::encode(&pose(0.01, 0.0, 0.0)).unwrap());
    write(left, 200, &msgs::encode(&pose(0.02, 0.0, 0.0)).unwrap());
    write(left, 200, &msgs::encode(&pose(0.5, 0.5, 0.5)).unwrap()); // same time: dropped
    write(right, 300, &msgs::encode(&pose(f64::NAN, 0.0, 0.0)).unwrap()); // dropped
    write(right, 400, &msgs::encode(&pose(0.01, 0.02, 0.0)).unwrap());
    writer.finish().unwrap();
    drop(writer);

    let (motion, counts) = defvol::record::bag::motion_from_bag(&path, &[]).unwrap();
    assert_eq!(counts.topics, vec!["/left/tool_pose".to_owned(), "/right/tool_pose".to_owned()]);
    assert_eq!((counts.messages, counts.dropped), (4, 2));
    let calibration = Calibration::new(Isometry3::identity(), 0.001);
    let at = motion.markers_at(&calibration, 0.1);
    assert_eq!(at.len(), 2);
    assert!((at[0].col - 10.0).abs() < 1e-9 && (at[0].height - 0.005).abs() < 1e-12, "{:?}", at[0]);
    assert!((at[1].col - 10.0).abs() < 1e-9 && at[1].row.abs() < 1e-9);
    let at = motion.markers_at(&calibration, 0.25);
    assert_eq!(at.len(), 1, "the left tool's track ended at 0.2 s");
    assert!((at[0].row - 10.0).abs() < 1e-9, "{:?}", at[0]);
    // One topic by name; a topic that is not a pose, or missing, is an error naming it.
    let (only_right, _) = defvol::record::bag::motion_from_bag(&path, &["/right/tool_pose".to_owned()]).unwrap();
    assert_eq!(only_right.markers_at(&calibration, 0.1).len(), 1);
    let err = defvol::record::bag::motion_from_bag(&path, &["/chatter".to_owned()]).unwrap_err().to_string();
    assert!(err.contains("/chatter") && err.contains("PoseStamped"), "{err}");
    std::fs::write(dir.path().join("broken.mcap"), b"not an mcap").unwrap();
    let err = defvol::record::bag::motion_from_bag(&dir.path().join("broken.mcap"), &[]).unwrap_err().to_string();
    assert!(err.contains("broken.mcap"), "{err}");
}

/// A sender flooding at full speed costs a step at most a bounded read: the step rate with
/// the flood stays within 20 % of the rate without it (windows taking turns in one run), the
/// polls that stopped at the bound are counted, and the newest frames still come through.
#[test]
fn a_udp_flood_leaves_the_step_rate_within_a_fifth_of_the_quiet_rate() {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    let mut source = UdpSource::bind("127.0.0.1:0".parse().unwrap()).unwrap();
    let addr = source.local_addr().unwrap();
    let (flooding, stop) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicBool::new(false)));
    let sender = {
        let (flooding, stop) = (flooding.clone(), stop.clone());
        std::thread::spawn(move || {
            let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
            let mut n = 0u32;
            while !stop.load(Ordering::Relaxed) {
                // Quiet, it spins: both windows share the cores alike, only datagrams differ.
                if flooding.load(Ordering::Relaxed) {
                    n += 1;
                    let _ = socket.send_to(&frame(n, &[(0, 1.0, 2.0)]).encode(), addr);
                } else {
                    std::hint::spin_loop();
                }
            }
        })
    };
    // A step's own work: about a millisecond of arithmetic on one thread.
    let data: Vec<f64> = (0..400_000).map(f64::from).collect();
    let steps_per_second = |source: &mut UdpSource| {
        let start = Instant::now();
        for _ in 0..100 {
            source.poll().unwrap();
            std::hint::black_box(data.iter().map(|x| x.sqrt()).sum::<f64>());
        }
        100.0 / start.elapsed().as_secs_f64()
    };
    let (mut quiet, mut flooded) = (Vec::new(), Vec::new());
    for round in 0..8 {
        let flood = round % 2 == 1;
        flooding.store(flood, Ordering::Relaxed);
        std::thread::sleep(Duration::from_millis(20));
        if !flood {
            // What a flood left in the socket is read before a quiet window.
            let mut before = u64::MAX;
            while source.parser.counts.backlogged != before {
                before = source.parser.counts.backlogged;
                source.poll().unwrap();
            }
        }
        let rate = steps_per_second(&mut source);
        if flood {
            flooded.push(rate)
        } else {
            quiet.push(rate)
        }
    }
    stop.store(true, Ordering::Relaxed);
    sender.join().unwrap();
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (quiet, flooded) = (median(&mut quiet), median(&mut flooded));
    let counts = source.parser.counts;
    assert!(flooded >= 0.8 * quiet, "{flooded:.0} steps/s flooded, {quiet:.0} quiet ({counts:?})");
    assert!(counts.backlogged > 0 && counts.received > 1000, "the flood reached the bound: {counts:?}");
    assert!(source.poll().unwrap().is_some_and(|f| f.frame > 1000));
}
