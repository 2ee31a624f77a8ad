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
//! crossed without sampling (fixed at creation: the rest mesh does not move).
//!
//! `tet_raycast.wgsl` holds the GPU twin (`source_cross`, `source_finish`, the `geometry`
//! kernel's maps). [`reference()`] is the f64 integral mapping each sample exactly.

use std::sync::Arc;

use nalgebra::{Matrix3, Matrix3x4, Vector3};
use rayon::prelude::*;

use super::camera::Camera;
use super::raycast::{cell_ranges, gradient_scale, Mode, RaycastParams, Shading, CELL};
use super::tet_raycast::{linear_field, TetRaycastParams, TetRaycaster, V3};
use super::transfer::{Tables, TransferFunction};
use super::RenderError;
use defvol_core::mesh::TetMesh;
use defvol_core::volume::bspline::{backward_all, compile_all, CompiledDisplacement, DisplacementVolume};
use defvol_core::volume::{tricubic, trilinear, Grid, Sampling, Volume, SAMPLE_TOLERANCE};

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

/// Samples this far (source voxels) outside the voxel-centre box are read on its edge: a
/// ray enters and leaves a mesh built on the box exactly there, and the f32 maps put those
/// samples a few 1e-6 voxels either side of it.
pub(crate) const EDGE_TOLERANCE: f32 = 1e-3;

/// Per tet: rows of the affine map from anchored deformed positions to the source's
/// continuous index (q = G·x + w, row i = (Gᵢ, wᵢ)).
pub(crate) type TetMap = [[f32; 4]; 3];

/// What the tet raycaster needs to show the source.
pub(crate) struct SourceLook {
    pub(crate) volume: Arc<Volume>,
    /// The volume's grid, where the displacement volumes move samples.
    grid: Grid,
    /// Per node: its rest position in the source's continuous index (w unused).
    pub(crate) rest_index: Vec<[f32; 4]>,
    /// Per tet, refreshed with the geometry.
    pub(crate) maps: Vec<TetMap>,
    /// Per tet: 1 when a sample inside it may be visible.
    pub(crate) visible: Vec<u32>,
    pub(crate) tables: Tables,
    pub(crate) params: RaycastParams,
    pub(crate) gradient_scale: f32,
    pub(crate) sampling: Sampling,
    pub(crate) displacements: Vec<CompiledDisplacement>,
}

/// A ray through the mesh (anchored origin and direction, the light it is lit from) and
/// where its samples are: the k-th at `t0 + (k + offset)·step` (offset ½ when point
/// sampling, the sample at the middle of its segment), and the last one's value.
pub(crate) struct March {
    o: V3,
    d: V3,
    light: V3,
    t0: f32,
    k: u32,
    front: Option<f32>,
}

#[inline]
fn apply(map: &TetMap, x: &V3) -> V3 {
    let row = |r: &[f32; 4]| r[0] * x.x + r[1] * x.y + r[2] * x.z + r[3];
    V3::new(row(&map[0]), row(&map[1]), row(&map[2]))
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
        super::raycast::check_params(&tables, params)?;
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

impl SourceLook {
    /// The tets' maps for anchored deformed positions.
    pub(crate) fn update_maps(&mut self, tets: &[[u32; 4]], anchored: &[V3]) {
        let rest = &self.rest_index;
        self.maps = tets
            .par_iter()
            .map(|tet| {
                let x = tet.map(|i| anchored[i as usize]);
                [0, 1, 2].map(|c| linear_field(&x, &tet.map(|i| rest[i as usize][c])))
            })
            .collect();
    }

    /// The source at continuous index q, after the displacement volumes; `None` outside
    /// the voxel-centre box (nothing is there to see).
    #[inline]
    fn value(&self, q: &V3) -> Option<f32> {
        let q = if self.displacements.is_empty() {
            *q
        } else {
            let world = self.grid.world_from_index(q.cast::<f64>());
            self.grid.index_from_world(backward_all(&self.displacements, &world)).cast::<f32>()
        };
        let (data, dims) = (self.volume.data(), self.volume.dims());
        let tol = EDGE_TOLERANCE;
        if !(0..3).all(|a| q[a] >= -tol && q[a] <= (dims[a] - 1) as f32 + tol) {
            return None;
        }
        match self.sampling {
            Sampling::Trilinear => Some(super::raycast::sample_clamped(data, dims, &q)),
            Sampling::Tricubic => tricubic(data, dims, q.x, q.y, q.z),
        }
    }

    /// The source clamped to its box (the gradient's neighbours at the border).
    #[inline]
    fn clamped(&self, q: &V3) -> f32 {
        super::raycast::sample_clamped(self.volume.data(), self.volume.dims(), q)
    }

    /// Lambert factor at rest index q in a tet with `map`, lit from `light` (deformed world).
    fn shade(&self, q: &V3, map: &TetMap, light: &V3) -> f32 {
        let ambient = self.params.ambient as f32;
        match self.params.shading {
            Shading::None => 1.0,
            Shading::Gradient => {
                let gi = V3::new(
                    self.clamped(&(q + V3::x())) - self.clamped(&(q - V3::x())),
                    self.clamped(&(q + V3::y())) - self.clamped(&(q - V3::y())),
                    self.clamped(&(q + V3::z())) - self.clamped(&(q - V3::z())),
                ) * 0.5;
                // ∇ₓf = Gᵀ ∇_q f: the source's gradient carried through the tet's map.
                let g = V3::new(
                    map[0][0] * gi.x + map[1][0] * gi.y + map[2][0] * gi.z,
                    map[0][1] * gi.x + map[1][1] * gi.y + map[2][1] * gi.z,
                    map[0][2] * gi.x + map[1][2] * gi.y + map[2][2] * gi.z,
                );
                let len = g.norm();
                if len > 1e-12 {
                    ambient + (1.0 - ambient) * (g.dot(light) / len).abs()
                } else {
                    1.0
                }
            }
            Shading::ForwardDifference => {
                // One world unit toward the light, in the source's index: G·l.
                let l = V3::new(
                    map[0][0] * light.x + map[0][1] * light.y + map[0][2] * light.z,
                    map[1][0] * light.x + map[1][1] * light.y + map[1][2] * light.z,
                    map[2][0] * light.x + map[2][1] * light.y + map[2][2] * light.z,
                );
                let drop = self.clamped(q) - self.clamped(&(q + l));
                ambient + (1.0 - ambient) * (drop / self.gradient_scale).clamp(0.0, 1.0)
            }
        }
    }

    /// Adds a segment's premultiplied colour and α, shaded at q.
    #[allow(clippy::too_many_arguments)]
    fn add(&self, acc: &mut [f32; 4], depth: &mut f32, e: [f32; 4], q: &V3, map: &TetMap, light: &V3, t_mid: f32) {
        if e[3] <= 1e-5 {
            return;
        }
        let shade = self.shade(q, map, light);
        let weight = 1.0 - acc[3];
        for c in 0..3 {
            acc[c] += weight * e[c] * shade;
        }
        acc[3] += weight * e[3];
        if depth.is_infinite() && acc[3] >= 0.5 {
            *depth = t_mid;
        }
    }

    /// A ray from anchored `o` along `d` entering the mesh at `t0`.
    pub(crate) fn march(&self, o: &V3, d: &V3, t0: f32) -> March {
        let light = self.params.light.map_or(-d, |l| Vector3::from(l).normalize().cast::<f32>());
        March { o: *o, d: *d, light, t0, k: 0, front: None }
    }

    /// The samples of `march` up to `t_out` inside `tet`.
    pub(crate) fn cross(&self, march: &mut March, tet: usize, t_out: f32, acc: &mut [f32; 4], depth: &mut f32) {
        let (o, d, light) = (march.o, march.d, march.light);
        let step = self.params.step as f32;
        let preintegrated = self.params.preintegrated;
        let offset = if preintegrated { 0.0 } else { 0.5 };
        let map = &self.maps[tet];
        let t0 = march.t0;
        let at = |k: u32| t0 + (k as f32 + offset) * step;
        let termination = self.params.early_termination as f32;
        // In a tet with nothing to see, only the segment coming in from the tet before (its
        // front there) adds anything.
        let mut composite = self.visible[tet] != 0 || (preintegrated && march.front.is_some());
        while at(march.k) <= t_out {
            if !composite {
                // The last sample inside is kept, the next segment's front.
                let last = ((t_out - t0) / step - offset).floor().max(march.k as f32) as u32;
                let last = if at(last) > t_out { last.saturating_sub(1).max(march.k) } else { last };
                if preintegrated {
                    march.front = self.value(&apply(map, &(o + d * at(last))));
                }
                march.k = last + 1;
                return;
            }
            composite = self.visible[tet] != 0;
            let t = at(march.k);
            let q = apply(map, &(o + d * t));
            let value = self.value(&q);
            if preintegrated {
                if let (Some(front), Some(back), true) = (march.front, value, march.k > 0) {
                    let middle = apply(map, &(o + d * (t - 0.5 * step)));
                    self.add(acc, depth, self.tables.segment(front, back), &middle, map, &light, t - 0.5 * step);
                }
                march.front = value;
            } else if let Some(v) = value {
                self.add(acc, depth, self.tables.sample_step(v), &q, map, &light, t);
            }
            march.k += 1;
            if acc[3] >= termination {
                return;
            }
        }
    }

    /// The shorter last segment, from the last sample to `t_end` (the ray leaves the mesh
    /// or meets a tool), inside `tet`.
    pub(crate) fn finish(&self, march: &March, tet: usize, t_end: f32, acc: &mut [f32; 4], depth: &mut f32) {
        let (o, d, light) = (&march.o, &march.d, &march.light);
        let step = self.params.step as f32;
        let map = &self.maps[tet];
        // The segment after the last sample (pre-integrated) or the last sample's segment
        // end (point sampling) up to t_end.
        let start = march.t0 + march.k as f32 * step - if self.params.preintegrated { step } else { 0.0 };
        let len = t_end - start;
        if len <= 1e-6 * step {
            return;
        }
        if self.params.preintegrated {
            let (Some(front), Some(back)) = (march.front, self.value(&apply(map, &(o + d * t_end)))) else { return };
            let seg = self.tables.segment(front, back);
            // A shorter last segment: the same extinction over less length.
            let alpha = 1.0 - (1.0 - seg[3]).max(0.0).powf(len / step);
            let scale = if seg[3] > 0.0 { alpha / seg[3] } else { len / step };
            let middle = apply(map, &(o + d * (start + 0.5 * len)));
            let e = [seg[0] * scale, seg[1] * scale, seg[2] * scale, alpha];
            self.add(acc, depth, e, &middle, map, light, start + 0.5 * len);
        } else {
            let middle = apply(map, &(o + d * (start + 0.5 * len)));
            let Some(v) = self.value(&middle) else { return };
            let e = self.tables.sample(v);
            let alpha = 1.0 - (-e[3] * len).exp();
            self.add(
                acc,
                depth,
                [e[0] * alpha, e[1] * alpha, e[2] * alpha, alpha],
                &middle,
                map,
                light,
                start + 0.5 * len,
            );
        }
    }
}

/// The f64 reference: the walk of [`super::tet_raycast::reference`] with, inside each tet,
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
    super::tet_raycast::reference_walk(mesh, positions, camera, &walk, |tet, o, d, t_in, t_out, acc| {
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
