//! The volume raycaster against analytic ray integrals and the f64 reference.

use nalgebra::{Matrix3, Point3, Vector3};

use defvol::render::camera::{Camera, Projection};
use defvol::render::transfer::{TfPoint, TransferFunction};
use defvol::render::volume::{self, Mode, RaycastParams, Shading};
use defvol::render::RenderError;
use defvol::volume::{phantom, Volume};

fn flat(color: [f64; 3], opacity: f64) -> TransferFunction {
    TransferFunction {
        points: vec![TfPoint { value: 0.0, color, opacity }, TfPoint { value: 200.0, color, opacity }],
        relative: false,
    }
}

fn along_x(volume: &Volume, size: usize) -> Camera {
    let (lo, hi) = volume.bounds();
    let centre = Point3::from((lo + hi) / 2.0);
    Camera::look_at(
        centre - Vector3::x() * 100.0,
        centre,
        Vector3::z(),
        Projection::Orthographic { height: 4.0 },
        size,
        size,
    )
    .unwrap()
}

#[test]
fn a_uniform_slab_absorbs_as_beer_lambert_says() {
    // 20 voxels at 1 mm along x: every ray crosses 19 mm between the first and last centres.
    let volume = Volume::new([20, 10, 10], [1.0; 3], [0.0; 3], Matrix3::identity(), vec![100.0; 2000], "slab").unwrap();
    let camera = along_x(&volume, 8);
    let tf = flat([0.2, 0.6, 1.0], 0.05);
    let alpha = 1.0 - 0.95f64.powf(19.0);
    for (preintegrated, step) in [(false, 1.0), (true, 1.0), (false, 0.7), (true, 0.7), (true, 3.0)] {
        let params = RaycastParams {
            step,
            preintegrated,
            shading: Shading::None,
            early_termination: 1.0,
            background: [0.0, 0.0, 0.0, 1.0],
            ..Default::default()
        };
        let image = volume::raycast(&volume, &camera, &tf, &params).unwrap();
        let px = &image.rgba[(4 * 8 + 4) * 4..(4 * 8 + 4) * 4 + 4];
        for (c, want) in [0.2, 0.6, 1.0].iter().enumerate() {
            let want = (want * alpha * 255.0).round();
            assert!(
                (f64::from(px[c]) - want).abs() <= 1.0,
                "step {step}, preintegrated {preintegrated}: channel {c} = {}, Beer-Lambert {want}",
                px[c]
            );
        }
        // Depth: where the accumulated opacity passes 0.5 (13.5 mm in), from the eye.
        let half = (0.5f64).ln() / 0.95f64.ln();
        assert!(
            (f64::from(image.depth[4 * 8 + 4]) - (100.0 - 9.5 + half)).abs() <= step,
            "depth {}",
            image.depth[4 * 8 + 4]
        );
    }
    let reference = volume::reference(&volume, &camera, &tf, 0.01, [0.0, 0.0, 0.0, 1.0]).unwrap();
    assert!((reference[4 * 8 + 4][1] - 0.6 * alpha).abs() < 1e-9, "f64 reference green {}", reference[4 * 8 + 4][1]);
}

fn phantom_view(size: usize) -> (Volume, Camera) {
    let volume = phantom::phantom([128, 80, 61], 2.0).unwrap();
    let (lo, hi) = volume.bounds();
    let centre = Point3::from((lo + hi) / 2.0);
    let eye = centre + Vector3::new(-150.0, -380.0, 120.0);
    let camera =
        Camera::look_at(eye, centre, Vector3::z(), Projection::Perspective { fov_y_deg: 40.0 }, size, size).unwrap();
    (volume, camera)
}

#[test]
fn the_phantom_matches_the_f64_reference_and_pre_integration_beats_point_sampling_at_a_coarse_step() {
    let (volume, camera) = phantom_view(96);
    let tf = TransferFunction::preset("ct_soft_tissue").unwrap();
    let reference = volume::reference(&volume, &camera, &tf, 0.05, [0.0, 0.0, 0.0, 1.0]).unwrap();
    let render = |step: f64, preintegrated: bool| {
        let params = RaycastParams { step, preintegrated, shading: Shading::None, ..Default::default() };
        volume::raycast(&volume, &camera, &tf, &params).unwrap()
    };
    let fine = render(0.25, true);
    let psnr = fine.psnr(&reference);
    let (mean, max) = fine.errors(&reference);
    assert!(
        psnr > 45.0 && mean < 0.6 && max < 12.0,
        "fine step: PSNR {psnr:.1} dB, mean {mean:.2}, max {max:.1} levels"
    );
    // A thin opaque band (an iso-surface-like transfer function) at a step of 4 mm (two
    // voxels): point samples step over the band, pre-integrated segments do not.
    let band = TransferFunction {
        points: vec![
            TfPoint { value: 100.0, color: [0.0; 3], opacity: 0.0 },
            TfPoint { value: 150.0, color: [1.0, 0.9, 0.7], opacity: 0.7 },
            TfPoint { value: 200.0, color: [0.0; 3], opacity: 0.0 },
        ],
        relative: false,
    };
    let band_reference = volume::reference(&volume, &camera, &band, 0.005, [0.0, 0.0, 0.0, 1.0]).unwrap();
    let render_band = |step: f64, preintegrated: bool| {
        volume::raycast(
            &volume,
            &camera,
            &band,
            &RaycastParams { step, preintegrated, shading: Shading::None, ..Default::default() },
        )
        .unwrap()
    };
    let coarse_pre = render_band(4.0, true).psnr(&band_reference);
    let coarse_point = render_band(4.0, false).psnr(&band_reference);
    // Measured: 27.6 against 20.8 dB.
    assert!(coarse_pre > coarse_point + 5.0, "pre-integrated {coarse_pre:.1} dB vs point-sampled {coarse_point:.1} dB");
    // Skipping and early termination change nothing visible.
    let plain = volume::raycast(
        &volume,
        &camera,
        &tf,
        &RaycastParams {
            step: 0.25,
            shading: Shading::None,
            empty_space_skipping: false,
            early_termination: 1.0,
            ..Default::default()
        },
    )
    .unwrap();
    let (mean, max) = fine
        .errors(&plain.rgba.chunks_exact(4).map(|p| [0, 1, 2, 3].map(|c| f64::from(p[c]) / 255.0)).collect::<Vec<_>>());
    assert!(mean < 0.05 && max <= 1.0, "skipping/termination moved pixels: mean {mean}, max {max}");
}

#[test]
fn iso_surfaces_are_hit_where_the_field_crosses_and_mip_finds_the_peak() {
    // A radial field: value = 100 - distance (mm) from the centre; iso 80 is a sphere of 20 mm.
    let n = 64;
    let data: Vec<f32> = (0..n * n * n)
        .map(|i| {
            let p = Vector3::new((i % n) as f64, ((i / n) % n) as f64, (i / (n * n)) as f64) - Vector3::repeat(31.5);
            (100.0 - p.norm()) as f32
        })
        .collect();
    let volume = Volume::new([n; 3], [1.0; 3], [0.0; 3], Matrix3::identity(), data, "radial").unwrap();
    let centre = Point3::new(31.5, 31.5, 31.5);
    let camera = Camera::look_at(
        centre - Vector3::y() * 80.0,
        centre,
        Vector3::z(),
        Projection::Perspective { fov_y_deg: 30.0 },
        32,
        32,
    )
    .unwrap();
    let tf = TransferFunction::preset("ct_bone").unwrap();
    let params = RaycastParams { mode: Mode::Iso, iso_value: 80.0, step: 0.5, ..Default::default() };
    let image = volume::raycast(&volume, &camera, &tf, &params).unwrap();
    // The centre pixels' rays pass within a pixel of the centre: the sphere is 60 mm away.
    let (ray_origin, ray_dir) = camera.ray(16, 16);
    let miss = (centre - ray_origin).cross(&ray_dir).norm();
    let expected = (centre - ray_origin).dot(&ray_dir) - (20.0f64 * 20.0 - miss * miss).sqrt();
    assert!(
        (f64::from(image.depth[16 * 32 + 16]) - expected).abs() < 0.05,
        "iso depth {} vs {expected}",
        image.depth[16 * 32 + 16]
    );
    assert!(image.depth[0].is_infinite(), "a corner ray misses the sphere");
    // MIP through the centre sees the peak (100, minus trilinear's dip near the peak).
    let mip = volume::raycast(
        &volume,
        &camera,
        &TransferFunction {
            points: vec![
                TfPoint { value: 0.0, color: [1.0; 3], opacity: 0.5 },
                TfPoint { value: 100.0, color: [1.0; 3], opacity: 0.5 },
            ],
            relative: false,
        },
        &RaycastParams { mode: Mode::Mip, step: 0.25, ..Default::default() },
    )
    .unwrap();
    assert!(mip.rgba[(16 * 32 + 16) * 4] >= 250, "MIP {}", mip.rgba[(16 * 32 + 16) * 4]);
}

#[test]
fn shading_lights_surfaces_facing_the_light() {
    let (volume, camera) = phantom_view(48);
    let tf = TransferFunction::preset("ct_bone").unwrap();
    let shaded = |shading| {
        volume::raycast(&volume, &camera, &tf, &RaycastParams { shading, step: 1.0, ..Default::default() }).unwrap()
    };
    let none = shaded(Shading::None);
    for shading in [Shading::Gradient, Shading::ForwardDifference] {
        let lit = shaded(shading);
        // Shading only darkens (ambient + diffuse <= 1), and it changes the picture.
        assert!(lit.rgba.iter().zip(&none.rgba).all(|(l, n)| l <= n || l - n <= 1), "{shading:?} brightened a pixel");
        assert!(lit.rgba.iter().zip(&none.rgba).any(|(l, n)| n - l > 20), "{shading:?} changed nothing");
    }
}

#[test]
fn bad_cameras_and_transfer_functions_are_refused_or_rendered_validly() {
    let (volume, camera) = phantom_view(16);
    let tf = TransferFunction::preset("ct_soft_tissue").unwrap();
    let empty = TransferFunction { points: vec![], relative: false };
    assert!(matches!(
        volume::raycast(&volume, &camera, &empty, &RaycastParams::default()),
        Err(RenderError::TransferFunction(_))
    ));
    assert!(matches!(TransferFunction::preset("pet"), Err(RenderError::UnknownPreset(_))));
    assert!(Camera::from_pose(
        [f64::NAN, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
        Projection::Perspective { fov_y_deg: 40.0 },
        8,
        8
    )
    .unwrap_err()
    .to_string()
    .contains("NaN"));
    assert!(Camera::from_pose([0.0; 3], [0.0, 0.0, 0.0, 2.0], Projection::Perspective { fov_y_deg: 40.0 }, 8, 8)
        .unwrap_err()
        .to_string()
        .contains("length"));
    assert!(Camera::look_at(
        Point3::origin(),
        Point3::origin(),
        Vector3::z(),
        Projection::Perspective { fov_y_deg: 40.0 },
        8,
        8
    )
    .is_err());
    // Inside the volume: a valid image of what lies ahead. Behind it, looking away: background.
    let (lo, hi) = volume.bounds();
    let centre = Point3::from((lo + hi) / 2.0);
    let inside = Camera::look_at(
        centre,
        centre + Vector3::x(),
        Vector3::z(),
        Projection::Perspective { fov_y_deg: 60.0 },
        16,
        16,
    )
    .unwrap();
    let image = volume::raycast(&volume, &inside, &tf, &RaycastParams::default()).unwrap();
    assert!(image.rgba.chunks_exact(4).any(|p| p[0] > 0), "nothing seen from inside");
    let away = Camera::look_at(
        centre - Vector3::x() * 1000.0,
        centre - Vector3::x() * 2000.0,
        Vector3::z(),
        Projection::Perspective { fov_y_deg: 60.0 },
        16,
        16,
    )
    .unwrap();
    let image = volume::raycast(&volume, &away, &tf, &RaycastParams::default()).unwrap();
    assert!(image.rgba.chunks_exact(4).all(|p| p == [0, 0, 0, 255]) && image.depth.iter().all(|d| d.is_infinite()));
    let zero_step = RaycastParams { step: 0.0, ..Default::default() };
    assert!(matches!(volume::raycast(&volume, &camera, &tf, &zero_step), Err(RenderError::Parameter(_))));
}

#[test]
fn a_tool_is_drawn_at_its_depth_behind_or_in_front_of_tissue() {
    use defvol::render::volume::ToolPicture;
    let volume = Volume::new([20, 10, 10], [1.0; 3], [0.0; 3], Matrix3::identity(), vec![100.0; 2000], "slab").unwrap();
    let camera = along_x(&volume, 8);
    let tf = flat([0.2, 0.6, 1.0], 0.05);
    let alpha = 1.0 - 0.95f64.powf(19.0);
    let centre = [9.5, 4.5, 4.5];
    let sphere = |x: f64| ToolPicture {
        tip: [x, centre[1], centre[2]],
        tail: [x, centre[1], centre[2]],
        radius: 3.0,
        color: [1.0, 0.5, 0.0],
    };
    let params = |tools| RaycastParams {
        shading: Shading::None,
        early_termination: 1.0,
        step: 0.5,
        tools,
        ..Default::default()
    };
    // Behind the slab: seen through it. The centre pixel's ray meets the sphere head-on,
    // so the headlight gives full diffuse light.
    let behind = volume::raycast(&volume, &camera, &tf, &params(vec![sphere(40.0)])).unwrap();
    let px = &behind.rgba[(4 * 8 + 4) * 4..(4 * 8 + 4) * 4 + 4];
    for (c, (tissue, tool)) in [(0.2, 1.0), (0.6, 0.5), (1.0, 0.0)].iter().enumerate() {
        let want = ((tissue * alpha + (1.0 - alpha) * tool) * 255.0).round();
        assert!((f64::from(px[c]) - want).abs() <= 1.5, "behind: channel {c} = {}, want {want}", px[c]);
    }
    // In front of the slab: the tool alone, at its distance (pixel centres are ±0.25 off
    // the axis, so the surface is within 0.02 mm of the head-on distance).
    let front = volume::raycast(&volume, &camera, &tf, &params(vec![sphere(-20.0)])).unwrap();
    let px = &front.rgba[(4 * 8 + 4) * 4..(4 * 8 + 4) * 4 + 4];
    for (c, want) in [255.0, 127.5, 0.0].iter().enumerate() {
        assert!((f64::from(px[c]) - want).abs() <= 1.5, "front: channel {c} = {}, want {want}", px[c]);
    }
    let expect = 100.0 - 9.5 - 20.0 - 3.0;
    assert!((f64::from(front.depth[4 * 8 + 4]) - expect).abs() < 0.05, "tool depth {}", front.depth[4 * 8 + 4]);
    // A bad tool is refused.
    let mut bad = sphere(0.0);
    bad.radius = f64::NAN;
    assert!(matches!(volume::raycast(&volume, &camera, &tf, &params(vec![bad])), Err(RenderError::Parameter(_))));
}

mod tet_mesh {
    use super::*;
    use defvol::mesh::generate::{self, CellSplit};
    use defvol::mesh::TetMesh;
    use defvol::render::mesh::{self, TetRaycastParams, TetRaycaster};
    use defvol::render::volume::ToolPicture;

    /// A lattice mesh on the voxel centres of an n³ grid at 1 mm, and the volume of `f`.
    fn grid_and_mesh(n: usize, f: impl Fn(&Vector3<f64>) -> f64) -> (Volume, TetMesh, Vec<f32>) {
        let data = (0..n * n * n)
            .map(|i| f(&Vector3::new((i % n) as f64, ((i / n) % n) as f64, (i / (n * n)) as f64)) as f32)
            .collect();
        let volume = Volume::new([n; 3], [1.0; 3], [0.0; 3], Matrix3::identity(), data, "grid").unwrap();
        let top = (n - 1) as f64;
        let mesh = generate::lattice(Vector3::zeros(), Vector3::repeat(top), [n - 1; 3], CellSplit::Five).unwrap();
        let scalars = mesh.nodes().iter().map(|p| f(p) as f32).collect();
        (volume, mesh, scalars)
    }

    fn oblique(n: usize, size: usize) -> Camera {
        let c = Point3::from(Vector3::repeat((n - 1) as f64 / 2.0));
        Camera::look_at(
            c + Vector3::new(-2.0, -3.0, 1.5) * n as f64,
            c,
            Vector3::z(),
            Projection::Perspective { fov_y_deg: 30.0 },
            size,
            size,
        )
        .unwrap()
    }

    fn ramp() -> TransferFunction {
        TransferFunction {
            points: vec![
                TfPoint { value: 0.0, color: [0.1, 0.2, 0.9], opacity: 0.0 },
                TfPoint { value: 100.0, color: [1.0, 0.6, 0.2], opacity: 0.08 },
                TfPoint { value: 300.0, color: [1.0, 1.0, 1.0], opacity: 0.02 },
            ],
            relative: false,
        }
    }

    fn agreement(n: usize, f: impl Fn(&Vector3<f64>) -> f64) -> f64 {
        let (volume, mesh, scalars) = grid_and_mesh(n, f);
        let camera = oblique(n, 64);
        let tets = TetRaycaster::new(
            &mesh,
            &scalars,
            &ramp(),
            &TetRaycastParams { step: 0.1, early_termination: 1.0, ..Default::default() },
        )
        .unwrap()
        .render(&camera)
        .unwrap();
        let voxels = volume::raycast(
            &volume,
            &camera,
            &ramp(),
            &RaycastParams {
                step: 0.1,
                preintegrated: false,
                shading: Shading::None,
                early_termination: 1.0,
                ..Default::default()
            },
        )
        .unwrap();
        assert!(voxels.rgba.chunks_exact(4).filter(|p| p[0] > 20).count() > 64 * 64 / 5, "the view is nearly empty");
        tets.psnr(
            &voxels.rgba.chunks_exact(4).map(|p| [0, 1, 2, 3].map(|c| f64::from(p[c]) / 255.0)).collect::<Vec<_>>(),
        )
    }

    #[test]
    fn the_tet_raycaster_agrees_with_the_volume_raycaster_on_a_split_voxel_grid() {
        // Linear fields are exact under both interpolations: only integration differs.
        let linear = agreement(16, |p| 10.0 * p.x + 5.0 * p.y + 2.0 * p.z);
        assert!(linear > 45.0, "linear field: {linear:.1} dB");
        // A smooth field: linear tets against trilinear voxels.
        let smooth = agreement(16, |p| 120.0 + 90.0 * (p.x * 0.3).sin() * (p.y * 0.25).cos() + 4.0 * p.z);
        assert!(smooth > 30.0, "smooth field: {smooth:.1} dB");
    }

    #[test]
    fn rays_leave_a_non_convex_mesh_and_re_enter_it() {
        // Two 4 mm boxes 6 mm apart along x, uniform scalar: the ray crosses 8 mm of tissue.
        let a = generate::lattice(Vector3::zeros(), Vector3::new(4.0, 4.0, 4.0), [2; 3], CellSplit::Five).unwrap();
        let b = generate::lattice(Vector3::new(10.0, 0.0, 0.0), Vector3::new(14.0, 4.0, 4.0), [2; 3], CellSplit::Five)
            .unwrap();
        let offset = a.nodes().len() as u32;
        let nodes: Vec<Vector3<f64>> = a.nodes().iter().chain(b.nodes()).copied().collect();
        let tets: Vec<[u32; 4]> =
            a.tets().iter().copied().chain(b.tets().iter().map(|t| t.map(|i| i + offset))).collect();
        let mesh = TetMesh::new(nodes, tets, None, "two boxes").unwrap();
        let scalars = vec![100.0f32; mesh.nodes().len()];
        let tf = flat([0.2, 0.6, 1.0], 0.05);
        let camera = Camera::look_at(
            Point3::new(-50.0, 2.1, 2.1),
            Point3::new(0.0, 2.1, 2.1),
            Vector3::z(),
            Projection::Orthographic { height: 0.5 },
            4,
            4,
        )
        .unwrap();
        let image =
            TetRaycaster::new(&mesh, &scalars, &tf, &TetRaycastParams { early_termination: 1.0, ..Default::default() })
                .unwrap()
                .render(&camera)
                .unwrap();
        let alpha = 1.0 - 0.95f64.powf(8.0);
        let px = &image.rgba[(2 * 4 + 2) * 4..(2 * 4 + 2) * 4 + 4];
        assert!((f64::from(px[1]) - (0.6 * alpha * 255.0).round()).abs() <= 1.0, "green {} for 8 mm", px[1]);
        // After a deformation step (the mesh moved 5 mm away), the depth follows (denser
        // tissue, so that opacity passes 0.5 inside the first box).
        let mut raycaster =
            TetRaycaster::new(&mesh, &scalars, &flat([1.0; 3], 0.2), &TetRaycastParams::default()).unwrap();
        let depth0 = raycaster.render(&camera).unwrap().depth[2 * 4 + 2];
        let half = 0.5f64.ln() / 0.8f64.ln();
        assert!((f64::from(depth0) - (50.0 + half)).abs() < 1.0, "depth {depth0}");
        let moved: Vec<Vector3<f64>> = mesh.nodes().iter().map(|p| p + Vector3::new(5.0, 0.0, 0.0)).collect();
        raycaster.update(&moved).unwrap();
        let depth1 = raycaster.render(&camera).unwrap().depth[2 * 4 + 2];
        assert!(((depth1 - depth0) - 5.0).abs() < 1e-3, "depth {depth0} -> {depth1}");
        assert!(raycaster.update(&moved[..3]).is_err());
    }

    /// A 20 mm cube of uniform tissue in 5 mm lattice cells.
    fn cube() -> TetMesh {
        generate::lattice(Vector3::zeros(), Vector3::repeat(20.0), [4; 3], CellSplit::Five).unwrap()
    }

    #[test]
    fn a_camera_inside_the_mesh_sees_the_tissue_up_to_the_wall() {
        let mesh = cube();
        let scalars = vec![100.0f32; mesh.nodes().len()];
        let tf = flat([0.2, 0.6, 1.0], 0.05);
        let centre = Point3::new(10.0, 10.3, 9.7);
        // Perspective from the middle (10 mm to the wall along the central ray), and
        // orthographic from 5 mm in (15 mm to the wall): Beer-Lambert either way.
        let views = [
            (
                Camera::look_at(
                    centre,
                    centre + Vector3::x(),
                    Vector3::z(),
                    Projection::Perspective { fov_y_deg: 60.0 },
                    5,
                    5,
                )
                .unwrap(),
                10.0,
            ),
            (
                Camera::look_at(
                    centre - Vector3::x() * 5.0,
                    centre,
                    Vector3::z(),
                    Projection::Orthographic { height: 2.0 },
                    5,
                    5,
                )
                .unwrap(),
                15.0,
            ),
        ];
        for (camera, inside) in views {
            for preintegrated in [true, false] {
                let params =
                    TetRaycastParams { preintegrated, step: 2.0, early_termination: 1.0, ..Default::default() };
                let image = TetRaycaster::new(&mesh, &scalars, &tf, &params).unwrap().render(&camera).unwrap();
                let alpha = 1.0 - 0.95f64.powf(inside);
                let px = &image.rgba[(2 * 5 + 2) * 4..(2 * 5 + 2) * 4 + 4];
                for (c, want) in [0.2, 0.6, 1.0].iter().enumerate() {
                    let want = (want * alpha * 255.0).round();
                    assert!(
                        (f64::from(px[c]) - want).abs() <= 1.0,
                        "{:?}, pre-integrated {preintegrated}: channel {c} = {}, Beer-Lambert {want}",
                        camera.projection,
                        px[c]
                    );
                }
                // Every ray starts in tissue: no pixel is left at the background.
                assert!(
                    image.rgba.chunks_exact(4).all(|p| p[2] > 20),
                    "{:?}: a ray missed the tissue around the eye",
                    camera.projection
                );
            }
            let reference = mesh::reference(
                &mesh,
                mesh.nodes(),
                &scalars,
                &camera,
                &tf,
                &TetRaycastParams { step: 0.01, ..Default::default() },
            )
            .unwrap();
            assert!(
                (reference[2 * 5 + 2][1] - 0.6 * (1.0 - 0.95f64.powf(inside))).abs() < 1e-6,
                "f64 reference green {}",
                reference[2 * 5 + 2][1]
            );
        }
    }

    /// A deformed lattice with a smooth field and a transfer function with a narrow peak:
    /// what coarse point sampling misses.
    fn bent_scene() -> (TetMesh, Vec<Vector3<f64>>, Vec<f32>, TransferFunction, Camera) {
        let mesh =
            generate::lattice(Vector3::zeros(), Vector3::new(40.0, 30.0, 30.0), [8, 6, 6], CellSplit::Five).unwrap();
        let scalars: Vec<f32> = mesh
            .nodes()
            .iter()
            .map(|p| (100.0 + 80.0 * (p.x * 0.15).sin() * (p.y * 0.12).cos() + 2.0 * p.z) as f32)
            .collect();
        let bent = mesh.nodes().iter().map(|p| p + Vector3::new(0.0, 0.0, 4.0 * (p.x / 12.0).sin())).collect();
        let tf = TransferFunction {
            points: vec![
                TfPoint { value: 0.0, color: [0.0; 3], opacity: 0.0 },
                TfPoint { value: 120.0, color: [0.2, 0.3, 0.9], opacity: 0.02 },
                TfPoint { value: 140.0, color: [1.0, 0.9, 0.3], opacity: 0.4 },
                TfPoint { value: 150.0, color: [1.0, 0.4, 0.2], opacity: 0.03 },
                TfPoint { value: 300.0, color: [1.0; 3], opacity: 0.05 },
            ],
            relative: false,
        };
        let camera = Camera::look_at(
            Point3::new(-40.0, -60.0, 50.0),
            Point3::new(20.0, 15.0, 15.0),
            Vector3::z(),
            Projection::Perspective { fov_y_deg: 40.0 },
            64,
            64,
        )
        .unwrap();
        (mesh, bent, scalars, tf, camera)
    }

    #[test]
    fn the_tet_raycaster_matches_the_f64_reference_and_pre_integration_beats_point_sampling() {
        let (mesh, bent, scalars, tf, camera) = bent_scene();
        let reference = mesh::reference(
            &mesh,
            &bent,
            &scalars,
            &camera,
            &tf,
            &TetRaycastParams { step: 0.02, ..Default::default() },
        )
        .unwrap();
        assert!(reference.iter().filter(|p| p[0] > 0.1).count() > 64 * 64 / 5, "the view is nearly empty");
        let render = |preintegrated: bool, step: f64| {
            let mut raycaster = TetRaycaster::new(
                &mesh,
                &scalars,
                &tf,
                &TetRaycastParams { preintegrated, step, early_termination: 1.0, ..Default::default() },
            )
            .unwrap();
            raycaster.update(&bent).unwrap();
            raycaster.render(&camera).unwrap()
        };
        let pre = render(true, 4.0);
        let point = render(false, 4.0);
        let fine = render(false, 0.05);
        let (pre_mean, pre_max) = pre.errors(&reference);
        let (point_mean, _) = point.errors(&reference);
        let (fine_mean, fine_max) = fine.errors(&reference);
        eprintln!("against the f64 reference (levels, mean/max): pre-integrated 4 mm {pre_mean:.3}/{pre_max:.1}, point 4 mm {point_mean:.3}, point 0.05 mm {fine_mean:.3}/{fine_max:.1}");
        // Pre-integration at 4 mm (one lookup per tet) against point sampling at 4 mm.
        assert!(
            pre_mean < 0.5 * point_mean,
            "mean error: pre-integrated {pre_mean:.2} levels, point-sampled {point_mean:.2}"
        );
        assert!(pre_mean < 0.3 && pre_max < 4.0, "pre-integrated: mean {pre_mean:.2}, max {pre_max:.1} levels");
        assert!(
            fine_mean < 0.5 && fine_max < 6.0,
            "point-sampled at 0.05 mm: mean {fine_mean:.2}, max {fine_max:.1} levels"
        );
    }

    #[test]
    fn a_tool_in_the_mesh_hides_what_lies_behind_it() {
        let mesh = cube();
        let scalars = vec![100.0f32; mesh.nodes().len()];
        let tf = flat([0.2, 0.6, 1.0], 0.05);
        // A probe whose tip sits 6 mm into the cube, on the central ray.
        let probe =
            ToolPicture { tip: [6.0, 10.0, 10.0], tail: [-30.0, 10.0, 10.0], radius: 1.0, color: [1.0, 0.0, 0.0] };
        let camera = Camera::look_at(
            Point3::new(10.0, 10.0, -50.0),
            Point3::new(10.0, 10.0, 10.0),
            Vector3::y(),
            Projection::Orthographic { height: 24.0 },
            24,
            24,
        )
        .unwrap();
        let params = TetRaycastParams { tools: vec![probe], early_termination: 1.0, ..Default::default() };
        let image = TetRaycaster::new(&mesh, &scalars, &tf, &params).unwrap().render(&camera).unwrap();
        let reference = mesh::reference(
            &mesh,
            mesh.nodes(),
            &scalars,
            &camera,
            &tf,
            &TetRaycastParams { step: 0.01, ..params.clone() },
        )
        .unwrap();
        let (mean, max) = image.errors(&reference);
        assert!(mean < 0.5 && max < 4.0, "against the f64 reference: mean {mean:.2}, max {max:.1} levels");
        // A pixel on the probe's axis, 3 mm along it inside the cube: 9 mm of tissue (from
        // z = 0 to the probe's top at z = 9), then red.
        let (u, v) = camera_pixel(&camera, Point3::new(3.0, 10.0, 10.0));
        let px = &image.rgba[(v * 24 + u) * 4..(v * 24 + u) * 4 + 4];
        assert!(px[0] > 60 && px[2] > 60, "probe pixel {px:?}: red behind blue tissue");
        assert!(
            (f64::from(image.depth[v * 24 + u]) - 59.0).abs() < 0.6,
            "depth {} (the probe's top at 59 mm from the eye)",
            image.depth[v * 24 + u]
        );
    }

    fn camera_pixel(camera: &Camera, p: Point3<f64>) -> (usize, usize) {
        let c = camera.world_from_camera.inverse() * p;
        let Projection::Orthographic { height } = camera.projection else { panic!("orthographic only") };
        let u = ((c.x / (height / 2.0) + 1.0) / 2.0 * camera.width as f64) as usize;
        let v = ((c.y / (height / 2.0) + 1.0) / 2.0 * camera.height as f64) as usize;
        (u, v)
    }

    #[test]
    fn bad_input_to_the_tet_raycaster_is_refused_and_keeps_the_last_good_frame() {
        let mesh = cube();
        let scalars = vec![100.0f32; mesh.nodes().len()];
        let tf = flat([0.2, 0.6, 1.0], 0.05);
        let empty = TransferFunction { points: Vec::new(), relative: false };
        assert!(matches!(
            TetRaycaster::new(&mesh, &scalars, &empty, &TetRaycastParams::default()),
            Err(RenderError::TransferFunction(_))
        ));
        let mut nan = scalars.clone();
        nan[3] = f32::NAN;
        assert!(matches!(
            TetRaycaster::new(&mesh, &nan, &tf, &TetRaycastParams::default()),
            Err(RenderError::Parameter(_))
        ));
        assert!(matches!(
            TetRaycaster::new(&mesh, &scalars, &tf, &TetRaycastParams { step: 0.0, ..Default::default() }),
            Err(RenderError::Parameter(_))
        ));
        let mut raycaster = TetRaycaster::new(&mesh, &scalars, &tf, &TetRaycastParams::default()).unwrap();
        let camera = Camera::look_at(
            Point3::new(10.0, 10.0, -50.0),
            Point3::new(10.0, 10.0, 10.0),
            Vector3::y(),
            Projection::Perspective { fov_y_deg: 40.0 },
            16,
            16,
        )
        .unwrap();
        let before = raycaster.render(&camera).unwrap();
        let mut moved = mesh.nodes().to_vec();
        moved[0].x = f64::NAN;
        assert!(matches!(raycaster.update(&moved), Err(RenderError::Parameter(_))));
        assert_eq!(raycaster.render(&camera).unwrap(), before, "a refused update changed the picture");
        // Looking away from the mesh: the background, not a crash.
        let away = Camera::look_at(
            Point3::new(10.0, 10.0, -50.0),
            Point3::new(10.0, 10.0, -100.0),
            Vector3::y(),
            Projection::Perspective { fov_y_deg: 40.0 },
            16,
            16,
        )
        .unwrap();
        let image = raycaster.render(&away).unwrap();
        assert!(image.rgba.chunks_exact(4).all(|p| p == [0, 0, 0, 255]) && image.depth.iter().all(|d| d.is_infinite()));
    }
}

/// The source volume seen through the deformed mesh (`camera.shows: source`), against the
/// volume raycaster, an f64 reference mapping each sample exactly, and a fine warp.
mod source_through_mesh {
    use super::*;
    use defvol::mesh::generate::{self, CellSplit};
    use defvol::mesh::TetMesh;
    use defvol::render::mesh::source::{self, SourceSampling};
    use defvol::render::mesh::TetRaycaster;
    use defvol::warp::{self, WarpOptions};
    use std::sync::Arc;

    /// An n³ volume at 1 mm of a smooth field with a bright ball (detail finer than any
    /// tet), and a lattice mesh of `cells`³ on its voxel-centre box.
    fn scan(n: usize, cells: usize) -> (Arc<Volume>, TetMesh) {
        let c = (n - 1) as f64 / 2.0;
        let data = (0..n * n * n)
            .map(|i| {
                let p = Vector3::new((i % n) as f64, ((i / n) % n) as f64, (i / (n * n)) as f64);
                let ball = if (p - Vector3::new(c + 3.0, c - 2.0, c)).norm() < 4.0 { 120.0 } else { 0.0 };
                (100.0 + 60.0 * (p.x * 0.3).sin() * (p.y * 0.25).cos() + 2.0 * p.z + ball) as f32
            })
            .collect();
        let volume = Volume::new([n; 3], [1.0; 3], [0.0; 3], Matrix3::identity(), data, "scan").unwrap();
        let top = (n - 1) as f64;
        let mesh = generate::lattice(Vector3::zeros(), Vector3::repeat(top), [cells; 3], CellSplit::Five).unwrap();
        (Arc::new(volume), mesh)
    }

    fn view(n: usize, size: usize) -> Camera {
        let c = Point3::from(Vector3::repeat((n - 1) as f64 / 2.0));
        Camera::look_at(
            c + Vector3::new(-1.6, -2.6, 1.2) * n as f64,
            c,
            Vector3::z(),
            Projection::Perspective { fov_y_deg: 30.0 },
            size,
            size,
        )
        .unwrap()
    }

    fn tf() -> TransferFunction {
        TransferFunction {
            points: vec![
                TfPoint { value: 0.0, color: [0.0; 3], opacity: 0.0 },
                TfPoint { value: 90.0, color: [0.2, 0.3, 0.9], opacity: 0.0 },
                TfPoint { value: 140.0, color: [1.0, 0.7, 0.3], opacity: 0.06 },
                TfPoint { value: 250.0, color: [1.0, 1.0, 1.0], opacity: 0.3 },
            ],
            relative: false,
        }
    }

    fn as_reference(image: &defvol::render::Rendered) -> Vec<[f64; 4]> {
        image.rgba.chunks_exact(4).map(|p| [0, 1, 2, 3].map(|c| f64::from(p[c]) / 255.0)).collect()
    }

    fn through(
        mesh: &TetMesh,
        volume: &Arc<Volume>,
        positions: &[Vector3<f64>],
        params: &RaycastParams,
        camera: &Camera,
    ) -> defvol::render::Rendered {
        let mut raycaster =
            TetRaycaster::with_source(mesh, volume.clone(), &tf(), params, &SourceSampling::default()).unwrap();
        raycaster.update(positions).unwrap();
        raycaster.render(camera).unwrap()
    }

    #[test]
    fn through_an_undeformed_mesh_the_source_looks_as_the_volume_raycaster_shows_it() {
        let (volume, mesh) = scan(24, 6);
        let camera = view(24, 64);
        for params in [
            RaycastParams::default(),
            RaycastParams { preintegrated: false, shading: Shading::ForwardDifference, ..Default::default() },
            RaycastParams { step: 0.5, shading: Shading::None, empty_space_skipping: false, ..Default::default() },
        ] {
            let image = through(&mesh, &volume, mesh.nodes(), &params, &camera);
            let voxels = volume::raycast(&volume, &camera, &tf(), &params).unwrap();
            assert!(
                voxels.rgba.chunks_exact(4).filter(|p| p[0] > 20).count() > 64 * 64 / 6,
                "the view is nearly empty"
            );
            let (mean, max) = image.errors(&as_reference(&voxels));
            eprintln!("{params:?}: mean {mean:.3}, max {max:.1} levels");
            assert!(mean < 0.5, "mean {mean:.3} levels from the volume raycaster ({params:?})");
        }
    }

    /// A bend no affine map follows: nodes moved by a smooth field.
    fn bend(n: usize) -> impl Fn(&Vector3<f64>) -> Vector3<f64> {
        let c = (n - 1) as f64 / 2.0;
        move |p| p + Vector3::new(0.0, 1.5 * ((p.z - c) / 6.0).sin(), 3.0 * ((p.x - c) / 8.0).sin())
    }

    #[test]
    fn through_a_bent_mesh_the_source_matches_the_exact_map_and_a_fine_warp() {
        let n = 24;
        let (volume, mesh) = scan(n, 6);
        let camera = view(n, 64);
        let bent: Vec<Vector3<f64>> = mesh.nodes().iter().map(bend(n)).collect();
        // A fine step on both paths: what is left is the map (and the warp's resampling).
        let plain = RaycastParams { step: 0.1, shading: Shading::None, early_termination: 1.0, ..Default::default() };
        let reference = source::reference(
            &mesh,
            &bent,
            &volume,
            &camera,
            &tf(),
            &RaycastParams { step: 0.02, ..plain.clone() },
            &[],
        )
        .unwrap();
        assert!(reference.iter().filter(|p| p[0] > 0.1).count() > 64 * 64 / 6, "the view is nearly empty");
        let source = through(&mesh, &volume, &bent, &plain, &camera);
        let (source_mean, source_max) = source.errors(&reference);
        // Warp at a quarter of the source's spacing, then the volume raycaster.
        let coarse = warp::default_grid(&volume, &bent);
        let fine = defvol::volume::Grid {
            dims: coarse.dims.map(|d| 4 * d),
            spacing: [0.25; 3],
            origin: coarse.origin,
            direction: coarse.direction,
        };
        let (warped, _) = warp::warp(&volume, &mesh, &bent, &fine, &WarpOptions::default()).unwrap();
        let warp_image = volume::raycast(&warped, &camera, &tf(), &plain).unwrap();
        let (warp_mean, warp_max) = warp_image.errors(&reference);
        eprintln!("against the f64 map (levels, mean/max): source through the mesh {source_mean:.3}/{source_max:.1}, warp at 0.25 mm then raycast {warp_mean:.3}/{warp_max:.1}");
        assert!(source_mean < 0.5 && source_max < 2.0, "source: mean {source_mean:.3}, max {source_max:.1} levels");
        assert!(warp_mean < 1.0, "warp then raycast: mean {warp_mean:.3} levels");
        // The bend is visible: the undeformed picture is much further off.
        let at_rest = through(&mesh, &volume, mesh.nodes(), &plain, &camera);
        let (rest_mean, _) = at_rest.errors(&reference);
        assert!(rest_mean > 5.0 * source_mean.max(0.1), "the bend barely shows: {rest_mean:.2} levels at rest");
    }

    #[test]
    fn an_affine_deformation_leaves_no_seams_between_tets() {
        let n = 20;
        let (volume, fine) = scan(n, 8);
        let (_, coarse) = scan(n, 1);
        let c = Vector3::repeat((n - 1) as f64 / 2.0);
        let a = Matrix3::new(1.2, 0.25, 0.0, -0.1, 0.9, 0.15, 0.05, 0.0, 1.1);
        let affine = |m: &TetMesh| -> Vec<Vector3<f64>> { m.nodes().iter().map(|p| c + a * (p - c)).collect() };
        let camera = view(n, 64);
        for params in [RaycastParams::default(), RaycastParams { preintegrated: false, ..Default::default() }] {
            let many = through(&fine, &volume, &affine(&fine), &params, &camera);
            let few = through(&coarse, &volume, &affine(&coarse), &params, &camera);
            assert!(many.rgba.chunks_exact(4).filter(|p| p[0] > 20).count() > 64 * 64 / 6, "the view is nearly empty");
            let (mean, max) = many.errors(&as_reference(&few));
            eprintln!(
                "{} tets against {}: mean {mean:.4}, max {max:.1} levels",
                fine.tets().len(),
                coarse.tets().len()
            );
            assert!(mean < 0.05 && max <= 2.0, "seams: mean {mean:.4}, max {max:.1} levels");
        }
    }

    #[test]
    fn bad_input_gives_a_valid_picture_or_a_named_error() {
        let n = 16;
        let (volume, mesh) = scan(n, 4);
        let camera = view(n, 48);
        let params = RaycastParams::default();
        // A mesh in metres over a millimetre volume (and far away): named.
        let mut metres = mesh.clone();
        metres.map_nodes(|p| p * 1e-3 + Vector3::repeat(100.0));
        let e = TetRaycaster::with_source(&metres, volume.clone(), &tf(), &params, &SourceSampling::default())
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("does not reach the volume") && e.contains("units"), "{e}");
        // Iso and MIP are the volume raycaster's modes.
        let e = TetRaycaster::with_source(
            &mesh,
            volume.clone(),
            &tf(),
            &RaycastParams { mode: Mode::Mip, ..Default::default() },
            &SourceSampling::default(),
        )
        .err()
        .unwrap()
        .to_string();
        assert!(e.contains("Mip"), "{e}");
        // Inverted tets after a violent step: a finite picture, no panic.
        let mut violent: Vec<Vector3<f64>> = mesh.nodes().to_vec();
        for (k, p) in violent.iter_mut().enumerate() {
            if k % 3 == 0 {
                *p = Vector3::repeat((n - 1) as f64) - *p;
            }
        }
        let image = through(&mesh, &volume, &violent, &params, &camera);
        assert!(image.depth.iter().all(|d| !d.is_nan()));
        // A mesh covering part of the view: background where it is not.
        let away = Camera::look_at(
            Point3::new(200.0, 200.0, 200.0),
            Point3::new(400.0, 400.0, 400.0),
            Vector3::z(),
            Projection::Perspective { fov_y_deg: 30.0 },
            16,
            16,
        )
        .unwrap();
        let image = through(&mesh, &volume, mesh.nodes(), &params, &away);
        assert!(image.rgba.chunks_exact(4).all(|p| p == [0, 0, 0, 255]) && image.depth.iter().all(|d| d.is_infinite()));
        // Non-finite positions are refused by name.
        let mut raycaster =
            TetRaycaster::with_source(&mesh, volume.clone(), &tf(), &params, &SourceSampling::default()).unwrap();
        let mut nan = mesh.nodes().to_vec();
        nan[3].x = f64::NAN;
        let e = raycaster.update(&nan).err().unwrap().to_string();
        assert!(e.contains("finite"), "{e}");
    }
}

/// The work `bench render --export` writes for the peers: rebuilt as a look-at from its
/// `case.json` (as VTK's camera is), the camera casts defvol's own rays, and the volume and
/// reference arrays hold what the bench used.
#[test]
fn an_exported_render_case_rebuilds_the_same_camera_and_arrays() {
    use defvol::bench::render::{self as bench_render, RenderBenchOptions};
    let dir = tempfile::tempdir().unwrap();
    let opts = RenderBenchOptions {
        sizes: vec![24],
        steps: vec![2.0],
        runs: 1,
        reference_step: 2.0,
        warped: false,
        meshes: Vec::new(),
        source_meshes: Vec::new(),
        gpu: None,
        export: Some(dir.path().to_owned()),
    };
    bench_render::run(&opts, |_| {}).unwrap();
    let case_dir = dir.path().join("phantom_24");
    let case: serde_json::Value = serde_json::from_slice(&std::fs::read(case_dir.join("case.json")).unwrap()).unwrap();
    let point =
        |v: &serde_json::Value| Point3::new(v[0].as_f64().unwrap(), v[1].as_f64().unwrap(), v[2].as_f64().unwrap());
    let cam = &case["camera"];
    let fov_y_deg = cam["fov_y_deg"].as_f64().unwrap();
    let rebuilt = Camera::look_at(
        point(&cam["eye"]),
        point(&cam["focal_point"]),
        point(&cam["up"]).coords,
        Projection::Perspective { fov_y_deg },
        24,
        24,
    )
    .unwrap();
    let source = phantom::phantom(phantom::DEFAULT_DIMS, 1.0).unwrap();
    let camera = bench_render::phantom_camera(&source, 24).unwrap();
    for (px, py) in [(0, 0), (23, 0), (5, 17), (23, 23)] {
        let ((o1, d1), (o2, d2)) = (camera.ray(px, py), rebuilt.ray(px, py));
        assert!((o1 - o2).norm() < 1e-9 && (d1 - d2).norm() < 1e-12, "pixel ({px}, {py}): {d1} against {d2}");
    }
    let volume = std::fs::read(case_dir.join("volume.f32")).unwrap();
    let values: Vec<f32> = volume.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
    assert_eq!(values, source.data());
    let reference = std::fs::read(case_dir.join("reference.f64")).unwrap();
    let expected = volume::reference(
        &source,
        &camera,
        &TransferFunction::preset("ct_soft_tissue").unwrap(),
        2.0,
        [0.0, 0.0, 0.0, 1.0],
    )
    .unwrap();
    let read: Vec<f64> = reference.chunks_exact(8).map(|b| f64::from_le_bytes(b.try_into().unwrap())).collect();
    assert_eq!(read, expected.iter().flatten().copied().collect::<Vec<f64>>());
    assert_eq!(case["dims"], serde_json::json!(source.dims()));
}

/// `bench render` holds the source through the mesh to the volume raycaster frame by frame:
/// each CPU source row's (pre-integrated, point sampled, shaded) `vs_volume_raycast` is
/// the median of its frames' ratios to a volume raycaster frame after each (one a frame,
/// all positive), and no other row carries one.
#[test]
fn the_source_rows_ratio_is_the_median_of_its_frames_against_the_volume_raycaster() {
    use defvol::bench::render::{self as bench_render, RenderBenchOptions};
    let opts = RenderBenchOptions {
        sizes: vec![24],
        steps: vec![3.0],
        runs: 2,
        reference_step: 3.0,
        warped: false,
        meshes: Vec::new(),
        source_meshes: vec![300],
        gpu: None,
        export: None,
    };
    let mut rows = Vec::new();
    bench_render::run(&opts, |row| rows.push((row.case.clone(), row.params.clone(), row.runs))).unwrap();
    let with_ratio: Vec<_> = rows.iter().filter(|(_, p, _)| p.get("vs_volume_raycast").is_some()).collect();
    let sampling: Vec<_> =
        with_ratio.iter().map(|(_, p, _)| (p["preintegrated"].clone(), p["shading"].clone())).collect();
    let row = |preintegrated: bool, shading: &str| (serde_json::json!(preintegrated), serde_json::json!(shading));
    assert_eq!(sampling, [row(true, "none"), row(false, "none"), row(true, "gradient")], "{rows:?}");
    for (case, params, runs) in with_ratio {
        assert!(case.ends_with(" source") && params["mode"] == "source_through_mesh", "{case}");
        let mut pairs: Vec<f64> =
            params["vs_volume_raycast_pairs"].as_array().unwrap().iter().map(|r| r.as_f64().unwrap()).collect();
        assert_eq!(pairs.len(), *runs, "{params}");
        assert!(pairs.iter().all(|r| r.is_finite() && *r > 0.0), "{pairs:?}");
        pairs.sort_by(f64::total_cmp);
        assert_eq!(params["vs_volume_raycast"].as_f64(), Some(pairs[pairs.len() / 2]));
    }
}
