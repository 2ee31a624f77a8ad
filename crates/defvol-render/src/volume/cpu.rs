//! The volume raycaster (CPU, rayon over rows): rays from the camera through the voxel grid,
//! trilinear samples, front-to-back compositing with point-sampled or pre-integrated
//! segments, early ray termination, empty-space skipping on 8³ macro cells, and shading by
//! gradients or by the forward difference toward the light (seed 002, section 3.3).
//! [`reference()`] is the independent f64 ray integral the tests and benchmarks compare to.

use std::sync::Arc;

use nalgebra::{Matrix3, Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, Rays};
use crate::transfer::{Tables, TransferFunction};
use crate::{RenderError, Rendered};
use defvol_core::volume::lanes::{trilinear_lanes, CellLookup};
use defvol_core::volume::{trilinear, Grid, Volume};

#[cfg(target_arch = "x86_64")]
pub(crate) mod packet;
#[cfg(target_arch = "x86_64")]
use defvol_core::volume::lanes::Trilinear8;

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// Emission-absorption compositing through the transfer function.
    Composite,
    /// Maximum intensity projection, windowed by the transfer function's span.
    Mip,
    /// The first crossing of `iso_value`, lit.
    Iso,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Shading {
    None,
    /// Central-difference gradients (6 extra samples), two-sided Lambert.
    Gradient,
    /// One extra sample toward the light, no stored or computed gradient (seed 002).
    ForwardDifference,
}

#[derive(Debug, Clone, PartialEq)]
pub struct RaycastParams {
    pub mode: Mode,
    /// Sample spacing along the ray, world units of the volume (mm for medical files).
    pub step: f64,
    pub preintegrated: bool,
    pub shading: Shading,
    /// Direction toward the light, world frame; the camera's own direction when `None`.
    pub light: Option<[f64; 3]>,
    pub ambient: f64,
    /// Rays stop once this opaque.
    pub early_termination: f64,
    pub empty_space_skipping: bool,
    pub iso_value: f64,
    /// |gradient| (value per world unit) that the forward difference maps to full light.
    pub gradient_scale: Option<f64>,
    /// RGBA behind the volume.
    pub background: [f64; 4],
    /// Tools drawn into the picture, opaque, at their depth (up to [`MAX_TOOLS`]).
    pub tools: Vec<ToolPicture>,
}

/// The most tools a frame draws (the GPU's uniform block holds this many).
pub const MAX_TOOLS: usize = 4;

/// A tool as the picture shows it: a capsule from `tip` to `tail` (a sphere when they
/// coincide) of `radius`, world units of the volume.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolPicture {
    pub tip: [f64; 3],
    pub tail: [f64; 3],
    pub radius: f64,
    pub color: [f64; 3],
}

impl ToolPicture {
    pub(crate) fn validate(&self) -> Result<(), RenderError> {
        let finite = self.tip.iter().chain(&self.tail).chain(&self.color).all(|v| v.is_finite());
        if !(finite && self.radius.is_finite() && self.radius > 0.0) {
            return Err(RenderError::Parameter(format!("tool {self:?}: positions must be finite and the radius > 0")));
        }
        Ok(())
    }

    /// Distance from p to the capsule's surface (negative inside).
    fn distance(&self, p: &Vector3<f64>) -> (f64, Vector3<f64>) {
        let (a, b) = (Vector3::from(self.tip), Vector3::from(self.tail));
        let ab = b - a;
        let h = if ab.norm_squared() > 0.0 { ((p - a).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0) } else { 0.0 };
        let outward = p - (a + ab * h);
        (outward.norm() - self.radius, outward)
    }

    /// The first hit along a world ray (sphere tracing the capsule's distance): distance
    /// and outward normal.
    fn hit(&self, origin: &Point3<f64>, direction: &Vector3<f64>) -> Option<(f64, Vector3<f64>)> {
        let mut t = 0.0;
        for _ in 0..128 {
            let (d, outward) = self.distance(&(origin.coords + direction * t));
            if d < 1e-6 * (1.0 + t) {
                return Some((t, outward.try_normalize(1e-12).unwrap_or(-direction)));
            }
            t += d;
            if t > 1e7 {
                break;
            }
        }
        None
    }
}

/// The nearest tool along a world ray: distance and its lit, opaque colour (what the ray
/// sees behind the tissue in front of it).
pub(crate) fn nearest_tool(
    tools: &[ToolPicture],
    ambient: f64,
    origin: &Point3<f64>,
    direction: &Vector3<f64>,
    light: &Vector3<f64>,
) -> Option<(f32, [f32; 4])> {
    tools
        .iter()
        .filter_map(|tool| tool.hit(origin, direction).map(|(t, n)| (t, tool, n)))
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(t, tool, n)| {
            let shade = ambient + (1.0 - ambient) * n.dot(light).max(0.0);
            (
                t as f32,
                [(tool.color[0] * shade) as f32, (tool.color[1] * shade) as f32, (tool.color[2] * shade) as f32, 1.0],
            )
        })
}

impl Default for RaycastParams {
    fn default() -> Self {
        Self {
            mode: Mode::Composite,
            step: 1.0,
            preintegrated: true,
            shading: Shading::Gradient,
            light: None,
            ambient: 0.35,
            early_termination: 0.999,
            empty_space_skipping: true,
            iso_value: 300.0,
            gradient_scale: None,
            background: [0.0, 0.0, 0.0, 1.0],
            tools: Vec::new(),
        }
    }
}

/// Side of the macro cells empty-space skipping works on.
pub(crate) const CELL: usize = 8;

/// Per macro cell: can any sample inside it be visible?
pub(crate) struct MacroCells {
    pub(crate) dims: [usize; 3],
    pub(crate) visible: Vec<bool>,
}

/// Per macro cell of `CELL`³ voxels: the lowest and highest value a sample inside it can
/// read (its voxels and one past its far sides). Returns the cells along each axis.
pub(crate) fn cell_ranges(volume: &Volume) -> ([usize; 3], Vec<(f32, f32)>) {
    let d = volume.dims();
    let dims = d.map(|n| n.div_ceil(CELL));
    let data = volume.data();
    let ranges = (0..dims[0] * dims[1] * dims[2])
        .into_par_iter()
        .map(|c| {
            let (cx, cy, cz) = (c % dims[0], (c / dims[0]) % dims[1], c / (dims[0] * dims[1]));
            let range = |c: usize, n: usize| c * CELL..((c + 1) * CELL + 1).min(n);
            let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
            for k in range(cz, d[2]) {
                for j in range(cy, d[1]) {
                    for i in range(cx, d[0]) {
                        let v = data[i + d[0] * (j + d[1] * k)];
                        lo = lo.min(v);
                        hi = hi.max(v);
                    }
                }
            }
            (lo, hi)
        })
        .collect();
    (dims, ranges)
}

impl MacroCells {
    fn new(volume: &Volume, tables: &Tables) -> Self {
        let (dims, ranges) = cell_ranges(volume);
        Self { dims, visible: ranges.into_par_iter().map(|(lo, hi)| tables.max_tau(lo, hi) > 0.0).collect() }
    }

    /// Whether the cell holding index-space point p may be visible.
    fn visible_at(&self, p: &Vector3<f32>) -> bool {
        let c = |v: f32, n: usize| ((v.max(0.0) as usize) / CELL).min(n - 1);
        self.visible[c(p.x, self.dims[0]) + self.dims[0] * (c(p.y, self.dims[1]) + self.dims[1] * c(p.z, self.dims[2]))]
    }

    /// The ray parameter where it leaves p's cell.
    fn exit(&self, p: &Vector3<f32>, d: &Vector3<f32>, t: f32) -> f32 {
        let mut exit = f32::INFINITY;
        for a in 0..3 {
            let cell = ((p[a].max(0.0) as usize) / CELL) as f32;
            let bound = if d[a] > 0.0 { (cell + 1.0) * CELL as f32 } else { cell * CELL as f32 };
            if d[a] != 0.0 {
                exit = exit.min(t + (bound - p[a]) / d[a]);
            }
        }
        exit
    }
}

/// The volume's index space: index = index_from_world · world + offset.
pub(crate) struct IndexSpace {
    pub(crate) index_from_world: Matrix3<f64>,
    pub(crate) origin: Vector3<f64>,
}

impl IndexSpace {
    pub(crate) fn of(grid: &Grid) -> Self {
        let index_from_world =
            Matrix3::from_diagonal(&Vector3::from(grid.spacing).map(|s| 1.0 / s)) * grid.direction.transpose();
        Self { index_from_world, origin: Vector3::from(grid.origin) }
    }

    /// Origin and direction (per world unit) of a world ray, in index space.
    fn ray(&self, origin: &Point3<f64>, direction: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
        (self.index_from_world * (origin.coords - self.origin), self.index_from_world * direction)
    }

    /// The matrix taking a gradient in index space (value per voxel) to a world gradient:
    /// ∇_world f = (∂index/∂world)ᵀ ∇_index f.
    fn gradient_to_world(&self) -> [[f32; 3]; 3] {
        std::array::from_fn(|i| std::array::from_fn(|j| self.index_from_world[(j, i)] as f32))
    }
}

/// Two-sided Lambert for world gradient `w` lit from `light`: `ambient` plus the rest
/// times |cos| between the normal and the light, or 1 where the gradient is too short for
/// a normal. In f32, as the GPU takes it; the lanes' `packet::lambert8` term by term.
pub(crate) fn lambert(w: &Vector3<f32>, light: &Vector3<f32>, ambient: f32) -> f32 {
    let len = (w.x * w.x + w.y * w.y + w.z * w.z).sqrt();
    if len > 1e-12 {
        ambient + (1.0 - ambient) * ((w.x * light.x + w.y * light.y + w.z * light.z) / len).abs()
    } else {
        1.0
    }
}

/// The light a sample gets from the value's `drop` one world unit toward the light, full
/// at `scale` (seed 002's forward difference); the lanes' `packet::forward_difference8`.
pub(crate) fn lit_by_drop(drop: f32, scale: f32, ambient: f32) -> f32 {
    ambient + (1.0 - ambient) * (drop / scale).clamp(0.0, 1.0)
}

impl Shading {
    /// How the lanes shade: none for an unshaded picture.
    #[cfg(target_arch = "x86_64")]
    pub(crate) fn in_lanes(self) -> Option<packet::ShadeBy> {
        match self {
            Shading::None => None,
            Shading::Gradient => Some(packet::ShadeBy::Gradient),
            Shading::ForwardDifference => Some(packet::ShadeBy::ForwardDifference),
        }
    }
}

/// The parameter interval where a ray is inside the voxel-centre box [0, n-1]³.
fn clip(dims: [usize; 3], o: &Vector3<f64>, d: &Vector3<f64>) -> Option<(f64, f64)> {
    let (mut near, mut far) = (0.0f64, f64::INFINITY);
    for a in 0..3 {
        let max = (dims[a] - 1) as f64;
        if d[a].abs() < 1e-300 {
            if o[a] < 0.0 || o[a] > max {
                return None;
            }
            continue;
        }
        let (t0, t1) = ((0.0 - o[a]) / d[a], (max - o[a]) / d[a]);
        near = near.max(t0.min(t1));
        far = far.min(t0.max(t1));
    }
    (near <= far).then_some((near, far))
}

/// A volume prepared for rendering with one transfer function and parameters: the tables
/// and macro cells are built once, then any number of frames render from it.
pub struct VolumeRaycaster<'a> {
    pub(crate) volume: &'a Volume,
    pub(crate) tables: Arc<Tables>,
    pub(crate) cells: Option<MacroCells>,
    pub(crate) space: IndexSpace,
    pub(crate) params: RaycastParams,
    pub(crate) gradient_scale: f32,
}

impl<'a> VolumeRaycaster<'a> {
    /// The parameters it was prepared with (the benches name them in their rows).
    pub fn params(&self) -> &RaycastParams {
        &self.params
    }

    /// The volume it casts through.
    pub fn volume(&self) -> &'a Volume {
        self.volume
    }

    pub fn new(volume: &'a Volume, tf: &TransferFunction, params: &RaycastParams) -> Result<Self, RenderError> {
        let tables = Self::tables_for(volume.range(), tf, params)?;
        Self::with_tables(volume, Arc::new(tables), params)
    }

    /// The tables of `tf` for `params` over a scalar `range`: built once and shared by the
    /// frames of a volume that changes within that range (the node's warped volume; the
    /// pre-integrated table alone takes 0.1-0.4 s).
    pub fn tables_for(range: (f32, f32), tf: &TransferFunction, params: &RaycastParams) -> Result<Tables, RenderError> {
        if !(params.step.is_finite() && params.step > 0.0) {
            return Err(RenderError::Parameter(format!("step {} must be finite and > 0", params.step)));
        }
        let tf = tf.resolve(range)?;
        Ok(Tables::new(&tf, range, params.step, params.preintegrated && params.mode == Mode::Composite))
    }

    /// `volume` with tables from [`Self::tables_for`] for the same parameters: only the
    /// macro cells are built.
    pub fn with_tables(volume: &'a Volume, tables: Arc<Tables>, params: &RaycastParams) -> Result<Self, RenderError> {
        check_params(&tables, params)?;
        let cells =
            (params.empty_space_skipping && params.mode == Mode::Composite).then(|| MacroCells::new(volume, &tables));
        let gradient_scale = gradient_scale(params, &volume.grid(), volume.range());
        Ok(Self {
            volume,
            tables,
            cells,
            space: IndexSpace::of(&volume.grid()),
            params: params.clone(),
            gradient_scale,
        })
    }

    /// One frame seen by `camera`.
    pub fn render(&self, camera: &Camera) -> Result<Rendered, RenderError> {
        camera.validate()?;
        let caster = self.caster();
        let rays = camera.rays();
        let (w, h) = (camera.width, camera.height);
        let mut rgba = vec![0u8; w * h * 4];
        let mut depth = vec![f32::INFINITY; w * h];
        // Bands of TILE rows walked tile by tile: neighbouring rays read the same voxels
        // while they are still in cache.
        const TILE: usize = 8;
        rgba.par_chunks_mut(w * 4 * TILE).zip(depth.par_chunks_mut(w * TILE)).enumerate().for_each(
            |(band, (rows, depth_rows))| {
                let band_h = depth_rows.len() / w;
                for tx in (0..w).step_by(TILE) {
                    let tile = (tx..(tx + TILE).min(w), band * TILE..band * TILE + band_h);
                    caster.cast_tile(&rays, tile, |(px, py), (color, d)| {
                        let i = (py - band * TILE) * w + px;
                        rows[i * 4..i * 4 + 4].copy_from_slice(&color.map(to_level));
                        depth_rows[i] = d;
                    });
                }
            },
        );
        Ok(Rendered { width: w, height: h, rgba, depth })
    }

    /// The caster of this volume, tables and parameters, with packets where they serve.
    fn caster(&self) -> Caster<'_> {
        let mut caster = Caster {
            #[cfg(target_arch = "x86_64")]
            packets: None,
            #[cfg(target_arch = "x86_64")]
            gradients: packet::Gradient8::new(self.volume.data(), self.volume.dims()),
            to_world: self.space.gradient_to_world(),
            volume: self.volume,
            sampler: Sampler::new(self.volume.data(), self.volume.dims()),
            tables: &self.tables,
            cells: self.cells.as_ref(),
            space: &self.space,
            params: &self.params,
            gradient_scale: self.gradient_scale,
        };
        #[cfg(target_arch = "x86_64")]
        {
            caster.packets = caster.packet_sampler();
        }
        caster
    }
}

/// A channel in 0..1 as its nearest 8-bit level (a plain add and truncation: `round` is a
/// library call on baseline x86-64, and this runs per pixel).
#[inline(always)]
pub(crate) fn to_level(c: f32) -> u8 {
    (c.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// Refuses parameters the tables were not built for, and bad lights and tools.
pub(crate) fn check_params(tables: &Tables, params: &RaycastParams) -> Result<(), RenderError> {
    if !(params.step.is_finite() && params.step > 0.0) {
        return Err(RenderError::Parameter(format!("step {} must be finite and > 0", params.step)));
    }
    let wants_preintegrated = params.preintegrated && params.mode == Mode::Composite;
    if (tables.step - params.step as f32).abs() > 1e-6 * tables.step.abs().max(1.0)
        || tables.preintegrated.is_empty() == wants_preintegrated
    {
        return Err(RenderError::Parameter(format!(
            "the tables were built for step {} (pre-integrated: {}), not for these parameters",
            tables.step,
            !tables.preintegrated.is_empty()
        )));
    }
    if params.light.is_some_and(|l| !l.iter().all(|v| v.is_finite()) || Vector3::from(l).norm() == 0.0) {
        return Err(RenderError::Parameter("the light direction must be finite and non-zero".into()));
    }
    if params.tools.len() > MAX_TOOLS {
        return Err(RenderError::Parameter(format!("{} tools; a picture draws up to {MAX_TOOLS}", params.tools.len())));
    }
    for tool in &params.tools {
        tool.validate()?;
    }
    Ok(())
}

/// The gradient magnitude the forward difference maps to full light: the parameter's, or a
/// quarter of the scalar range per voxel of the finest spacing.
pub(crate) fn gradient_scale(params: &RaycastParams, grid: &Grid, (lo, hi): (f32, f32)) -> f32 {
    let min_spacing = grid.spacing.iter().copied().fold(f64::INFINITY, f64::min);
    params.gradient_scale.unwrap_or((f64::from(hi - lo) / (4.0 * min_spacing)).max(1e-12)) as f32
}

/// Renders `volume` seen by `camera` (prepares and renders one frame).
pub fn raycast(
    volume: &Volume,
    camera: &Camera,
    tf: &TransferFunction,
    params: &RaycastParams,
) -> Result<Rendered, RenderError> {
    camera.validate()?;
    VolumeRaycaster::new(volume, tf, params)?.render(camera)
}

/// Trilinear at a continuous index, the point clamped to the voxel-centre box: the same
/// arithmetic as `volume::trilinear` without its range checks, for the hot loops.
#[inline(always)]
pub(crate) fn sample_clamped(data: &[f32], dims: [usize; 3], p: &Vector3<f32>) -> f32 {
    Sampler::new(data, dims).at(p)
}

/// The central-difference gradient at a continuous index (value per voxel), the neighbours
/// clamped to the voxel-centre box ([`Sampler::gradient`]).
pub(crate) fn gradient_clamped(data: &[f32], dims: [usize; 3], p: &Vector3<f32>) -> Vector3<f32> {
    Sampler::new(data, dims).gradient(p)
}

/// [`sample_clamped`] with its per-volume constants worked out once: the per-sample work is
/// 32-bit index arithmetic and one bounds check for the cell's eight corners. Its cell
/// lookup is the one the eight-lane sampler takes.
#[derive(Clone, Copy)]
pub(crate) struct Sampler<'a> {
    data: &'a [f32],
    cell: CellLookup,
    /// The voxel-centre box's top per axis.
    top: [f32; 3],
}

impl<'a> Sampler<'a> {
    pub(crate) fn new(data: &'a [f32], dims: [usize; 3]) -> Self {
        Self { data, cell: CellLookup::for_dims(dims), top: dims.map(|n| n.saturating_sub(1) as f32) }
    }

    /// Coordinate `v` on axis `a` clamped to the box: its cell and the fraction in it.
    #[inline(always)]
    fn cell_of(&self, v: f32, a: usize) -> (i32, f32) {
        // Plain comparisons rather than `clamp` (points are finite here): the hot loop.
        let v = if v > 0.0 {
            if v < self.top[a] {
                v
            } else {
                self.top[a]
            }
        } else {
            0.0
        };
        let i = (v as i32).min(self.cell.top[a]);
        (i, v - i as f32)
    }

    #[inline(always)]
    pub(crate) fn at(&self, p: &Vector3<f32>) -> f32 {
        let ((i, fx), (j, fy), (k, fz)) = (self.cell_of(p.x, 0), self.cell_of(p.y, 1), self.cell_of(p.z, 2));
        let [sx, sy, sz] = self.cell.strides.map(|s| s as usize);
        let base = (i + self.cell.nx * j + self.cell.nxy * k) as usize;
        // One check for the whole cell (the clamps keep it inside the data).
        let cell = &self.data[base..=base + sx + sy + sz];
        defvol_core::volume::lerp_cube(|o| cell[o], [sx, sy, sz], [fx, fy, fz])
    }

    /// The central-difference gradient at `p` (value per voxel) of samples clamped to the
    /// box a voxel either side, `(f(p + eₐ) - f(p - eₐ)) / 2`: read as the grid's central
    /// differences (the neighbours clamped at the faces) interpolated in p's own cell, the
    /// same function from 32 voxels instead of 48 ([`packet::Gradient8`] in the lanes). A
    /// point past the box is clamped onto it first.
    pub(crate) fn gradient(&self, p: &Vector3<f32>) -> Vector3<f32> {
        let strides = [1, self.cell.nx, self.cell.nxy];
        let cells = [0, 1, 2].map(|a| self.cell_of(p[a], a));
        // Per axis the voxels before, at, after and two after the cell's first, clamped.
        let rows = [0, 1, 2].map(|a| {
            let (i, last) = (cells[a].0, self.top[a] as i32);
            [(i - 1).max(0), i, (i + 1).min(last), (i + 2).min(last)].map(|v| (v * strides[a]) as usize)
        });
        let fractions = cells.map(|c| c.1);
        Vector3::from(std::array::from_fn(|a| {
            let difference = |c: usize| {
                let corner = [c & 1, c >> 1 & 1, c >> 2 & 1];
                let at = |shift: usize| {
                    let row = |b: usize| rows[b][if a == b { shift + corner[b] } else { 1 + corner[b] }];
                    self.data[row(0) + row(1) + row(2)]
                };
                at(2) - at(0)
            };
            defvol_core::volume::lerp_cube(difference, [1, 2, 4], fractions) * 0.5
        }))
    }

    /// Samples at `base + step·(first + n)` into `out`: eight at a time where AVX2 serves,
    /// else one by one.
    #[inline(always)]
    pub(crate) fn along(&self, base: Vector3<f32>, step: Vector3<f32>, first: usize, out: &mut [f32]) {
        if trilinear_lanes(self.data, &self.cell, out, base.into(), step.into(), first as i32, None) == 0 {
            for (k, value) in (first..).zip(out.iter_mut()) {
                *value = self.at(&(base + step * k as f32));
            }
        }
    }
}

/// A ray in the volume's index space, clipped to it and to a tool in front.
struct Clipped {
    o: Vector3<f32>,
    d: Vector3<f32>,
    t_near: f32,
    t_far: f32,
    /// What lies behind the volume on this ray (the background or the tool), and where.
    bg: [f32; 4],
    behind: f32,
    /// Toward the light, world frame.
    light: Vector3<f64>,
    tool: bool,
}

/// A ray as the caster sets it up.
enum Setup {
    /// It misses the volume: the pixel and its depth.
    Missed([f32; 4], f32),
    Inside(Clipped),
}

/// The full segments of `step` in [t_near, t_far], and the length left after them.
#[inline(always)]
fn segments(t_near: f32, t_far: f32, step: f32) -> (usize, f32) {
    let full = ((t_far - t_near) / step).floor() as usize;
    (full, (t_far - t_near) - full as f32 * step)
}

struct Caster<'a> {
    /// Eight rays at once, where they serve (see `cast_packet`).
    #[cfg(target_arch = "x86_64")]
    packets: Option<Trilinear8<'a>>,
    /// The lanes' gradients, which shaded packets need.
    #[cfg(target_arch = "x86_64")]
    gradients: Option<packet::Gradient8<'a>>,
    /// An index-space gradient to a world one (`IndexSpace::gradient_to_world`), made once.
    to_world: [[f32; 3]; 3],
    volume: &'a Volume,
    sampler: Sampler<'a>,
    tables: &'a Tables,
    cells: Option<&'a MacroCells>,
    space: &'a IndexSpace,
    params: &'a RaycastParams,
    gradient_scale: f32,
}

impl Caster<'_> {
    /// The pixels `xs` of rows `ys`, each handed to `put` with its (x, y): a [`packet::Block`]
    /// at once where packets serve these parameters, else one by one.
    fn cast_tile(
        &self,
        rays: &Rays,
        (xs, ys): (std::ops::Range<usize>, std::ops::Range<usize>),
        mut put: impl FnMut((usize, usize), ([f32; 4], f32)),
    ) {
        #[cfg(target_arch = "x86_64")]
        if let Some(trilinear) = self.packets {
            use packet::Block;
            for py in ys.clone().step_by(Block::ROWS) {
                for px in xs.clone().step_by(Block::COLUMNS) {
                    let block = Block { corner: (px, py), size: (xs.end - px, ys.end - py) };
                    let pixels = self.cast_packet(trilinear, rays, block);
                    for (l, pixel) in pixels.into_iter().enumerate() {
                        if let Some(at) = block.pixel(l) {
                            put(at, pixel);
                        }
                    }
                }
            }
            return;
        }
        for py in ys {
            for px in xs.clone() {
                let (origin, direction) = rays.ray(px, py);
                put((px, py), self.cast(&origin, &direction));
            }
        }
    }

    /// Trilinear, clamped (rays are clipped to the box, so only round-off and the
    /// gradient's neighbours at the border are clamped).
    #[inline(always)]
    fn sample(&self, p: &Vector3<f32>) -> f32 {
        self.sampler.at(p)
    }

    /// Samples at the ray's parameters t_near + (first + n + offset)·step into `out`.
    #[inline(always)]
    fn samples_along(&self, ray: &Ray, offset: f32, first: usize, out: &mut [f32]) {
        self.sampler.along(ray.o + ray.d * (ray.t_near + offset * ray.step), ray.d * ray.step, first, out);
    }

    /// Lambert factor at p for the light (index-space direction `light_index`, world `light`).
    fn shade(&self, p: &Vector3<f32>, light: &Vector3<f64>, light_index: &Vector3<f32>) -> f32 {
        let ambient = self.params.ambient as f32;
        match self.params.shading {
            Shading::None => 1.0,
            Shading::Gradient => {
                let g = self.sampler.gradient(p);
                let w = Vector3::from(self.to_world.map(|row| row[0] * g.x + row[1] * g.y + row[2] * g.z));
                lambert(&w, &light.cast::<f32>(), ambient)
            }
            Shading::ForwardDifference => {
                // ∇f·l ≈ (f(p + δl) - f(p)) / δ, δ = one world unit; the surface faces the
                // light where values fall toward it.
                lit_by_drop(self.sample(p) - self.sample(&(p + light_index)), self.gradient_scale, ambient)
            }
        }
    }

    /// The ray in index space clipped to the volume (and to the tool in front), or the
    /// pixel itself where the ray misses the volume.
    fn clip_ray(&self, origin: &Point3<f64>, direction: &Vector3<f64>) -> Setup {
        let light = self.params.light.map_or(-direction, |l| Vector3::from(l).normalize());
        let tool = nearest_tool(&self.params.tools, self.params.ambient, origin, direction, &light);
        // A tool hides what lies behind it: it is the background of the ray from its surface.
        let (bg, behind) = match tool {
            Some((t, color)) => (color, t),
            None => (self.params.background.map(|c| c as f32), f32::INFINITY),
        };
        let (o, d) = self.space.ray(origin, direction);
        let inside = clip(self.volume.dims(), &o, &d);
        Self::set_up(&o, &d, inside, (bg, behind), light, tool.is_some())
    }

    /// A ray in index space (`o + d·t`) inside the box over `inside`, as far as what lies
    /// `behind` it (where `bg` is seen): clipped, or missed where nothing is left.
    fn set_up(
        o: &Vector3<f64>,
        d: &Vector3<f64>,
        inside: Option<(f64, f64)>,
        (bg, behind): ([f32; 4], f32),
        light: Vector3<f64>,
        tool: bool,
    ) -> Setup {
        let Some((t_near, t_far)) = inside else { return Setup::Missed(bg, behind) };
        let (t_near, t_far) = (t_near as f32, (t_far as f32).min(behind));
        if t_far < t_near {
            return Setup::Missed(bg, behind);
        }
        Setup::Inside(Clipped { o: o.cast::<f32>(), d: d.cast::<f32>(), t_near, t_far, bg, behind, light, tool })
    }

    /// Premultiplied RGBA over the background (or the tool), and the depth where opacity
    /// passed 0.5 (or the tool's surface).
    fn cast(&self, origin: &Point3<f64>, direction: &Vector3<f64>) -> ([f32; 4], f32) {
        let Clipped { o, d, t_near, t_far, bg, behind, light, tool } = match self.clip_ray(origin, direction) {
            Setup::Missed(bg, behind) => return (bg, behind),
            Setup::Inside(clipped) => clipped,
        };
        let light_index = (self.space.index_from_world * light).cast::<f32>();
        let step = self.params.step as f32;
        let steps = ((t_far - t_near) / step).floor() as usize;
        match self.params.mode {
            Mode::Mip => {
                if tool {
                    return (bg, behind);
                }
                let mut peak = f32::NEG_INFINITY;
                for k in 0..=steps {
                    peak = peak.max(self.sample(&(o + d * (t_near + k as f32 * step))));
                }
                let v = ((peak - self.tables.lo) / (self.tables.hi - self.tables.lo)).clamp(0.0, 1.0);
                ([v, v, v, 1.0], f32::INFINITY)
            }
            Mode::Iso => {
                let (color, depth) = self.iso(&o, &d, t_near, steps, step, &light, &light_index, bg);
                (color, if depth.is_finite() { depth } else { behind })
            }
            Mode::Composite => {
                let ray = match self.params.shading {
                    Shading::None => self.composite(&o, &d, t_near, t_far, |_| 1.0),
                    _ => self.composite(&o, &d, t_near, t_far, |p| self.shade(p, &light, &light_index)),
                };
                ray.over(bg, behind)
            }
        }
    }

    /// Front-to-back over segments of `step` (the last one shorter), each point-sampled at
    /// its middle or pre-integrated between its ends. The full segments go in runs that
    /// stay inside one visible macro cell (looked up once per cell), each run a tight loop.
    fn composite<'r>(
        &self,
        o: &'r Vector3<f32>,
        d: &'r Vector3<f32>,
        t_near: f32,
        t_far: f32,
        shade: impl Fn(&Vector3<f32>) -> f32,
    ) -> Ray<'r> {
        let step = self.params.step as f32;
        let (full, remainder) = segments(t_near, t_far, step);
        let mut ray = Ray { o, d, t_near, step, acc: [0.0; 4], depth: f32::INFINITY, front: None };
        let termination = self.params.early_termination as f32;
        let mut k = 0usize;
        let mut terminated = false;
        while k < full && !terminated {
            let end = self.run_end(&mut ray, &mut k, full);
            terminated = if self.params.preintegrated {
                // Between the segment's ends; the back scalar of one is the front of the next.
                ray.run((self, k..end, 1.0), &shade, termination, |ray, k, back| {
                    let front = ray.front.unwrap_or_else(|| self.front(ray, k));
                    ray.front = Some(back);
                    self.tables.segment(front, back)
                })
            } else {
                // At the segment's middle.
                ray.run((self, k..end, 0.5), &shade, termination, |_, _, middle| self.tables.sample_step(middle))
            };
            k = end.max(k);
        }
        if !terminated && remainder > 1e-6 * step {
            ray.last_segment(self, full, remainder, &shade);
        }
        ray
    }

    /// The end of the run of full segments from `k` (< `full`): every segment that starts
    /// inside a visible macro cell, or only the one that crosses out of an invisible cell,
    /// after `k` jumped over the segments wholly inside it (which add nothing; the scalar at
    /// the next segment's front is then read anew).
    #[inline(always)]
    fn run_end(&self, ray: &mut Ray, k: &mut usize, full: usize) -> usize {
        let Some(cells) = self.cells else { return full };
        let t0 = ray.t_near + *k as f32 * ray.step;
        let p0 = ray.o + ray.d * t0;
        let exit = cells.exit(&p0, ray.d, t0);
        if cells.visible_at(&p0) {
            // Every segment that starts inside the cell.
            (((exit - ray.t_near) / ray.step).ceil() as usize).clamp(*k + 1, full)
        } else {
            let inside = ((exit - ray.t_near) / ray.step).floor() as usize;
            if inside > *k {
                *k = inside;
                ray.front = None;
            }
            (*k + 1).min(full)
        }
    }

    /// The scalar at the front of segment `k`: the back of segment k - 1, at the point
    /// `samples_along` gives it (so the packets' lanes, which read it as such, agree).
    #[inline(always)]
    fn front(&self, ray: &Ray, k: usize) -> f32 {
        let back = ray.o + ray.d * (ray.t_near + ray.step);
        self.sample(&(back + ray.d * ray.step * (k as i32 - 1) as f32))
    }

    #[allow(clippy::too_many_arguments)]
    fn iso(
        &self,
        o: &Vector3<f32>,
        d: &Vector3<f32>,
        t_near: f32,
        steps: usize,
        step: f32,
        light: &Vector3<f64>,
        light_index: &Vector3<f32>,
        bg: [f32; 4],
    ) -> ([f32; 4], f32) {
        let iso = self.params.iso_value as f32;
        let mut prev = self.sample(&(o + d * t_near));
        for k in 1..=steps {
            let t = t_near + k as f32 * step;
            let s = self.sample(&(o + d * t));
            if (prev - iso) * (s - iso) <= 0.0 && prev != s {
                // Bisection on [t - step, t] for the crossing.
                let (mut a, mut b, mut sa) = (t - step, t, prev);
                for _ in 0..12 {
                    let m = 0.5 * (a + b);
                    let sm = self.sample(&(o + d * m));
                    if (sa - iso) * (sm - iso) <= 0.0 {
                        b = m;
                    } else {
                        (a, sa) = (m, sm);
                    }
                }
                let hit = 0.5 * (a + b);
                let e = self.tables.sample(iso);
                let base = if e[0] + e[1] + e[2] > 0.0 { [e[0], e[1], e[2]] } else { [1.0; 3] };
                let shade = self.shade(&(o + d * hit), light, light_index);
                return ([base[0] * shade, base[1] * shade, base[2] * shade, 1.0], hit);
            }
            prev = s;
        }
        (bg, f32::INFINITY)
    }
}

/// Packets of eight rays for the composite picture (the vector half in `cpu/packet.rs`):
/// ray set-up and the last, shorter segment are scalar, as in `cast`; the macro-cell walk,
/// the steps through the runs and their shading eight wide; the pixels are `cast`'s bits.
#[cfg(target_arch = "x86_64")]
impl<'a> Caster<'a> {
    /// The eight-point sampler where packets give this caster's pictures: composite, AVX2
    /// present, the volume inside the sampler's reach (and the gradients' where shaded).
    fn packet_sampler(&self) -> Option<Trilinear8<'a>> {
        if self.params.mode != Mode::Composite || (self.params.shading != Shading::None && self.gradients.is_none()) {
            return None;
        }
        Trilinear8::new(self.volume.data(), &self.sampler.cell)
    }

    /// The block's pixels, lane by lane: colour and depth, as `cast` gives them (lanes past
    /// the picture's edge the background).
    fn cast_packet(
        &self,
        trilinear: Trilinear8<'a>,
        rays: &Rays,
        block: packet::Block,
    ) -> [([f32; 4], f32); packet::LANES] {
        let mut pixels = [([0.0; 4], f32::INFINITY); packet::LANES];
        let mut clipped: [Option<Clipped>; packet::LANES] = Default::default();
        // SAFETY: a Trilinear8 exists only where the CPU has AVX2.
        let setups = unsafe { self.clip_packet(rays, block) };
        for ((pixel, lane), setup) in pixels.iter_mut().zip(&mut clipped).zip(setups) {
            match setup {
                Setup::Missed(bg, behind) => *pixel = (bg, behind),
                Setup::Inside(c) => *lane = Some(c),
            }
        }
        let step = self.params.step as f32;
        let mut rays = clipped.each_ref().map(|c| {
            c.as_ref().map(|c| Ray {
                o: &c.o,
                d: &c.d,
                t_near: c.t_near,
                step,
                acc: [0.0; 4],
                depth: f32::INFINITY,
                front: None,
            })
        });
        // Each ray's full segments and the last, shorter one's length, worked out once.
        let split = clipped.each_ref().map(|c| c.as_ref().map_or((0, 0.0), |c| segments(c.t_near, c.t_far, step)));
        // SAFETY: a Trilinear8 exists only where the CPU has AVX2.
        let terminated = unsafe { self.composite_packet(trilinear, &mut rays, &clipped, split.map(|s| s.0)) };
        for l in 0..packet::LANES {
            let (Some(ray), Some(c)) = (&mut rays[l], &clipped[l]) else { continue };
            let (full, remainder) = split[l];
            if !terminated[l] && remainder > 1e-6 * step {
                let light_index = (self.space.index_from_world * c.light).cast::<f32>();
                ray.last_segment(self, full, remainder, &|p: &Vector3<f32>| self.shade(p, &c.light, &light_index));
            }
            pixels[l] = ray.over(c.bg, c.behind);
        }
        pixels
    }

    /// `Rays::ray` then [`Self::clip_ray`] for the block's rays, the same bits: eight at once
    /// in the lanes for a perspective camera with no tool in the scene, else ray by ray
    /// (lanes past the picture's edge miss).
    #[target_feature(enable = "avx2")]
    fn clip_packet(&self, rays: &Rays, block: packet::Block) -> [Setup; packet::LANES] {
        let background = self.params.background.map(|c| c as f32);
        let missed = || Setup::Missed(background, f32::INFINITY);
        if !rays.is_perspective() || !self.params.tools.is_empty() {
            return std::array::from_fn(|l| {
                let Some((px, py)) = block.pixel(l) else { return missed() };
                let (origin, direction) = rays.ray(px, py);
                self.clip_ray(&origin, &direction)
            });
        }
        let o = self.space.index_from_world * (rays.eye.coords - self.space.origin);
        let top = self.volume.dims().map(|n| (n - 1) as f64);
        let lanes = packet::setup8(rays, &self.space.index_from_world, (o.into(), top), block.corner);
        let light = self.params.light.map(|l| Vector3::from(l).normalize());
        std::array::from_fn(|l| {
            if block.pixel(l).is_none() {
                return missed();
            }
            let lane = |v: &[[f64; packet::LANES]; 3]| Vector3::from(std::array::from_fn(|a| v[a][l]));
            let inside = lanes.inside[l].then_some((lanes.near[l], lanes.far[l]));
            let light = light.unwrap_or(-lane(&lanes.direction));
            Self::set_up(&o, &lane(&lanes.d), inside, (background, f32::INFINITY), light, false)
        })
    }

    /// The `full` segments of the packet's rays, front to back, into each ray's `acc`,
    /// `depth` and `front`; which rays terminated.
    #[target_feature(enable = "avx2")]
    fn composite_packet(
        &self,
        trilinear: Trilinear8<'a>,
        rays: &mut [Option<Ray>; packet::LANES],
        clipped: &[Option<Clipped>; packet::LANES],
        full: [usize; packet::LANES],
    ) -> [bool; packet::LANES] {
        const LANES: usize = packet::LANES;
        let step = self.params.step as f32;
        let mut lanes =
            packet::PacketRays { o: [[0.0; LANES]; 3], d: [[0.0; LANES]; 3], t_near: [0.0; LANES], full: [0; LANES] };
        for (l, c) in clipped.iter().enumerate() {
            let Some(c) = c else { continue };
            for a in 0..3 {
                (lanes.o[a][l], lanes.d[a][l]) = (c.o[a], c.d[a]);
            }
            (lanes.t_near[l], lanes.full[l]) = (c.t_near, full[l]);
        }
        let cells = self.cells.map(|cells| packet::CellWalk { visible: &cells.visible, dims: cells.dims, edge: CELL });
        let lanes = packet::Lanes::new(
            (trilinear, self.tables, self.params.preintegrated),
            (cells, self.packet_shading(clipped)),
            &lanes,
            (step, self.params.early_termination as f32),
        );
        let end = lanes.runs();
        for (l, ray) in rays.iter_mut().enumerate() {
            if let Some(ray) = ray {
                (ray.acc, ray.depth, ray.front) = (end.acc[l], end.depth[l], end.front[l]);
            }
        }
        end.terminated
    }

    /// What the lanes need to shade as `shade` does: none for an unshaded picture (a
    /// shaded one has packets only with gradients, `packet_sampler`).
    fn packet_shading(&self, clipped: &[Option<Clipped>; packet::LANES]) -> Option<packet::PacketShading<'a>> {
        let by = self.params.shading.in_lanes()?;
        let mut shading = packet::PacketShading {
            gradients: self.gradients?,
            by,
            ambient: self.params.ambient as f32,
            gradient_scale: self.gradient_scale,
            to_world: self.to_world,
            light: [[0.0; packet::LANES]; 3],
            light_index: [[0.0; packet::LANES]; 3],
        };
        for (l, c) in clipped.iter().enumerate() {
            let Some(c) = c else { continue };
            let light_index = (self.space.index_from_world * c.light).cast::<f32>();
            for a in 0..3 {
                (shading.light[a][l], shading.light_index[a][l]) = (c.light[a] as f32, light_index[a]);
            }
        }
        Some(shading)
    }
}

/// Samples a run reads at once (eight-lane groups where AVX2 serves) before compositing
/// them: a ray that turns opaque wastes at most this many minus one.
const BATCH: usize = 16;

/// One ray's front-to-back state while its segments are composited.
struct Ray<'a> {
    o: &'a Vector3<f32>,
    d: &'a Vector3<f32>,
    t_near: f32,
    step: f32,
    acc: [f32; 4],
    /// Where opacity passed 0.5.
    depth: f32,
    /// The scalar at the start of the next pre-integrated segment, when it was read.
    front: Option<f32>,
}

impl Ray<'_> {
    /// The composited colour over what lies behind it (`bg` at `behind`), and the depth.
    fn over(&self, bg: [f32; 4], behind: f32) -> ([f32; 4], f32) {
        let (acc, rest) = (self.acc, 1.0 - self.acc[3]);
        let color = [
            acc[0] + rest * bg[0] * bg[3],
            acc[1] + rest * bg[1] * bg[3],
            acc[2] + rest * bg[2] * bg[3],
            acc[3] + rest * bg[3],
        ];
        (color, if self.depth.is_finite() { self.depth } else { behind })
    }

    /// Adds a segment's premultiplied colour and α, shaded at its middle; whether the ray is
    /// now opaque enough to stop.
    #[inline(always)]
    fn add(&mut self, color: [f32; 4], middle_t: f32, shade: &impl Fn(&Vector3<f32>) -> f32, termination: f32) -> bool {
        if color[3] <= 1e-5 {
            return false;
        }
        let light = shade(&(self.o + self.d * middle_t));
        let weight = 1.0 - self.acc[3];
        for c in 0..3 {
            self.acc[c] += weight * color[c] * light;
        }
        self.acc[3] += weight * color[3];
        if self.depth.is_infinite() && self.acc[3] >= 0.5 {
            self.depth = middle_t;
        }
        self.acc[3] >= termination
    }

    /// Full segments `ks` in batches: a batch's samples at t_near + (k + offset)·step taken
    /// at once, then each segment's colour, `segment(ray, k, sample)`, composited; whether
    /// the ray terminated.
    #[inline(always)]
    fn run(
        &mut self,
        (caster, ks, offset): (&Caster, std::ops::Range<usize>, f32),
        shade: &impl Fn(&Vector3<f32>) -> f32,
        termination: f32,
        segment: impl Fn(&mut Self, usize, f32) -> [f32; 4],
    ) -> bool {
        let mut values = [0.0f32; BATCH];
        for first in ks.clone().step_by(BATCH) {
            let values = &mut values[..(ks.end - first).min(BATCH)];
            caster.samples_along(self, offset, first, values);
            for (k, value) in (first..).zip(values.iter()) {
                let color = segment(self, k, *value);
                if self.add(color, self.t_near + k as f32 * self.step + 0.5 * self.step, shade, termination) {
                    return true;
                }
            }
        }
        false
    }

    /// The shorter last segment, segment index `k` of length `len`: the same extinction
    /// over less length.
    fn last_segment(&mut self, caster: &Caster, k: usize, len: f32, shade: &impl Fn(&Vector3<f32>) -> f32) {
        let t0 = self.t_near + k as f32 * self.step;
        let middle_t = t0 + 0.5 * len;
        let color = if caster.params.preintegrated {
            let front = self.front.unwrap_or_else(|| caster.sample(&(self.o + self.d * t0)));
            let seg = caster.tables.segment(front, caster.sample(&(self.o + self.d * (t0 + len))));
            let alpha = 1.0 - (1.0 - seg[3]).max(0.0).powf(len / self.step);
            let scale = if seg[3] > 0.0 { alpha / seg[3] } else { len / self.step };
            [seg[0] * scale, seg[1] * scale, seg[2] * scale, alpha]
        } else {
            let e = caster.tables.sample(caster.sample(&(self.o + self.d * middle_t)));
            let alpha = 1.0 - (-e[3] * len).exp();
            [e[0] * alpha, e[1] * alpha, e[2] * alpha, alpha]
        };
        self.add(color, middle_t, shade, f32::INFINITY);
    }
}

/// The ray integral in f64 by point sampling at `step` with the exact transfer function, no
/// skipping or termination, unshaded: the reference the fast paths are measured against
/// (a small step converges to the exact emission-absorption integral).
pub fn reference(
    volume: &Volume,
    camera: &Camera,
    tf: &TransferFunction,
    step: f64,
    background: [f64; 4],
) -> Result<Vec<[f64; 4]>, RenderError> {
    camera.validate()?;
    let tf = tf.resolve(volume.range())?;
    let space = IndexSpace::of(&volume.grid());
    let (w, h) = (camera.width, camera.height);
    Ok((0..w * h)
        .into_par_iter()
        .map(|i| {
            let (origin, direction) = camera.ray(i % w, i / w);
            let (o, d) = space.ray(&origin, &direction);
            let mut acc = [0.0f64; 4];
            if let Some((t0, t1)) = clip(volume.dims(), &o, &d) {
                // Midpoint rule over [t0, t1].
                let n = ((t1 - t0) / step).ceil().max(1.0) as usize;
                let ds = (t1 - t0) / n as f64;
                for k in 0..n {
                    let p = o + d * (t0 + (k as f64 + 0.5) * ds);
                    let Some(s) = trilinear::<f64>(volume.data(), volume.dims(), p.x, p.y, p.z, 1e-6) else { continue };
                    let (c, tau) = tf.eval(s);
                    let alpha = 1.0 - (-tau * ds).exp();
                    let weight = (1.0 - acc[3]) * alpha;
                    for ch in 0..3 {
                        acc[ch] += weight * c[ch];
                    }
                    acc[3] += weight;
                }
            }
            let rest = 1.0 - acc[3];
            [0, 1, 2, 3].map(|c| {
                if c < 3 {
                    acc[c] + rest * background[c] * background[3]
                } else {
                    acc[3] + rest * background[3]
                }
            })
        })
        .collect())
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use nalgebra::{Matrix3, Point3, Vector3};

    use super::{clip, nearest_tool, IndexSpace, RaycastParams, Shading, ToolPicture, VolumeRaycaster};
    use crate::camera::{Camera, Projection};
    use crate::transfer::TransferFunction;
    use defvol_core::volume::{phantom, Volume};

    /// An oblique perspective view of `volume` from outside its box, `size` a side.
    fn oblique(volume: &Volume, (width, height): (usize, usize)) -> Camera {
        let (lo, hi) = volume.bounds();
        let centre = Point3::from((lo + hi) / 2.0);
        let eye = centre + (hi - lo).component_mul(&Vector3::new(-0.6, -1.7, 0.9));
        Camera::look_at(eye, centre, Vector3::z(), Projection::Perspective { fov_y_deg: 40.0 }, width, height).unwrap()
    }

    /// A ball of tissue in a box of air (most macro cells invisible, so rays jump over
    /// runs of them).
    fn ball_in_air() -> Volume {
        let n = [40usize, 33, 29];
        let data = (0..n[0] * n[1] * n[2])
            .map(|i| {
                let p = Vector3::new((i % n[0]) as f64, (i / n[0] % n[1]) as f64, (i / (n[0] * n[1])) as f64);
                let r = (p - Vector3::new(22.0, 15.0, 13.0)).norm();
                (-1000.0 + 1100.0 * (1.0 - r / 9.0).clamp(0.0, 1.0)) as f32
            })
            .collect();
        Volume::new(n, [1.5, 1.0, 1.2], [3.0, -2.0, 1.0], Matrix3::identity(), data, "ball").unwrap()
    }

    /// Blocks of tissue (80 HU) a macro cell apart in fat just too dark to see (-250 HU),
    /// each block a voxel inside its cell so the cells between stay dark: the first sample
    /// after a jump often lies in the tissue's ramp, so it adds.
    fn blocks_in_fat() -> Volume {
        let n = [40usize, 33, 29];
        let inside = |v: usize| (9..16).contains(&(v % 16));
        let data =
            (0..n[0] * n[1] * n[2])
                .map(|i| {
                    if inside(i % n[0]) && inside(i / n[0] % n[1]) && inside(i / (n[0] * n[1])) {
                        80.0
                    } else {
                        -250.0
                    }
                })
                .collect();
        Volume::new(n, [1.0, 0.9, 1.1], [3.0, -2.0, 1.0], Matrix3::identity(), data, "blocks").unwrap()
    }

    /// Trilinear in f64 at `p` clamped to the voxel-centre box of `dims`.
    fn trilinear_f64(data: &[f32], dims: [usize; 3], p: [f64; 3]) -> f64 {
        let cell = |a: usize| {
            let v = p[a].clamp(0.0, (dims[a] - 1) as f64);
            let i = (v.floor() as usize).min(dims[a].saturating_sub(2));
            (i, v - i as f64)
        };
        let [(i, fx), (j, fy), (k, fz)] = [0, 1, 2].map(cell);
        let at = |x: usize, y: usize, z: usize| {
            let [x, y, z] = [(i + x, 0), (j + y, 1), (k + z, 2)].map(|(v, a)| v.min(dims[a] - 1));
            f64::from(data[x + dims[0] * (y + dims[1] * z)])
        };
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let y0 = |z| lerp(lerp(at(0, 0, z), at(1, 0, z), fx), lerp(at(0, 1, z), at(1, 1, z), fx), fy);
        lerp(y0(0), y0(1), fz)
    }

    /// The gradient read from the grid's central differences is the difference of clamped
    /// trilinear samples a voxel either side (f64) at points inside and on every face, and
    /// the eight-lane gradients are the scalar ones to the bit there and past the faces;
    /// grids with an axis one and two voxels thick.
    #[test]
    fn gradients_are_central_differences_of_clamped_samples() {
        let mut rng = fastrand::Rng::with_seed(7);
        for dims in [[9usize, 7, 6], [5, 1, 4], [2, 6, 3]] {
            let data: Vec<f32> = (0..dims.iter().product()).map(|_| rng.f32() * 200.0 - 100.0).collect();
            let sampler = super::Sampler::new(&data, dims);
            let points: Vec<[f32; 3]> = (0..4000)
                .map(|n| {
                    std::array::from_fn(|a| {
                        let top = (dims[a] - 1) as f32;
                        // Every tenth coordinate on a face or a voxel centre.
                        match n % 10 {
                            0 => 0.0,
                            1 => top,
                            2 => rng.usize(0..dims[a]) as f32,
                            _ => rng.f32() * (top + 3.0) - 1.5,
                        }
                    })
                })
                .collect();
            // The point itself is clamped first: past a face the two definitions part.
            let inside = |p: &&[f32; 3]| (0..3).all(|a| (0.0..=(dims[a] - 1) as f32).contains(&p[a]));
            let mut compared = 0;
            for p in points.iter().filter(inside) {
                compared += 1;
                let got = sampler.gradient(&Vector3::from(*p));
                for a in 0..3 {
                    let moved = |by: f64| std::array::from_fn(|b| f64::from(p[b]) + if a == b { by } else { 0.0 });
                    let want = (trilinear_f64(&data, dims, moved(1.0)) - trilinear_f64(&data, dims, moved(-1.0))) / 2.0;
                    assert!(
                        (f64::from(got[a]) - want).abs() < 1e-3,
                        "{dims:?} at {p:?}, axis {a}: {got} against {want}"
                    );
                }
            }
            assert!(compared > 1000, "{compared}");
            #[cfg(target_arch = "x86_64")]
            if let Some(lanes) = super::packet::Gradient8::new(&data, dims) {
                for eight in points.chunks_exact(8) {
                    // SAFETY (here and below): a Gradient8 exists only where the CPU has AVX2.
                    let axis = |a: usize| unsafe { super::packet::load(std::array::from_fn(|l| eight[l][a])) };
                    let got =
                        unsafe { lanes.at([axis(0), axis(1), axis(2)]) }.map(|v| unsafe { super::packet::store(v) });
                    for (l, p) in eight.iter().enumerate() {
                        let want = sampler.gradient(&Vector3::from(*p));
                        assert_eq!(
                            [0, 1, 2].map(|a| got[a][l].to_bits()),
                            [0, 1, 2].map(|a| want[a].to_bits()),
                            "{p:?}"
                        );
                    }
                }
            }
        }
    }

    /// The packets' ray set-up, eight lanes of f64, is `Rays::ray`, `IndexSpace::ray` and
    /// `clip` ray by ray to the bit: a grid turned off the world's axes (so every term of
    /// both matrix products counts), cameras inside and outside the box, rays that miss.
    #[test]
    fn packets_set_up_their_rays_as_the_one_ray_caster() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            eprintln!("skipped: no AVX2 on this CPU");
            return;
        }
        let direction = nalgebra::Rotation3::from_euler_angles(0.3, -0.5, 0.9).into_inner();
        let volume =
            Volume::new([40, 33, 29], [1.5, 1.0, 1.2], [3.0, -2.0, 1.0], direction, vec![0.0; 40 * 33 * 29], "turned")
                .unwrap();
        let space = IndexSpace::of(&volume.grid());
        let top = volume.dims().map(|n| (n - 1) as f64);
        let (lo, hi) = volume.bounds();
        let centre = Point3::from((lo + hi) / 2.0);
        let (mut inside, mut missed) = (0, 0);
        for (eye, fov) in [
            (Vector3::new(-0.6, -1.7, 0.9), 40.0),
            (Vector3::new(0.1, 0.05, -0.02), 100.0),
            (Vector3::new(2.0, 0.3, 0.1), 25.0),
        ] {
            let eye = centre + (hi - lo).component_mul(&eye);
            let camera = Camera::look_at(
                eye,
                centre + Vector3::new(0.0, 0.0, 5.0),
                Vector3::z(),
                Projection::Perspective { fov_y_deg: fov },
                45,
                37,
            )
            .unwrap();
            let rays = camera.rays();
            assert!(rays.is_perspective());
            let o = space.index_from_world * (rays.eye.coords - space.origin);
            for py0 in 0..camera.height - 1 {
                for px0 in (0..camera.width - 3).step_by(3) {
                    // SAFETY: the CPU has AVX2 (checked above).
                    let lanes =
                        unsafe { super::packet::setup8(&rays, &space.index_from_world, (o.into(), top), (px0, py0)) };
                    for l in 0..super::packet::LANES {
                        let (px, py) = (px0 + l % 4, py0 + l / 4);
                        let (origin, world) = rays.ray(px, py);
                        let (want_o, d) = space.ray(&origin, &world);
                        assert_eq!(want_o.map(f64::to_bits), o.map(f64::to_bits));
                        for a in 0..3 {
                            assert_eq!(lanes.direction[a][l].to_bits(), world[a].to_bits(), "pixel ({px}, {py})");
                            assert_eq!(lanes.d[a][l].to_bits(), d[a].to_bits(), "pixel ({px}, {py})");
                        }
                        let want = clip(volume.dims(), &want_o, &d);
                        assert_eq!(lanes.inside[l], want.is_some(), "pixel ({px}, {py})");
                        if let Some((near, far)) = want {
                            assert_eq!(
                                (lanes.near[l].to_bits(), lanes.far[l].to_bits()),
                                (near.to_bits(), far.to_bits())
                            );
                            inside += 1;
                        } else {
                            missed += 1;
                        }
                    }
                }
            }
        }
        assert!(inside > 1000 && missed > 1000, "{inside} {missed}");
    }

    /// Every pixel of eight-ray packets is the one-ray caster's, colour and depth to the
    /// bit: point-sampled and pre-integrated, unshaded, gradient-shaded and shaded by the
    /// forward difference (the camera's light and one of its own), with and without
    /// empty-space skipping, early termination often and rarely reached, a tool in view,
    /// packets cut by the picture's right and bottom edges (45x37), over the phantom
    /// (tissue everywhere), a ball in air (rays jumping invisible cells) and blocks in fat
    /// (rays landing in tissue after each jump).
    #[test]
    fn packets_give_the_one_ray_casters_bits() {
        let tf = TransferFunction::preset("ct_soft_tissue").unwrap();
        let (mut compared, mut tissue, mut tool_hits, mut jumped) = (0usize, 0usize, 0usize, false);
        for volume in [phantom::phantom([64, 40, 31], 4.0).unwrap(), ball_in_air(), blocks_in_fat()] {
            let camera = oblique(&volume, (45, 37));
            let (lo, hi) = volume.bounds();
            let tip = ((lo + hi) / 2.0 - (hi - lo).component_mul(&Vector3::new(0.1, 0.45, -0.1))).into();
            let tool = ToolPicture { tip, tail: [tip[0], tip[1], hi.z + 10.0], radius: 3.0, color: [0.9, 0.8, 0.1] };
            // A light of its own (the camera's where none), turned off every axis.
            let (none, gradient, forward) = (Shading::None, Shading::Gradient, Shading::ForwardDifference);
            let lit = Some([0.3, -0.8, 0.5]);
            for (preintegrated, empty_space_skipping, early_termination, tools, (shading, light)) in [
                (false, true, 0.999, vec![], (none, None)),
                (true, true, 0.999, vec![], (none, None)),
                (false, false, 0.9, vec![tool], (none, None)),
                (true, true, 0.9, vec![tool], (none, None)),
                (true, false, 0.999, vec![], (none, None)),
                (true, true, 0.999, vec![], (gradient, None)),
                (false, true, 0.9, vec![tool], (gradient, lit)),
                (true, false, 0.999, vec![], (forward, None)),
                (false, true, 0.999, vec![tool], (forward, lit)),
            ] {
                let params = RaycastParams {
                    step: 0.7,
                    preintegrated,
                    shading,
                    light,
                    empty_space_skipping,
                    early_termination,
                    background: [0.2, 0.3, 0.4, 1.0],
                    tools,
                    ..Default::default()
                };
                let raycaster = VolumeRaycaster::new(&volume, &tf, &params).unwrap();
                let caster = raycaster.caster();
                if caster.packets.is_none() {
                    eprintln!("skipped: no AVX2 on this CPU");
                    return;
                }
                jumped |= caster
                    .cells
                    .is_some_and(|cells| 2 * cells.visible.iter().filter(|v| !**v).count() > cells.visible.len());
                // The picture as one tile: blocks walked as `render` walks them.
                let picture = (0..camera.width, 0..camera.height);
                caster.cast_tile(&camera.rays(), picture, |(px, py), (color, depth)| {
                    let (origin, direction) = camera.ray(px, py);
                    let (want, want_depth) = caster.cast(&origin, &direction);
                    assert_eq!(
                        (color.map(f32::to_bits), depth.to_bits()),
                        (want.map(f32::to_bits), want_depth.to_bits()),
                        "pixel ({px}, {py}), {params:?}: {color:?} at {depth} against {want:?} at {want_depth}"
                    );
                    tissue += usize::from(depth.is_finite());
                    let light = -direction;
                    tool_hits +=
                        usize::from(nearest_tool(&params.tools, params.ambient, &origin, &direction, &light).is_some());
                    compared += 1;
                });
            }
        }
        assert_eq!(compared, 3 * 9 * 45 * 37);
        // Both scenes show tissue and the tool; the ball's box is mostly invisible cells.
        assert!(jumped && tissue > 2000 && tool_hits > 100, "{jumped} {tissue} {tool_hits}");
    }
}
