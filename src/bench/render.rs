//! `defvol bench render`: the phantom (256x160x122, 1 mm), plain and warped through the
//! bend, at 512² and 1024²: ms per frame and PSNR against the f64 ray integral at a fine
//! step, over steps, with and without pre-integration; the tet raycaster; and the bent
//! phantom seen through the mesh (`shows: source`) beside the warp + volume raycast it
//! replaces, per backend, against the f64 reference that maps each sample exactly.

use std::time::Instant;

use nalgebra::{Point3, Vector3};
use serde_json::json;

use super::{cpu_description, time_stats, BenchRow, ErrorMeasure, WarpCase};
use crate::backend::RunsOn;
use crate::mesh::generate::{self, CellSplit};
use crate::render::camera::{Camera, Projection};
use crate::render::mesh::{self, TetRaycastParams, TetRaycaster};
use crate::render::transfer::TransferFunction;
use crate::render::volume::{self, RaycastParams, Shading, VolumeRaycaster};
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
    /// Lattice meshes bending the phantom: the source through the mesh beside warp + raycast.
    pub source_meshes: Vec<usize>,
    /// Also time the GPU raycasters.
    pub gpu: Option<crate::backend::Backend>,
    /// Write each volume case's work (volume, camera, transfer function, reference) into
    /// this folder for the peers in benches/peers/.
    pub export: Option<std::path::PathBuf>,
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
            let reference = volume::reference(volume, &camera, &tf, opts.reference_step, background)?;
            if let Some(dir) = &opts.export {
                let work = VolumeWork { volume, camera: &camera, tf: &tf, background, steps: &opts.steps };
                export_case(&dir.join(format!("{name}_{size}")), &work, &reference)
                    .map_err(|e| RenderBenchError::Setup(format!("export into {}: {e}", dir.display())))?;
            }
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
                    let runs = samples.len();
                    let time_ms = time_stats(samples);
                    emit(&BenchRow {
                        stage: "render",
                        case: format!("{name}_{size}"),
                        backend: "cpu".into(),
                        device: device.clone(),
                        params: json!({"mode": "composite", "prepare_ms": prepare_ms, "step_mm": step, "preintegrated": preintegrated, "shading": shading, "reference_step_mm": opts.reference_step, "tf": "ct_soft_tissue"}),
                        runs,
                        time_ms,
                        error,
                        work: json!({"rays": size * size, "voxels": volume.len()}),
                        gpu: None,
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
            let reference = mesh::reference(
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
                        gpu: None,
                    });
                    #[cfg(feature = "gpu")]
                    if let Some(ctx) = &gpu {
                        mesh_gpu_row(ctx, &raycaster, mesh.nodes(), &camera, &reference, &case, &mut emit)?;
                    }
                }
            }
        }
    }
    for &target in &opts.source_meshes {
        source_rows(&source, target, &tf, opts, &mut emit)?;
    }
    Ok(())
}

/// One volume frame's inputs, as a peer needs them.
struct VolumeWork<'a> {
    volume: &'a Volume,
    camera: &'a Camera,
    tf: &'a TransferFunction,
    background: [f64; 4],
    steps: &'a [f64],
}

/// Writes a volume frame's work as raw little-endian arrays and a `case.json`: the volume
/// (f32, x fastest), the f64 reference image (RGBA per pixel, rows top to bottom), and the
/// camera as a look-at (eye, focal point, up, vertical field of view), the transfer function
/// resolved to the volume's values, the steps and the background.
fn export_case(dir: &std::path::Path, work: &VolumeWork, reference: &[[f64; 4]]) -> Result<(), String> {
    let camera = work.camera;
    let Projection::Perspective { fov_y_deg } = camera.projection else {
        return Err("only perspective cameras are exported".into());
    };
    let grid = work.volume.grid();
    if (grid.direction - nalgebra::Matrix3::identity()).abs().max() > 1e-12 {
        return Err("an oblique volume: the peers take axis-aligned grids".into());
    }
    let pose = &camera.world_from_camera;
    let eye = Point3::from(pose.translation.vector);
    let (lo, hi) = work.volume.bounds();
    let distance = (Point3::from((lo + hi) / 2.0) - eye).norm();
    // The optical frame: z forward, y down the picture.
    let focal_point = eye + pose.rotation * Vector3::z() * distance;
    let up = -(pose.rotation * Vector3::y());
    let tf = work.tf.resolve(work.volume.range()).map_err(|e| e.to_string())?;
    let case = json!({
        "case": dir.file_name().map(|n| n.to_string_lossy().into_owned()),
        "dims": work.volume.dims(), "spacing": grid.spacing, "origin": grid.origin,
        "camera": {"eye": eye.coords.as_slice(), "focal_point": focal_point.coords.as_slice(), "up": up.as_slice(), "fov_y_deg": fov_y_deg},
        "width": camera.width, "height": camera.height, "steps": work.steps, "background": work.background,
        "tf": tf.points,
    });
    let volume: Vec<u8> = work.volume.data().iter().flat_map(|v| v.to_le_bytes()).collect();
    let reference: Vec<u8> = reference.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
    let write = |name: &str, data: &[u8]| std::fs::write(dir.join(name), data).map_err(|e| format!("{name}: {e}"));
    std::fs::create_dir_all(dir).map_err(|e| e.to_string())?;
    write("volume.f32", &volume)?;
    write("reference.f64", &reference)?;
    write("case.json", case.to_string().as_bytes())
}

/// The phantom bent through a `target`-tet lattice at each size and step: per frame (the
/// mesh moving every frame, between the bend and 95 % of it) the source through the mesh
/// (update + frame; pre-integrated and point sampled) and the warp + volume raycast it
/// replaces (the whole volume warped, then a frame), on the CPU and on the GPU when asked;
/// PSNR of the last frame (the full bend) against the f64 reference that maps each sample
/// exactly. The CPU source rows' `vs_volume_raycast` is the median of their frames' times
/// over a volume raycaster frame after each (the source, the same sampling, step and
/// camera): the figure the source path is held to.
fn source_rows(
    source: &Volume,
    target: usize,
    tf: &TransferFunction,
    opts: &RenderBenchOptions,
    emit: &mut impl FnMut(&BenchRow),
) -> Result<(), RenderBenchError> {
    use crate::backend::Backend;
    use crate::render::engine::{MeshRenderer, Shown, VolumeRenderer};
    use crate::render::mesh::source::{self, SourceSampling};
    use crate::warp::engine::WarpEngine;
    use std::sync::Arc;

    let setup = |e: &dyn std::fmt::Display| RenderBenchError::Setup(e.to_string());
    let (lo, hi) = source.bounds();
    let rest = Arc::new(generate::lattice_for_box(lo, hi, target, CellSplit::Five).map_err(|e| setup(&e))?);
    let (centre, half) = ((lo + hi) / 2.0, (hi - lo) / 2.0);
    let bent = WarpCase::Bend.deform(rest.nodes(), centre, half);
    let less: Vec<Vector3<f64>> = rest.nodes().iter().zip(&bent).map(|(r, b)| r + (b - r) * 0.95).collect();
    // The grid the node warps onto: the source's spacing over the deformed box.
    let grid = crate::warp::default_grid(source, &bent);
    let half_grid = crate::volume::Grid {
        dims: grid.dims.map(|d| 2 * d - 1),
        spacing: grid.spacing.map(|s| s / 2.0),
        ..grid.clone()
    };
    let shared = Arc::new(source.clone());
    let mut backends = vec![(Backend::cpu(), cpu_description())];
    if let Some(gpu) = &opts.gpu {
        backends.push((gpu.clone(), gpu.describe()));
    }
    let case = |size: usize| format!("bend{}k_{size}", rest.tets().len() / 1000);
    for &size in &opts.sizes {
        let camera = phantom_camera(source, size)?;
        let background = [0.0, 0.0, 0.0, 1.0];
        let reference_step = opts.reference_step.max(0.25);
        let reference = source::reference(
            &rest,
            &bent,
            source,
            &camera,
            tf,
            &RaycastParams { step: reference_step, background, ..Default::default() },
            &[],
        )?;
        for &step in &opts.steps {
            let params =
                RaycastParams { step, preintegrated: true, shading: Shading::None, background, ..Default::default() };
            // The volume raycaster's tables over the source's values (0.1-0.4 s each), made
            // once for the source row's paired frames and the warped volumes alike.
            let tables = Arc::new(VolumeRaycaster::tables_for(source.range(), tf, &params)?);
            let point = RaycastParams { preintegrated: false, ..params.clone() };
            let point_tables = Arc::new(VolumeRaycaster::tables_for(source.range(), tf, &point)?);
            for (backend, device) in &backends {
                let frames = [&less, &bent];
                // The source through the mesh, pre-integrated and point sampled, and
                // pre-integrated with gradient shading (the node's default; timed only).
                for (preintegrated, shading) in
                    [(true, Shading::None), (false, Shading::None), (true, Shading::Gradient)]
                {
                    let params = RaycastParams { preintegrated, shading, ..params.clone() };
                    let prepared =
                        TetRaycaster::with_source(&rest, shared.clone(), tf, &params, &SourceSampling::default())?;
                    let mut mesh = MeshRenderer::new(backend, prepared, 1.0).map_err(|e| setup(&e))?;
                    let on = mesh.runs_on();
                    let mut frame = |k: usize| -> Result<crate::render::Rendered, RenderBenchError> {
                        mesh.update(frames[k % 2]).map_err(|e| setup(&e))?;
                        mesh.render(&[], &camera).map_err(|e| setup(&e))
                    };
                    let row = |samples, image: &_| {
                        source_row(&case(size), on, device, "source_through_mesh", &params, samples, image, &reference)
                    };
                    if on == RunsOn::Cpu {
                        // Held to the volume raycaster on the source at the same settings, a
                        // frame of it after each of this row's.
                        let tables = if preintegrated { &tables } else { &point_tables };
                        let volume = VolumeRaycaster::with_tables(source, tables.clone(), &params)?;
                        let mut against = || volume.render(&camera).map(|_| ()).map_err(RenderBenchError::from);
                        let (image, samples, ratios) = timed_against(opts.runs, &mut frame, &mut against)?;
                        let mut row = row(samples, &image);
                        row.params["vs_volume_raycast"] = json!(time_stats(ratios.clone()).median);
                        row.params["vs_volume_raycast_pairs"] = json!(ratios);
                        emit(&row);
                    } else {
                        let (image, samples, cost) = timed(opts.runs, (backend, on), &mut frame)?;
                        emit(&BenchRow { gpu: cost, ..row(samples, &image) });
                    }
                }
                // Warp + volume raycast: onto the source's spacing (what the node does),
                // and onto half of it (what it takes to come near the source's accuracy).
                for (mode, warp_grid) in [("warp_then_raycast", &grid), ("warp_half_then_raycast", &half_grid)] {
                    let warp = WarpEngine::new(
                        backend,
                        shared.clone(),
                        rest.clone(),
                        warp_grid.clone(),
                        crate::warp::WarpOptions { background: source.range().0, ..Default::default() },
                        1.0,
                        0.0,
                    );
                    let mut warp = match warp {
                        Ok(warp) => warp,
                        // A grid over the adapter's buffer limit: no row, as for the others.
                        Err(e) if backend.runs_on() == RunsOn::Gpu => {
                            tracing::warn!("no {mode} row on {device}: {e}");
                            continue;
                        }
                        Err(e) => return Err(setup(&e)),
                    };
                    let warped_grid = warp.grid().clone();
                    let mut host = Volume::from_grid(&warped_grid, vec![0.0; warped_grid.len()], "warped volume")
                        .map_err(|e| setup(&e))?;
                    #[cfg(feature = "gpu")]
                    let on_device = match (warp.device_output(), backend.context()) {
                        (Some(samples), Some(ctx)) => Some(
                            // The warped grid's device buffer (`host` only lends its grid).
                            VolumeRenderer::on_device(ctx.clone(), samples.clone(), &host, &tables, &params)
                                .map_err(|e| setup(&e))?,
                        ),
                        _ => None,
                    };
                    #[cfg(not(feature = "gpu"))]
                    let on_device: Option<VolumeRenderer> = None;
                    let mut volume = match on_device {
                        Some(v) => v,
                        None => VolumeRenderer::new(&Backend::cpu(), &host, tables.clone(), &params)
                            .map_err(|e| setup(&e))?,
                    };
                    let on = warp.runs_on();
                    let mut frame = |k: usize| -> Result<crate::render::Rendered, RenderBenchError> {
                        let u: Vec<Vector3<f64>> = frames[k % 2].iter().zip(rest.nodes()).map(|(p, r)| p - r).collect();
                        warp.advance(Some(&u)).map_err(|e| setup(&e))?;
                        if volume.runs_on() == RunsOn::Gpu {
                            volume.volume_changed();
                            volume.render(Shown::Device, &[], &camera).map_err(|e| setup(&e))
                        } else {
                            warp.write_into(host.data_mut(), None).map_err(|e| setup(&e))?;
                            volume.render(Shown::Host(&host), &[], &camera).map_err(|e| setup(&e))
                        }
                    };
                    let (image, samples, cost) = timed(opts.runs, (backend, on), &mut frame)?;
                    let row = source_row(&case(size), on, device, mode, &params, samples, &image, &reference);
                    emit(&BenchRow { gpu: cost, ..row });
                }
            }
        }
    }
    Ok(())
}

/// `2·runs` frames after one to settle, each timed, with their GPU cost when the stage runs
/// `on` the backend's GPU; every frame moves the mesh (even k the partial bend, odd k the
/// full one). The image is the last full bend's.
fn timed(
    runs: usize,
    (backend, on): (&crate::backend::Backend, RunsOn),
    frame: &mut impl FnMut(usize) -> Result<crate::render::Rendered, RenderBenchError>,
) -> Result<(crate::render::Rendered, Vec<f64>, Option<super::GpuCost>), RenderBenchError> {
    let settled = frame(1)?;
    let meter = super::GpuMeter::start(backend, on);
    let (image, samples) = timed_frames(runs, settled, frame, |_| Ok(()))?;
    let cost = meter.and_then(|m| m.finish(samples.len()));
    Ok((image, samples, cost))
}

/// [`timed`] on the CPU with a frame of `against` right after each frame (timed apart):
/// the image, the frames' times and each frame's time over the next `against`'s. On a
/// shared host whose speed drifts by up to 1.7x between runs, the pairs' median moved less
/// than two medians taken minutes apart (three runs: 2.17-2.54x against 1.95-2.65x).
fn timed_against(
    runs: usize,
    frame: &mut impl FnMut(usize) -> Result<crate::render::Rendered, RenderBenchError>,
    against: &mut impl FnMut() -> Result<(), RenderBenchError>,
) -> Result<(crate::render::Rendered, Vec<f64>, Vec<f64>), RenderBenchError> {
    let settled = frame(1)?;
    against()?;
    let mut ratios = Vec::with_capacity(2 * runs);
    let (image, samples) = timed_frames(runs, settled, frame, |ms| {
        let start = Instant::now();
        against()?;
        ratios.push(ms / (start.elapsed().as_secs_f64() * 1e3));
        Ok(())
    })?;
    Ok((image, samples, ratios))
}

/// Frames 2 to 2·runs + 1 after the settling frame's `image`, each timed and `after` handed
/// its time outside the timing: the times, and the last full bend's image (odd k).
fn timed_frames(
    runs: usize,
    mut image: crate::render::Rendered,
    frame: &mut impl FnMut(usize) -> Result<crate::render::Rendered, RenderBenchError>,
    mut after: impl FnMut(f64) -> Result<(), RenderBenchError>,
) -> Result<(crate::render::Rendered, Vec<f64>), RenderBenchError> {
    let mut samples = Vec::with_capacity(2 * runs);
    for k in 2..2 * runs.max(1) + 2 {
        let start = Instant::now();
        let frame_k = frame(k)?;
        let ms = start.elapsed().as_secs_f64() * 1e3;
        samples.push(ms);
        after(ms)?;
        if k % 2 == 1 {
            image = frame_k;
        }
    }
    Ok((image, samples))
}

#[allow(clippy::too_many_arguments)]
fn source_row(
    case: &str,
    backend: RunsOn,
    device: &str,
    mode: &str,
    params: &RaycastParams,
    samples: Vec<f64>,
    image: &crate::render::Rendered,
    reference: &[[f64; 4]],
) -> BenchRow {
    BenchRow {
        stage: "render",
        case: format!(
            "{case} {}",
            match mode {
                "source_through_mesh" => "source",
                "warp_then_raycast" => "warp+cast",
                _ => "warp½+cast",
            }
        ),
        backend: backend.name().into(),
        device: device.into(),
        params: json!({"mode": mode, "step_mm": params.step, "preintegrated": params.preintegrated, "shading": params.shading, "tf": "ct_soft_tissue", "includes_readback": true, "every_frame_moves_the_mesh": true}),
        runs: samples.len(),
        time_ms: time_stats(samples),
        // The reference is unshaded: shaded rows are timed only.
        error: (params.shading == Shading::None).then(|| ErrorMeasure {
            metric: "psnr_db",
            value: image.psnr(reference),
            reference: "f64 map of each sample",
        }),
        work: json!({"rays": image.width * image.height}),
        gpu: None,
    }
}

/// Frames timed on the GPU, read-back included, after one to settle.
#[cfg(feature = "gpu")]
fn gpu_frames(
    ctx: &crate::gpu::GpuContext,
    runs: usize,
    mut frame: impl FnMut() -> Result<crate::render::Rendered, crate::render::volume::gpu::GpuRenderError>,
) -> Result<(crate::render::Rendered, Vec<f64>, Option<super::GpuCost>), crate::render::volume::gpu::GpuRenderError> {
    let mut image = frame()?;
    let mut samples = Vec::with_capacity(runs);
    let meter = super::GpuMeter::on(ctx);
    for _ in 0..runs {
        let start = Instant::now();
        image = frame()?;
        samples.push(start.elapsed().as_secs_f64() * 1e3);
    }
    Ok((image, samples, meter.finish(runs)))
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
    use crate::render::volume::gpu::GpuVolumeRaycaster;
    let raycaster = match GpuVolumeRaycaster::new(ctx.clone(), prepared) {
        Ok(r) => r,
        Err(e) => {
            tracing::warn!("GPU raycaster unavailable: {e}");
            return Ok(());
        }
    };
    let (image, samples, cost) =
        gpu_frames(ctx, opts.runs, || raycaster.render(camera)).map_err(|e| RenderBenchError::Gpu(e.to_string()))?;
    let params = prepared.params();
    emit(&BenchRow {
        stage: "render",
        case: case.to_owned(),
        backend: "gpu".into(),
        device: ctx.describe(),
        params: json!({"mode": "composite", "step_mm": params.step, "preintegrated": params.preintegrated, "shading": "none", "reference_step_mm": opts.reference_step, "tf": "ct_soft_tissue", "includes_readback": true}),
        runs: samples.len(),
        time_ms: time_stats(samples),
        error: Some(ErrorMeasure { metric: "psnr_db", value: image.psnr(reference), reference: "f64 point sampling" }),
        work: json!({"rays": camera.width * camera.height, "voxels": prepared.volume().len()}),
        gpu: cost,
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
    use crate::render::mesh::gpu::GpuTetRaycaster;
    let gpu_err = |e: crate::render::volume::gpu::GpuRenderError| RenderBenchError::Gpu(e.to_string());
    let mut raycaster = match GpuTetRaycaster::new(ctx.clone(), prepared, 1.0) {
        Ok(r) => r,
        Err(e) => {
            tracing::warn!("GPU tet raycaster unavailable: {e}");
            return Ok(());
        }
    };
    let (image, samples, cost) = gpu_frames(ctx, 3, || {
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
        gpu: cost,
    });
    Ok(())
}

pub const TABLE_HEADER: &str =
    "case                   backend  step  preint shading     median ms    fps   PSNR dB  vs volume";

pub fn table_row(row: &BenchRow) -> String {
    let p = &row.params;
    let error = row.error.as_ref().map_or("-".to_owned(), |e| format!("{:.1}", e.value));
    let vs_volume = p["vs_volume_raycast"].as_f64().map_or("-".to_owned(), |r| format!("{r:.2}x"));
    format!(
        "{:<22} {:<7} {:>5} {:>6} {:<10} {:>10.1} {:>6.1} {:>9} {:>10}",
        row.case,
        row.backend,
        p["step_mm"],
        p["preintegrated"],
        p["shading"].as_str().unwrap_or("?"),
        row.time_ms.median,
        1e3 / row.time_ms.median,
        error,
        vs_volume
    )
}
