//! Grid warp against independent references: the source itself (identity), analytic affine
//! resampling, an f64 path, and per-voxel point-in-tet tests from the vertex positions.

use defvol::mesh::generate::{self, CellSplit};
use defvol::mesh::TetMesh;
use defvol::volume::{phantom, Grid, Volume};
use defvol::warp::{self, DisplacementVolume, IncrementalWarp, Sampling, Scheme, WarpError, WarpOptions};
use nalgebra::{Matrix3, Rotation3, Vector3};

const OUTSIDE: f32 = -12345.0;

fn source() -> Volume {
    phantom::phantom([48, 32, 26], 5.0).unwrap()
}

/// A lattice embedding the source's voxel-centre box, in the source's units (mm).
fn box_mesh(v: &Volume, tets: usize) -> TetMesh {
    let (lo, hi) = v.bounds();
    generate::lattice_for_box(lo, hi, tets, CellSplit::Five).unwrap()
}

fn options(scheme: Scheme) -> WarpOptions {
    WarpOptions { scheme, background: OUTSIDE, ..Default::default() }
}

#[test]
fn identity_reproduces_the_source_inside_the_mesh() {
    let v = source();
    let mesh = box_mesh(&v, 700);
    let grid = warp::default_grid(&v, mesh.nodes());
    assert_eq!(grid, v.grid(), "default grid snaps to the source lattice");
    let (out, stats) = warp::warp(&v, &mesh, mesh.nodes(), &grid, &options(Scheme::Spans)).unwrap();
    let (lo, hi) = v.range();
    let worst = out.data().iter().zip(v.data()).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(worst <= 1e-5 * (hi - lo), "identity differs by {worst}");
    assert!(stats.inside >= v.len() as u64, "every voxel covered: {stats:?}");
}

fn affine() -> (Matrix3<f64>, Vector3<f64>) {
    let r = Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_4)
        * Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_4);
    (r.into_inner() * Matrix3::from_diagonal(&Vector3::new(1.1, 0.9, 1.0)), Vector3::new(7.0, -3.0, 2.5))
}

#[test]
fn affine_deformation_matches_analytic_resampling_for_every_scheme() {
    let v = source();
    let mesh = box_mesh(&v, 700);
    let (a, t) = affine();
    let deformed: Vec<Vector3<f64>> = mesh.nodes().iter().map(|p| a * p + t).collect();
    let grid = warp::default_grid(&v, &deformed);
    let a_inv = a.try_inverse().unwrap();
    let (lo, hi) = v.range();
    let mut results = Vec::new();
    for scheme in [Scheme::Spans, Scheme::Culling, Scheme::Bbox] {
        let (out, stats) = warp::warp(&v, &mesh, &deformed, &grid, &options(scheme)).unwrap();
        let mut checked = 0;
        for k in 0..grid.dims[2] {
            for j in 0..grid.dims[1] {
                for i in 0..grid.dims[0] {
                    let value = out.data()[i + grid.dims[0] * (j + grid.dims[1] * k)];
                    if value == OUTSIDE {
                        continue;
                    }
                    let x1 = grid.world_from_index(Vector3::new(i as f64, j as f64, k as f64));
                    let expected = v.sample_world(a_inv * (x1 - t)).unwrap();
                    assert!(
                        (value - expected).abs() <= 1e-5 * (hi - lo),
                        "{scheme:?} voxel ({i},{j},{k}): {value} vs {expected}"
                    );
                    checked += 1;
                }
            }
        }
        assert!(
            checked as u64 == stats.inside.min(checked as u64) && checked > 10_000,
            "{scheme:?}: {checked} {stats:?}"
        );
        results.push((out, stats));
    }
    // Same decisions and values whatever the scheme; culling tests fewer voxels than the box.
    assert_eq!(results[0].0.data(), results[1].0.data());
    assert_eq!(results[0].0.data(), results[2].0.data());
    let (spans, culling, bbox) = (results[0].1, results[1].1, results[2].1);
    assert_eq!(spans.inside, culling.inside);
    assert_eq!(spans.inside, bbox.inside);
    assert!(
        spans.candidates < culling.candidates && culling.candidates <= bbox.candidates,
        "{spans:?} {culling:?} {bbox:?}"
    );
}

#[test]
fn culling_skips_cells_of_large_tets() {
    // 80 tets over the volume: tets span ~20 voxels, several 8³ cells each.
    let v = source();
    let mesh = box_mesh(&v, 80);
    let grid = v.grid();
    let (_, culling) = warp::warp(&v, &mesh, mesh.nodes(), &grid, &options(Scheme::Culling)).unwrap();
    let (_, bbox) = warp::warp(&v, &mesh, mesh.nodes(), &grid, &options(Scheme::Bbox)).unwrap();
    assert_eq!(culling.inside, bbox.inside);
    let (useful_culling, useful_bbox) =
        (culling.inside as f64 / culling.candidates as f64, bbox.inside as f64 / bbox.candidates as f64);
    assert!(useful_culling > 1.2 * useful_bbox, "useful fraction: culling {useful_culling:.3}, box {useful_bbox:.3}");
}

/// Barycentric coordinates of `p` in the tet by solving its 4x4 system from the vertices.
fn barycentric(v: [Vector3<f64>; 4], p: Vector3<f64>) -> [f64; 4] {
    let m = nalgebra::Matrix4::new(
        v[0].x, v[1].x, v[2].x, v[3].x, v[0].y, v[1].y, v[2].y, v[3].y, v[0].z, v[1].z, v[2].z, v[3].z, 1.0, 1.0, 1.0,
        1.0,
    );
    let b = m.lu().solve(&nalgebra::Vector4::new(p.x, p.y, p.z, 1.0)).unwrap();
    [b[0], b[1], b[2], b[3]]
}

#[test]
fn f32_path_is_within_bound_of_f64_and_inside_decisions_match_point_in_tet() {
    let v = source();
    let mesh = box_mesh(&v, 300);
    // A smooth bend: nodes displaced along z by a parabola in x.
    let deformed: Vec<Vector3<f64>> =
        mesh.nodes().iter().map(|p| p + Vector3::new(0.0, 0.1 * p.z, 0.002 * p.x * p.x)).collect();
    let grid = warp::default_grid(&v, &deformed);
    let opts = options(Scheme::Spans);
    let (fast, _) = warp::warp_samples::<f32>(&v, &mesh, &deformed, &grid, &opts).unwrap();
    let (reference, _) = warp::warp_samples::<f64>(&v, &mesh, &deformed, &grid, &opts).unwrap();
    let (lo, hi) = v.range();
    let worst = fast.iter().zip(&reference).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max);
    assert!(worst <= 2e-6 * (hi - lo) as f64, "f32 vs f64: {worst}");
    // Inside/outside against an independent per-voxel point-in-tet test.
    let mut disagreements = 0;
    for k in 0..grid.dims[2] {
        for j in 0..grid.dims[1] {
            for i in 0..grid.dims[0] {
                let p = grid.world_from_index(Vector3::new(i as f64, j as f64, k as f64));
                let mut inside = false;
                let mut tie = false;
                for t in mesh.tets() {
                    let b = barycentric(t.map(|n| deformed[n as usize]), p);
                    let min = b.iter().copied().fold(f64::INFINITY, f64::min);
                    inside |= min >= 0.0;
                    tie |= min.abs() < 1e-9;
                }
                let ours = reference[i + grid.dims[0] * (j + grid.dims[1] * k)] != OUTSIDE as f64;
                if ours != inside && !tie {
                    disagreements += 1;
                }
            }
        }
    }
    assert_eq!(disagreements, 0);
}

/// An incremental warp of `v` through `mesh` at rest onto `grid`.
fn incremental(v: &Volume, mesh: &TetMesh, grid: &Grid, opts: &WarpOptions) -> IncrementalWarp {
    IncrementalWarp::new(
        std::sync::Arc::new(v.clone()),
        std::sync::Arc::new(mesh.clone()),
        mesh.nodes(),
        grid.clone(),
        opts.clone(),
    )
    .unwrap()
}

#[test]
fn incremental_update_equals_a_full_warp() {
    let v = source();
    let mesh = box_mesh(&v, 700);
    let grid = warp::default_grid(&v, mesh.nodes());
    let opts = WarpOptions { keep_uncovered: true, ..options(Scheme::Spans) };
    let mut inc = incremental(&v, &mesh, &grid, &opts);
    let mut out = vec![0f32; grid.len()];
    assert_eq!(inc.write_into(&mut out, None).unwrap().voxels, grid.len() as u64, "a fresh buffer is warped whole");
    // A tool presses locally: nodes near one point move.
    let tip = Vector3::new(20.0, 10.0, 60.0);
    let pressed: Vec<Vector3<f64>> = mesh
        .nodes()
        .iter()
        .map(|p| {
            let d = (p - tip).norm();
            if d < 30.0 {
                p - Vector3::z() * (6.0 * (1.0 - d / 30.0))
            } else {
                *p
            }
        })
        .collect();
    let sequence = inc.advance(&pressed, 1e-9).unwrap();
    let stats = inc.write_into(&mut out, Some(sequence - 1)).unwrap();
    assert!(stats.voxels > 0 && stats.voxels < grid.len() as u64 / 4, "local region: {stats:?}");
    let (full, _) = warp::warp(&v, &mesh, &pressed, &grid, &opts).unwrap();
    assert_eq!(out, full.data());
    let again = inc.advance(&pressed, 1e-9).unwrap();
    assert_eq!(inc.write_into(&mut out, Some(again - 1)).unwrap().voxels, 0, "nothing moved, nothing done");
}

/// Motion below the tolerance leaves the warp as it was (a volume held through it is
/// still this warp's, to the bit) until it adds up past the tolerance; then the volume is
/// the full warp of where the nodes were placed.
#[test]
fn drift_below_the_tolerance_changes_nothing_until_it_adds_up() {
    let v = source();
    let mesh = box_mesh(&v, 700);
    let grid = warp::default_grid(&v, mesh.nodes());
    let opts = options(Scheme::Spans);
    let mut inc = incremental(&v, &mesh, &grid, &opts);
    let mut held = vec![0f32; grid.len()];
    inc.write_into(&mut held, None).unwrap();
    let tolerance = 0.01;
    // Every node creeps 0.6 of the tolerance a step (the solver's jitter, a slow sag).
    let crept = |steps: f64| -> Vec<Vector3<f64>> {
        mesh.nodes().iter().map(|p| p - Vector3::z() * (0.6 * tolerance * steps)).collect()
    };
    let first = inc.advance(&crept(1.0), tolerance).unwrap();
    let mut fresh = vec![0f32; grid.len()];
    inc.write_into(&mut fresh, None).unwrap();
    assert_eq!(fresh, held, "below the tolerance, a whole new warp is the warp held");
    assert_eq!(inc.write_into(&mut held, Some(first - 1)).unwrap().voxels, 0);
    let second = inc.advance(&crept(2.0), tolerance).unwrap();
    assert!(inc.write_into(&mut held, Some(second - 1)).unwrap().voxels > 0, "1.2 tolerances moved it");
    let (full, _) = warp::warp(&v, &mesh, &crept(2.0), &grid, &opts).unwrap();
    assert_eq!(held, full.data());
}

#[test]
fn inverted_tets_are_skipped_and_counted() {
    let v = source();
    let mesh = box_mesh(&v, 80);
    let mut deformed = mesh.nodes().to_vec();
    let t = mesh.tets()[7];
    // Push one vertex through the opposite face.
    let face_centre = (deformed[t[1] as usize] + deformed[t[2] as usize] + deformed[t[3] as usize]) / 3.0;
    deformed[t[0] as usize] = face_centre * 2.0 - deformed[t[0] as usize];
    let grid = warp::default_grid(&v, &deformed);
    let (_, stats) = warp::warp(&v, &mesh, &deformed, &grid, &options(Scheme::Spans)).unwrap();
    assert!(stats.skipped_tets >= 1, "{stats:?}");
}

#[test]
fn bad_input_is_refused_with_a_reason() {
    let v = source();
    let mesh = box_mesh(&v, 80);
    let grid = v.grid();
    let e = warp::warp(&v, &mesh, &mesh.nodes()[1..], &grid, &WarpOptions::default()).unwrap_err();
    assert!(matches!(e, WarpError::NodeCount { .. }), "{e}");
    let mut nan = mesh.nodes().to_vec();
    nan[3].x = f64::NAN;
    assert!(matches!(
        warp::warp(&v, &mesh, &nan, &grid, &WarpOptions::default()).unwrap_err(),
        WarpError::NonFiniteNode { node: 3 }
    ));
    let huge = Grid { dims: [4000, 4000, 4000], ..grid.clone() };
    let e = warp::warp(&v, &mesh, mesh.nodes(), &huge, &WarpOptions::default()).unwrap_err();
    assert!(e.to_string().contains("MiB"), "{e}");
    let folding = WarpOptions {
        displacements: vec![DisplacementVolume { centre: [0.0; 3], displacement: [0.0, 0.0, 30.0], extent: 20.0 }],
        ..Default::default()
    };
    assert!(matches!(
        warp::warp(&v, &mesh, mesh.nodes(), &grid, &folding).unwrap_err(),
        WarpError::BadDisplacement { index: 0, .. }
    ));
}

#[test]
fn tricubic_beats_trilinear_on_a_smooth_field() {
    // A smooth analytic field sampled coarsely, then resampled at the offsets of a shift.
    let dims = [24, 24, 24];
    let f = |p: Vector3<f64>| (p.x * 0.35).sin() * (p.y * 0.3).cos() + (p.z * 0.25).sin();
    let data: Vec<f32> = (0..dims[0] * dims[1] * dims[2])
        .map(|n| f(Vector3::new((n % 24) as f64, ((n / 24) % 24) as f64, (n / 576) as f64)) as f32)
        .collect();
    let v = Volume::new(dims, [1.0; 3], [0.0; 3], Matrix3::identity(), data, "field").unwrap();
    let mesh = generate::lattice(Vector3::repeat(2.0), Vector3::repeat(21.0), [3, 3, 3], CellSplit::Five).unwrap();
    let shift = Vector3::new(0.37, -0.21, 0.43);
    let deformed: Vec<Vector3<f64>> = mesh.nodes().iter().map(|p| p + shift).collect();
    let grid = warp::default_grid(&v, &deformed);
    let mut errors = Vec::new();
    for sampling in [Sampling::Trilinear, Sampling::Tricubic] {
        let opts = WarpOptions { sampling, background: OUTSIDE, ..Default::default() };
        let (out, _) = warp::warp(&v, &mesh, &deformed, &grid, &opts).unwrap();
        let mut worst: f64 = 0.0;
        for (n, value) in out.data().iter().enumerate() {
            if *value == OUTSIDE {
                continue;
            }
            let ijk = Vector3::new(
                (n % grid.dims[0]) as f64,
                ((n / grid.dims[0]) % grid.dims[1]) as f64,
                (n / (grid.dims[0] * grid.dims[1])) as f64,
            );
            worst = worst.max((*value as f64 - f(grid.world_from_index(ijk) - shift)).abs());
        }
        errors.push(worst);
    }
    assert!(errors[1] < 0.5 * errors[0], "tricubic {:e} vs trilinear {:e}", errors[1], errors[0]);
}

#[test]
fn displacement_volume_moves_content_by_its_vector() {
    let v = source();
    let d = DisplacementVolume { centre: [12.5, 2.5, 2.5], displacement: [0.0, 0.0, 8.0], extent: 40.0 };
    let opts = WarpOptions { displacements: vec![d], ..Default::default() };
    let out = warp::displace(&v, &v.grid(), &opts).unwrap();
    let c = Vector3::from(d.centre);
    let at_centre = out.sample_world(c).unwrap();
    let expected = v.sample_world(c - Vector3::from(d.displacement)).unwrap();
    // The output lattice holds the exact values; between voxels it is interpolated.
    let idx = v.index_from_world(c);
    assert!(idx.iter().all(|x| (x - x.round()).abs() < 1e-9), "centre on a voxel");
    assert!((at_centre - expected).abs() < 1e-3, "{at_centre} vs {expected}");
    // Far away: untouched.
    let far = Vector3::new(-100.0, -60.0, -50.0);
    assert_eq!(out.sample_world(far), v.sample_world(far));
}
