//! `defvol bench render`: the phantom (256x160x122, 1 mm), plain and warped through the
//! bend, at 512² and 1024²: ms per frame and PSNR against the f64 ray integral at a fine
//! step, over steps, with and without pre-integration.

use std::time::Instant;

use nalgebra::{Point3, Vector3};
use serde_json::json;

use super::{cpu_description, time_stats, BenchRow, ErrorMeasure, WarpCase};
use crate::mesh::generate::{self, CellSplit};
use crate::render::camera::{Camera, Projection};
use crate::render::raycast::{self, RaycastParams, Shading, VolumeRaycaster};
use crate::render::transfer::TransferFunction;
use crate::render::RenderError;
use crate::volume::{phantom, Volume};

pub struct RenderBenchOptions {
    pub sizes: Vec<usize>,
    pub steps: Vec<f64>,
    pub runs: usize,
    /// Step of the f64 reference.
    pub reference_step: f64,
    pub warped: bool,
    /// Lattice meshes over the phantom for the tetrahedral-mesh raycaster (tets).
    pub meshes: Vec<usize>,
}

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RenderBenchError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error("preparing the phantom: {0}")]
    Setup(String),
}

/// The benchmark view: from the front-left, above, the whole phantom in frame.
pub fn phantom_camera(volume: &Volume, size: usize) -> Result<Camera, RenderError> {
    let (lo, hi) = volume.bounds();
    let centre = Point3::from((lo + hi) / 2.0);
    let radius = (hi - lo).norm() / 2.0;
    let eye = centre + Vector3::new(-0.45, -1.0, 0.5).normalize() * (radius * 2.6);
    Camera::look_at(eye, centre, Vector3::z(), Projection::Perspective { fov_y_deg: 45.0 }, size, size)
}

fn warped_phantom(source: &Volume) -> Result<Volume, RenderBenchError> {
    let (lo, hi) = source.bounds();
    let rest = generate::lattice_for_box(lo, hi, 700, CellSplit::Five).map_err(|e| RenderBenchError::Setup(e.to_string()))?;
    let bent = WarpCase::Bend.deform(rest.nodes(), (lo + hi) / 2.0, (hi - lo) / 2.0);
    let grid = crate::warp::default_grid(source, &bent);
    let options = crate::warp::WarpOptions { background: source.range().0, ..Default::default() };
    crate::warp::warp(source, &rest, &bent, &grid, &options).map(|(v, _)| v).map_err(|e| RenderBenchError::Setup(e.to_string()))
}

pub fn run(opts: &RenderBenchOptions, mut emit: impl FnMut(&BenchRow)) -> Result<(), RenderBenchError> {
    let device = cpu_description();
    let source = phantom::phantom(phantom::DEFAULT_DIMS, 1.0).map_err(|e| RenderBenchError::Setup(e.to_string()))?;
    let mut volumes = vec![("phantom", source.clone())];
    if opts.warped {
        volumes.push(("phantom_warped", warped_phantom(&source)?));
    }
    let tf = TransferFunction::preset("ct_soft_tissue")?;
    for (name, volume) in &volumes {
        for &size in &opts.sizes {
            let camera = phantom_camera(volume, size)?;
            let background = [0.0, 0.0, 0.0, 1.0];
            let reference = raycast::reference(volume, &camera, &tf, opts.reference_step, background)?;
            for &step in &opts.steps {
                for (preintegrated, shading) in [(true, Shading::None), (false, Shading::None), (true, Shading::Gradient)] {
                    let params = RaycastParams { step, preintegrated, shading, background, ..Default::default() };
                    // Preparing (tables, macro cells) happens once per transfer function and
                    // step, not per frame: timed apart.
                    let start = Instant::now();
                    let raycaster = VolumeRaycaster::new(volume, &tf, &params)?;
                    let prepare_ms = start.elapsed().as_secs_f64() * 1e3;
                    // Settle: the first frame warms the caches.
                    let mut image = raycaster.render(&camera)?;
                    let mut samples = Vec::with_capacity(opts.runs);
                    for _ in 0..opts.runs {
                        let start = Instant::now();
                        image = raycaster.render(&camera)?;
                        samples.push(start.elapsed().as_secs_f64() * 1e3);
                    }
                    // The reference is unshaded: shaded rows are timed only.
                    let error = (shading == Shading::None).then(|| ErrorMeasure { metric: "psnr_db", value: image.psnr(&reference), reference: "f64 point sampling" });
                    emit(&BenchRow {
                        stage: "render",
                        case: format!("{name}_{size}"),
                        backend: "cpu".into(),
                        device: device.clone(),
                        params: json!({"mode": "composite", "prepare_ms": prepare_ms, "step_mm": step, "preintegrated": preintegrated, "shading": shading, "reference_step_mm": opts.reference_step, "tf": "ct_soft_tissue"}),
                        runs: samples.len(),
                        time_ms: time_stats(samples),
                        error,
                        work: json!({"rays": size * size, "voxels": volume.len()}),
                    });
                }
            }
        }
    }
    for &target in &opts.meshes {
        let (lo, hi) = source.bounds();
        let mesh = generate::lattice_for_box(lo, hi, target, CellSplit::Five).map_err(|e| RenderBenchError::Setup(e.to_string()))?;
        let outside = source.range().0;
        let scalars: Vec<f32> = mesh.nodes().iter().map(|p| source.sample_world(*p).unwrap_or(outside)).collect();
        for &size in &opts.sizes {
            let camera = phantom_camera(&source, size)?;
            let step = opts.steps.iter().copied().fold(f64::INFINITY, f64::min).max(0.25);
            let params = crate::render::tet_raycast::TetRaycastParams { step, ..Default::default() };
            let start = Instant::now();
            let mut raycaster = crate::render::tet_raycast::TetRaycaster::new(&mesh, &scalars, &tf, &params)?;
            let prepare_ms = start.elapsed().as_secs_f64() * 1e3;
            raycaster.render(&camera)?;
            let mut samples = Vec::with_capacity(opts.runs);
            for _ in 0..opts.runs {
                // Each frame refreshes planes and gradients, as after a deformation step.
                let start = Instant::now();
                raycaster.update(mesh.nodes())?;
                raycaster.render(&camera)?;
                samples.push(start.elapsed().as_secs_f64() * 1e3);
            }
            emit(&BenchRow {
                stage: "render",
                case: format!("mesh{}k_{size}", mesh.tets().len() / 1000),
                backend: "cpu".into(),
                device: device.clone(),
                params: json!({"mode": "tet_mesh", "prepare_ms": prepare_ms, "step_mm": step, "preintegrated": false, "shading": "none", "tf": "ct_soft_tissue"}),
                runs: samples.len(),
                time_ms: time_stats(samples),
                error: None,
                work: json!({"rays": size * size, "tets": mesh.tets().len()}),
            });
        }
    }
    Ok(())
}

pub const TABLE_HEADER: &str = "case                   step  preint shading     median ms    fps   PSNR dB";

pub fn table_row(row: &BenchRow) -> String {
    let p = &row.params;
    let error = row.error.as_ref().map_or("-".to_owned(), |e| format!("{:.1}", e.value));
    format!(
        "{:<22} {:>5} {:>6} {:<10} {:>10.1} {:>6.1} {:>9}",
        row.case,
        p["step_mm"],
        p["preintegrated"],
        p["shading"].as_str().unwrap_or("?"),
        row.time_ms.median,
        1e3 / row.time_ms.median,
        error
    )
}
