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
use crate::render::tet_raycast::{self, TetRaycastParams, TetRaycaster};
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
    /// Also time the GPU raycasters.
    pub gpu: Option<crate::backend::Backend>,
}

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RenderBenchError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error("preparing the phantom: {0}")]
    Setup(String),
    #[error("GPU frame: {0}")]
    Gpu(String),
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
    let rest =
        generate::lattice_for_box(lo, hi, 700, CellSplit::Five).map_err(|e| RenderBenchError::Setup(e.to_string()))?;
    let bent = WarpCase::Bend.deform(rest.nodes(), (lo + hi) / 2.0, (hi - lo) / 2.0);
    let grid = crate::warp::default_grid(source, &bent);
    let options = crate::warp::WarpOptions { background: source.range().0, ..Default::default() };
    crate::warp::warp(source, &rest, &bent, &grid, &options)
        .map(|(v, _)| v)
        .map_err(|e| RenderBenchError::Setup(e.to_string()))
}

pub fn run(opts: &RenderBenchOptions, mut emit: impl FnMut(&BenchRow)) -> Result<(), RenderBenchError> {
    let device = cpu_description();
    let source = phantom::phantom(phantom::DEFAULT_DIMS, 1.0).map_err(|e| RenderBenchError::Setup(e.to_string()))?;
    let mut volumes = vec![("phantom", source.clone())];
    if opts.warped {
        volumes.push(("phantom_warped", warped_phantom(&source)?));
    }
    let tf = TransferFunction::preset("ct_soft_tissue")?;
    #[cfg(feature = "gpu")]
    let gpu = opts.gpu.as_ref().and_then(crate::backend::Backend::context).cloned();
    for (name, volume) in &volumes {
        for &size in &opts.sizes {
            let camera = phantom_camera(volume, size)?;
            let background = [0.0, 0.0, 0.0, 1.0];
            let reference = raycast::reference(volume, &camera, &tf, opts.reference_step, background)?;
            for &step in &opts.steps {
                for (preintegrated, shading) in
                    [(true, Shading::None), (false, Shading::None), (true, Shading::Gradient)]
                {
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
                    let error = (shading == Shading::None).then(|| ErrorMeasure {
                        metric: "psnr_db",
                        value: image.psnr(&reference),
                        reference: "f64 point sampling",
                    });
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
                    #[cfg(feature = "gpu")]
                    if let (Some(ctx), Shading::None) = (&gpu, shading) {
                        volume_gpu_row(
                            ctx,
                            &raycaster,
                            &camera,
                            &reference,
                            &format!("{name}_{size}"),
                            opts,
                            &mut emit,
                        )?;
                    }
                }
            }
        }
    }
    for &target in &opts.meshes {
        let (lo, hi) = source.bounds();
        let mesh = generate::lattice_for_box(lo, hi, target, CellSplit::Five)
            .map_err(|e| RenderBenchError::Setup(e.to_string()))?;
        let outside = source.range().0;
        let scalars: Vec<f32> = mesh.nodes().iter().map(|p| source.sample_world(*p).unwrap_or(outside)).collect();
        for &size in &opts.sizes {
            let camera = phantom_camera(&source, size)?;
            let background = [0.0, 0.0, 0.0, 1.0];
            // The f64 walk with the exact transfer function; no finer than 0.25 mm, which
            // is already below a level of error at these tet sizes.
            let reference_step = opts.reference_step.max(0.25);
            let reference = tet_raycast::reference(
                &mesh,
                mesh.nodes(),
                &scalars,
                &camera,
                &tf,
                &TetRaycastParams { step: reference_step, background, ..Default::default() },
            )?;
            let case = format!("mesh{}k_{size}", mesh.tets().len() / 1000);
            for &step in &opts.steps {
                for preintegrated in [true, false] {
                    let params = TetRaycastParams { step, preintegrated, background, ..Default::default() };
                    let start = Instant::now();
                    let mut raycaster = TetRaycaster::new(&mesh, &scalars, &tf, &params)?;
                    let prepare_ms = start.elapsed().as_secs_f64() * 1e3;
                    let mut image = raycaster.render(&camera)?;
                    let (mut samples, mut updates) = (Vec::with_capacity(opts.runs), Vec::with_capacity(opts.runs));
                    for _ in 0..opts.runs {
                        // Each frame refreshes planes and gradients, as after a deformation step.
                        let start = Instant::now();
                        raycaster.update(mesh.nodes())?;
                        updates.push(start.elapsed().as_secs_f64() * 1e3);
                        image = raycaster.render(&camera)?;
                        samples.push(start.elapsed().as_secs_f64() * 1e3);
                    }
                    emit(&BenchRow {
                        stage: "render",
                        case: case.clone(),
                        backend: "cpu".into(),
                        device: device.clone(),
                        params: json!({"mode": "tet_mesh", "prepare_ms": prepare_ms, "update_ms": time_stats(updates).median, "step_mm": step, "preintegrated": preintegrated, "shading": "none", "reference_step_mm": reference_step, "tf": "ct_soft_tissue"}),
                        runs: samples.len(),
                        time_ms: time_stats(samples),
                        error: Some(ErrorMeasure {
                            metric: "psnr_db",
                            value: image.psnr(&reference),
                            reference: "f64 tet walk",
                        }),
                        work: json!({"rays": size * size, "tets": mesh.tets().len()}),
                    });
                    #[cfg(feature = "gpu")]
                    if let Some(ctx) = &gpu {
                        mesh_gpu_row(ctx, &raycaster, mesh.nodes(), &camera, &reference, &case, &mut emit)?;
                    }
                }
            }
        }
    }
    Ok(())
}

/// Frames timed on the GPU, read-back included, after one to settle.
#[cfg(feature = "gpu")]
fn gpu_frames(
    runs: usize,
    mut frame: impl FnMut() -> Result<crate::render::Rendered, crate::render::raycast_gpu::GpuRenderError>,
) -> Result<(crate::render::Rendered, Vec<f64>), crate::render::raycast_gpu::GpuRenderError> {
    let mut image = frame()?;
    let mut samples = Vec::with_capacity(runs);
    for _ in 0..runs {
        let start = Instant::now();
        image = frame()?;
        samples.push(start.elapsed().as_secs_f64() * 1e3);
    }
    Ok((image, samples))
}

/// The GPU twin of a CPU volume row: the same prepared tables and macro cells.
#[cfg(feature = "gpu")]
fn volume_gpu_row(
    ctx: &std::sync::Arc<crate::gpu::GpuContext>,
    prepared: &VolumeRaycaster,
    camera: &Camera,
    reference: &[[f64; 4]],
    case: &str,
    opts: &RenderBenchOptions,
    emit: &mut impl FnMut(&BenchRow),
) -> Result<(), RenderBenchError> {
    use crate::render::raycast_gpu::GpuVolumeRaycaster;
    let raycaster = match GpuVolumeRaycaster::new(ctx.clone(), prepared) {
        Ok(r) => r,
        Err(e) => {
            tracing::warn!("GPU raycaster unavailable: {e}");
            return Ok(());
        }
    };
    let (image, samples) =
        gpu_frames(opts.runs, || raycaster.render(camera)).map_err(|e| RenderBenchError::Gpu(e.to_string()))?;
    let params = &prepared.params;
    emit(&BenchRow {
        stage: "render",
        case: case.to_owned(),
        backend: "gpu".into(),
        device: ctx.describe(),
        params: json!({"mode": "composite", "step_mm": params.step, "preintegrated": params.preintegrated, "shading": "none", "reference_step_mm": opts.reference_step, "tf": "ct_soft_tissue", "includes_readback": true}),
        runs: samples.len(),
        time_ms: time_stats(samples),
        error: Some(ErrorMeasure { metric: "psnr_db", value: image.psnr(reference), reference: "f64 point sampling" }),
        work: json!({"rays": camera.width * camera.height, "voxels": prepared.volume.len()}),
    });
    Ok(())
}

/// The GPU twin of a CPU mesh row: positions uploaded and geometry refreshed every frame.
#[cfg(feature = "gpu")]
fn mesh_gpu_row(
    ctx: &std::sync::Arc<crate::gpu::GpuContext>,
    prepared: &TetRaycaster,
    nodes: &[nalgebra::Vector3<f64>],
    camera: &Camera,
    reference: &[[f64; 4]],
    case: &str,
    emit: &mut impl FnMut(&BenchRow),
) -> Result<(), RenderBenchError> {
    use crate::render::tet_raycast_gpu::GpuTetRaycaster;
    let gpu_err = |e: crate::render::raycast_gpu::GpuRenderError| RenderBenchError::Gpu(e.to_string());
    let mut raycaster = match GpuTetRaycaster::new(ctx.clone(), prepared, 1.0) {
        Ok(r) => r,
        Err(e) => {
            tracing::warn!("GPU tet raycaster unavailable: {e}");
            return Ok(());
        }
    };
    let (image, samples) = gpu_frames(3, || {
        raycaster.update(nodes)?;
        raycaster.render(camera)
    })
    .map_err(gpu_err)?;
    emit(&BenchRow {
        stage: "render",
        case: case.to_owned(),
        backend: "gpu".into(),
        device: ctx.describe(),
        params: json!({"mode": "tet_mesh", "step_mm": prepared.params().step, "preintegrated": prepared.params().preintegrated, "shading": "none", "tf": "ct_soft_tissue", "includes_readback": true}),
        runs: samples.len(),
        time_ms: time_stats(samples),
        error: Some(ErrorMeasure { metric: "psnr_db", value: image.psnr(reference), reference: "f64 tet walk" }),
        work: json!({"rays": camera.width * camera.height, "tets": prepared.tets().len()}),
    });
    Ok(())
}

pub const TABLE_HEADER: &str = "case                   backend  step  preint shading     median ms    fps   PSNR dB";

pub fn table_row(row: &BenchRow) -> String {
    let p = &row.params;
    let error = row.error.as_ref().map_or("-".to_owned(), |e| format!("{:.1}", e.value));
    format!(
        "{:<22} {:<7} {:>5} {:>6} {:<10} {:>10.1} {:>6.1} {:>9}",
        row.case,
        row.backend,
        p["step_mm"],
        p["preintegrated"],
        p["shading"].as_str().unwrap_or("?"),
        row.time_ms.median,
        1e3 / row.time_ms.median,
        error
    )
}
