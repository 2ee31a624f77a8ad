//! The source volume seen through the deformed mesh, with no warp (seed 002, sections 2-3,
//! on seed 000's tet walk): shape is the deformed mesh, appearance the source volume, never
//! resampled. The tet raycaster walks the deformed tets as for node scalars; inside a tet
//! the map to the source's index space is affine (the warp's own map, barycentric), so each
//! sample's rest position is one 3x4 product, and the source is sampled there (trilinear or
//! tricubic, after the displacement volumes' backward distortion, seed 002 section 3.2).
//!
//! Samples lie on one grid along the ray, `step` apart from where it enters the mesh, so a
//! tet boundary changes which map a sample uses, never where samples fall: on an affine
//! deformation a ray crossing many tets integrates exactly as one crossing none.
//! Compositing is the volume raycaster's (point-sampled or pre-integrated segments, early
//! termination), shading its gradient or forward difference carried through the tet's map.
//! Empty-space skipping is per tet: a tet whose rest box reads only invisible values is
//! crossed without sampling (fixed at creation: the rest mesh does not move), and such
//! tets around the tissue are not walked at all (the tet raycaster's `cut_outer_air`).
//!
//! `tet_raycast.wgsl` holds the GPU twin (`source_cross`, `source_finish`, the `geometry`
//! kernel's maps). [`reference()`] is the f64 integral mapping each sample exactly.

use std::sync::Arc;

use nalgebra::{Matrix3, Matrix3x4, Vector3};
use rayon::prelude::*;

use super::cpu::{TetRaycastParams, TetRaycaster};
use super::look::{SourceLook, EDGE_TOLERANCE};
use crate::camera::Camera;
use crate::transfer::{Tables, TransferFunction};
use crate::volume::{cell_ranges, gradient_scale, Mode, RaycastParams, CELL};
use crate::RenderError;
use defvol_core::mesh::TetMesh;
use defvol_core::volume::bspline::{backward_all, compile_all, DisplacementVolume};
use defvol_core::volume::{trilinear, Sampling, Volume, SAMPLE_TOLERANCE};

/// How the source is read at a sample's rest position.
#[derive(Debug, Clone, PartialEq)]
pub struct SourceSampling {
    pub sampling: Sampling,
    /// Applied on top of the mesh's map, as backward distortions in the source's space.
    pub displacements: Vec<DisplacementVolume>,
}

impl Default for SourceSampling {
    fn default() -> Self {
        Self { sampling: Sampling::Trilinear, displacements: Vec::new() }
    }
}
impl TetRaycaster {
    /// The source `volume` through the mesh: `mesh` is the rest mesh in the volume's world
    /// units (the positions the source is read at); [`TetRaycaster::update`] moves it.
    /// `params` are the volume raycaster's (composite mode; `step` in the volume's units).
    pub fn with_source(
        mesh: &TetMesh,
        volume: Arc<Volume>,
        tf: &TransferFunction,
        params: &RaycastParams,
        sampling: &SourceSampling,
    ) -> Result<Self, RenderError> {
        if params.mode != Mode::Composite {
            return Err(RenderError::Parameter(format!(
                "the source through the mesh is composited; mode {:?} is the volume raycaster's",
                params.mode
            )));
        }
        let tables = Tables::new(&tf.resolve(volume.range())?, volume.range(), params.step, params.preintegrated);
        crate::volume::check_params(&tables, params)?;
        let displacements = compile_all(&sampling.displacements)
            .map_err(|(i, why)| RenderError::Parameter(format!("displacement volume {i}: {why}")))?;
        let grid = volume.grid();
        let rest_index = grid.indices_f32(mesh.nodes());
        if !rest_index.iter().all(|q| q.iter().all(|v| v.is_finite())) {
            return Err(RenderError::Parameter("the rest mesh's nodes must be finite".into()));
        }
        check_overlap(mesh, &volume)?;
        // The samples of a tet read the voxels around its rest box, moved by at most the
        // largest displacement.
        let reach = displacements_reach(&sampling.displacements, &grid.spacing) + 1.0;
        let visible = tet_visibility(mesh, &rest_index, &volume, &tables, params.empty_space_skipping, reach);
        let gradient_scale = gradient_scale(params, &grid, volume.range());
        let tet_params = TetRaycastParams {
            step: params.step,
            preintegrated: false,
            early_termination: params.early_termination,
            background: params.background,
            tools: params.tools.clone(),
            ambient: params.ambient,
        };
        let look = SourceLook {
            volume,
            grid,
            rest_index,
            maps: Vec::new(),
            visible,
            tables,
            params: params.clone(),
            gradient_scale,
            sampling: sampling.sampling,
            displacements,
        };
        Self::prepare(mesh, &vec![0.0; mesh.nodes().len()], tf, &tet_params, Some(Box::new(look)))
    }
}

/// The largest displacement of the volumes, in voxels of the finest spacing.
fn displacements_reach(volumes: &[DisplacementVolume], spacing: &[f64; 3]) -> f64 {
    let finest = spacing.iter().copied().fold(f64::INFINITY, f64::min);
    volumes.iter().map(|d| Vector3::from(d.displacement).norm()).sum::<f64>() / finest
}

/// A mesh that does not reach the volume at all is in other units (or another place): the
/// picture would be empty for a reason the user must hear.
fn check_overlap(mesh: &TetMesh, volume: &Volume) -> Result<(), RenderError> {
    let grid = volume.grid();
    let corners: Vec<Vector3<f64>> = (0..8)
        .map(|c| {
            let ijk = Vector3::new(
                if c & 1 == 0 { 0.0 } else { (grid.dims[0] - 1) as f64 },
                if c & 2 == 0 { 0.0 } else { (grid.dims[1] - 1) as f64 },
                if c & 4 == 0 { 0.0 } else { (grid.dims[2] - 1) as f64 },
            );
            grid.world_from_index(ijk)
        })
        .collect();
    let (vlo, vhi) = defvol_core::mesh::bounds(&corners);
    let (mlo, mhi) = mesh.bounds();
    let apart = (0..3).any(|a| mhi[a] < vlo[a] || mlo[a] > vhi[a]);
    if apart {
        return Err(RenderError::Parameter(format!(
            "the mesh (box {:?} to {:?}) does not reach the volume (box {:?} to {:?}): are both in the same units and frame?",
            mlo.as_slice(),
            mhi.as_slice(),
            vlo.as_slice(),
            vhi.as_slice()
        )));
    }
    Ok(())
}

/// Per tet: whether any value its samples can read is visible, from the macro cells'
/// ranges over its rest box widened by `reach` voxels.
fn tet_visibility(
    mesh: &TetMesh,
    rest_index: &[[f32; 4]],
    volume: &Volume,
    tables: &Tables,
    skipping: bool,
    reach: f64,
) -> Vec<u32> {
    if !skipping {
        return vec![1; mesh.tets().len()];
    }
    let (cells, ranges) = cell_ranges(volume);
    let dims = volume.dims();
    let cell_visible: Vec<bool> = ranges.par_iter().map(|&(lo, hi)| tables.max_tau(lo, hi) > 0.0).collect();
    mesh.tets()
        .par_iter()
        .map(|tet| {
            let mut span = [(0usize, 0usize); 3];
            for a in 0..3 {
                let (lo, hi) = tet.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &n| {
                    let v = f64::from(rest_index[n as usize][a]);
                    (lo.min(v), hi.max(v))
                });
                let (lo, hi) = (lo - reach, hi + reach);
                let top = (dims[a] - 1) as f64;
                if hi < -f64::from(EDGE_TOLERANCE) || lo > top + f64::from(EDGE_TOLERANCE) {
                    return 0;
                }
                let cell = |v: f64| ((v.clamp(0.0, top) as usize) / CELL).min(cells[a] - 1);
                span[a] = (cell(lo), cell(hi));
            }
            for cz in span[2].0..=span[2].1 {
                for cy in span[1].0..=span[1].1 {
                    for cx in span[0].0..=span[0].1 {
                        if cell_visible[cx + cells[0] * (cy + cells[1] * cz)] {
                            return 1;
                        }
                    }
                }
            }
            0
        })
        .collect()
}

/// The f64 reference: the walk of [`crate::mesh::reference`] with, inside each tet,
/// sub-steps no longer than `step` whose middles are mapped exactly (barycentric, f64) to
/// the source, sampled trilinearly in f64 after the displacement volumes, through the exact
/// transfer function; unshaded, no tools. `params` gives the step and the background.
/// Linear RGBA per pixel, rows top to bottom.
pub fn reference(
    mesh: &TetMesh,
    positions: &[Vector3<f64>],
    volume: &Volume,
    camera: &Camera,
    tf: &TransferFunction,
    params: &RaycastParams,
    displacements: &[DisplacementVolume],
) -> Result<Vec<[f64; 4]>, RenderError> {
    let step = params.step;
    if !(step.is_finite() && step > 0.0) {
        return Err(RenderError::Parameter(format!("step {step} must be finite and > 0")));
    }
    let tf = tf.resolve(volume.range())?;
    let displacements = compile_all(displacements)
        .map_err(|(i, why)| RenderError::Parameter(format!("displacement volume {i}: {why}")))?;
    let grid = volume.grid();
    // Per tet: the f64 map from deformed world to rest world.
    let maps: Vec<Option<Matrix3x4<f64>>> = mesh
        .tets()
        .iter()
        .map(|tet| {
            let x = tet.map(|i| positions[i as usize]);
            let r = tet.map(|i| mesh.nodes()[i as usize]);
            let dx = Matrix3::from_columns(&[x[1] - x[0], x[2] - x[0], x[3] - x[0]]);
            let dr = Matrix3::from_columns(&[r[1] - r[0], r[2] - r[0], r[3] - r[0]]);
            dx.try_inverse().map(|inv| {
                let a = dr * inv;
                let b = r[0] - a * x[0];
                Matrix3x4::from_columns(&[
                    a.column(0).into_owned(),
                    a.column(1).into_owned(),
                    a.column(2).into_owned(),
                    b,
                ])
            })
        })
        .collect();
    let walk = TetRaycastParams { step, background: params.background, ..Default::default() };
    crate::mesh::reference_walk(mesh, positions, camera, &walk, |tet, o, d, t_in, t_out, acc| {
        let Some(map) = &maps[tet] else { return };
        let n = ((t_out - t_in) / step).ceil().max(1.0) as usize;
        let ds = (t_out - t_in) / n as f64;
        for m in 0..n {
            let x = o + d * (t_in + (m as f64 + 0.5) * ds);
            let rest = map * x.push(1.0);
            let rest = backward_all(&displacements, &rest);
            let q = grid.index_from_world(rest);
            let Some(s) = trilinear::<f64>(volume.data(), volume.dims(), q.x, q.y, q.z, SAMPLE_TOLERANCE) else {
                continue;
            };
            let (color, tau) = tf.eval(s);
            let alpha = (1.0 - acc[3]) * (1.0 - (-tau * ds).exp());
            for c in 0..3 {
                acc[c] += alpha * color[c];
            }
            acc[3] += alpha;
        }
    })
}
