//! Grid warp (seed 003): the source volume resampled through a deformed tetrahedral mesh.
//!
//! Each output voxel x₁ inside a deformed tet takes the source value at x₀, the point with
//! the same barycentric coordinates in the rest tet. Per tet both mappings fold into one
//! affine map from output voxel index to source voxel index, and the barycentric
//! coordinates into four affine functions of the output index, all computed in f64.
//!
//! Rasterization schemes (all make the same inside decisions, b_m ≥ 0 for all m, evaluated
//! by the same expression):
//! - `Spans` (the default): per row of the tet's box, the exact interval where all four
//!   barycentric coordinates are non-negative; only inside voxels are visited.
//! - `Culling`: the seed's 8-bit half-space masks on coarse points every 8 voxels; cells
//!   whose 8 corner masks share a bit are skipped, the rest tested voxel by voxel.
//! - `Bbox`: every voxel of the tet's box tested (the seed's baseline).
//!
//! Output slices are processed in parallel, each visiting the tets that overlap it in tet
//! order, so a run is deterministic and a voxel on a shared face takes the later tet's value.

// Errors are returned, not unwrapped (tests may unwrap).
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::expect_used))]

pub use defvol_core::volume::bspline;
pub mod engine;
#[cfg(feature = "gpu")]
pub mod gpu;

use std::sync::Arc;

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

pub use bspline::DisplacementVolume;
use bspline::{backward_all, CompiledDisplacement};
pub use defvol_core::volume::{tricubic, Sampling, SAMPLE_TOLERANCE};

use defvol_core::math::Real;
use defvol_core::mesh::TetMesh;
pub use defvol_core::volume::trilinear;
use defvol_core::volume::{Grid, Volume, VolumeError};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WarpError {
    #[error("{got} deformed positions for a mesh of {expected} nodes")]
    NodeCount { got: usize, expected: usize },
    #[error("deformed node {node} is not finite")]
    NonFiniteNode { node: usize },
    #[error("output grid {dims:?} needs {needed_mib} MiB, above the limit of {limit_mib} MiB")]
    TooLarge { dims: [usize; 3], needed_mib: u64, limit_mib: u64 },
    #[error("displacement volume {index}: {why}")]
    BadDisplacement { index: usize, why: String },
    #[error("output buffer holds {got} samples; the grid has {expected}")]
    BufferSize { got: usize, expected: usize },
    #[error(transparent)]
    Volume(#[from] VolumeError),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Scheme {
    Spans,
    Culling,
    Bbox,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WarpOptions {
    pub scheme: Scheme,
    pub sampling: Sampling,
    /// Value of output voxels outside every deformed tet.
    pub background: f32,
    /// Output voxels no tet covers keep the source's value there (for meshes covering
    /// part of the volume) instead of the background.
    pub keep_uncovered: bool,
    pub displacements: Vec<DisplacementVolume>,
    /// Refuse output grids larger than this (bytes of f32 samples).
    pub max_bytes: u64,
}

impl Default for WarpOptions {
    fn default() -> Self {
        Self {
            scheme: Scheme::Spans,
            sampling: Sampling::Trilinear,
            background: 0.0,
            keep_uncovered: false,
            displacements: Vec::new(),
            max_bytes: 4 << 30,
        }
    }
}

/// Work done by one warp.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct WarpStats {
    pub voxels: u64,
    /// Voxels whose barycentric coordinates were evaluated.
    pub candidates: u64,
    /// Voxel writes from inside a tet.
    pub inside: u64,
    /// Deformed tets skipped as inverted or degenerate.
    pub skipped_tets: u64,
}

impl std::ops::AddAssign for WarpStats {
    fn add_assign(&mut self, o: Self) {
        self.voxels += o.voxels;
        self.candidates += o.candidates;
        self.inside += o.inside;
        self.skipped_tets += o.skipped_tets;
    }
}

/// A voxel is inside a tet when every barycentric coordinate is ≥ -ε. Without it, voxels on
/// a mesh boundary that coincides with the lattice (a mesh built on the volume's box) fall
/// out by round-off; ε is far below a voxel (coordinates are in voxel units).
pub const INSIDE_TOLERANCE: f64 = 1e-9;

/// One tet's maps in output index space.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TetMap {
    /// Inclusive output voxel box, clipped to the grid.
    pub lo: [usize; 3],
    pub hi: [usize; 3],
    /// `b_m = bary[m][0] + bary[m][1]·i + bary[m][2]·j + bary[m][3]·k`.
    pub bary: [[f64; 4]; 4],
    /// Source index `r = src[r][0] + src[r][1]·i + src[r][2]·j + src[r][3]·k`.
    pub src: [[f64; 4]; 3],
    /// Deformed vertices in output index space.
    pub verts: [[f64; 3]; 4],
    /// `1 / bary[m][1]` (0 where that is 0): the span bounds without divisions per row.
    pub inv_c: [f64; 4],
    /// The rest tet lies inside the source's voxel-centre box, so its samples need no
    /// bounds test (true for meshes embedding the volume).
    pub src_inside: bool,
}

impl TetMap {
    /// Barycentric offsets of row (j, k): `b_m(i) + ε = a[m] + bary[m][1]·i`, with the
    /// tolerance ε = [`INSIDE_TOLERANCE`] folded in.
    #[inline]
    pub fn row(&self, j: usize, k: usize) -> [f64; 4] {
        let (j, k) = (j as f64, k as f64);
        self.bary.map(|b| b[0] + b[2] * j + b[3] * k + INSIDE_TOLERANCE)
    }

    #[inline]
    pub fn inside(&self, a: &[f64; 4], i: usize) -> bool {
        let i = i as f64;
        (0..4).all(|m| a[m] + self.bary[m][1] * i >= 0.0)
    }

    /// The inside voxels of row (j, k) as an inclusive range of i, exact w.r.t. `inside`.
    pub fn span(&self, a: &[f64; 4]) -> Option<(usize, usize)> {
        let (mut lo, mut hi) = (self.lo[0] as f64, self.hi[0] as f64);
        for m in 0..4 {
            let c = self.bary[m][1];
            if c > 0.0 {
                lo = lo.max((-a[m] * self.inv_c[m]).ceil());
            } else if c < 0.0 {
                hi = hi.min((-a[m] * self.inv_c[m]).floor());
            } else if a[m] < 0.0 {
                return None;
            }
        }
        // The divisions can be off by one at a tie: widen by one voxel, then settle on
        // the evaluated predicate (the inside set of a row is an interval).
        let (box_lo, box_hi) = (self.lo[0] as f64, self.hi[0] as f64);
        let mut lo = (lo - 1.0).clamp(box_lo, box_hi) as usize;
        let mut hi = (hi + 1.0).clamp(box_lo, box_hi) as usize;
        while lo <= hi && !self.inside(a, lo) {
            lo += 1;
        }
        while hi >= lo && !self.inside(a, hi) {
            if hi == 0 {
                return None;
            }
            hi -= 1;
        }
        (lo <= hi).then_some((lo, hi))
    }

    /// Rows j of slice k that can meet the tet: the y-range of its cross-section with the
    /// plane z = k, widened by one row (spans settle the exact set).
    pub fn section_rows(&self, k: usize) -> Option<(usize, usize)> {
        let z = k as f64;
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for a in 0..4 {
            let pa = self.verts[a];
            // Vertices within round-off of the plane belong to the section (a face lying
            // on a voxel plane must not lose its rows).
            if (pa[2] - z).abs() <= SAMPLE_TOLERANCE {
                lo = lo.min(pa[1]);
                hi = hi.max(pa[1]);
            }
            for b in a + 1..4 {
                let pb = self.verts[b];
                if (pa[2] - z) * (pb[2] - z) < 0.0 {
                    let y = pa[1] + (z - pa[2]) / (pb[2] - pa[2]) * (pb[1] - pa[1]);
                    lo = lo.min(y);
                    hi = hi.max(y);
                }
            }
        }
        if lo > hi {
            return None;
        }
        let j0 = (lo.ceil() - 1.0).max(self.lo[1] as f64);
        let j1 = (hi.floor() + 1.0).min(self.hi[1] as f64);
        (j0 <= j1).then_some((j0 as usize, j1 as usize))
    }
}

/// The maps of every tet; `None` for deformed tets that are inverted, degenerate or miss the grid.
pub fn tet_maps(
    rest: &TetMesh,
    deformed: &[Vector3<f64>],
    source: &Grid,
    grid: &Grid,
) -> Result<Vec<Option<TetMap>>, WarpError> {
    if deformed.len() != rest.nodes().len() {
        return Err(WarpError::NodeCount { got: deformed.len(), expected: rest.nodes().len() });
    }
    if let Some(node) = deformed.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        return Err(WarpError::NonFiniteNode { node });
    }
    let out_index: Vec<Vector3<f64>> = deformed.iter().map(|p| grid.index_from_world(*p)).collect();
    let src_index: Vec<Vector3<f64>> = rest.nodes().iter().map(|p| source.index_from_world(*p)).collect();
    let limit = Vector3::from(source.dims.map(|d| (d - 1) as f64));
    let within = |q: &Vector3<f64>| (0..3).all(|a| q[a] >= -SAMPLE_TOLERANCE && q[a] <= limit[a] + SAMPLE_TOLERANCE);
    Ok(rest
        .tets()
        .par_iter()
        .map(|t| {
            tet_map(t, &out_index, &src_index, grid.dims).map(|mut m| {
                m.src_inside = t.iter().all(|n| within(&src_index[*n as usize]));
                m
            })
        })
        .collect())
}

fn tet_map(t: &[u32; 4], out_index: &[Vector3<f64>], src_index: &[Vector3<f64>], dims: [usize; 3]) -> Option<TetMap> {
    let p = t.map(|n| out_index[n as usize]);
    let q = t.map(|n| src_index[n as usize]);
    let d = Matrix3::from_columns(&[p[1] - p[0], p[2] - p[0], p[3] - p[0]]);
    let qm = Matrix3::from_columns(&[q[1] - q[0], q[2] - q[0], q[3] - q[0]]);
    let (det, rest_det) = (d.determinant(), qm.determinant());
    // Same orientation as at rest, and not flat: |det| against the cube of its longest edge.
    let longest =
        (0..4).flat_map(|a| (a + 1..4).map(move |b| (a, b))).map(|(a, b)| (p[a] - p[b]).norm()).fold(0.0, f64::max);
    if det * rest_det <= 0.0 || det.abs() < 1e-9 * longest.powi(3) {
        return None;
    }
    let inv = d.try_inverse()?;
    let mut bary = [[0.0; 4]; 4];
    for m in 1..4 {
        let row = inv.row(m - 1);
        bary[m] = [-(row * p[0])[0], row[0], row[1], row[2]];
    }
    for c in 0..4 {
        bary[0][c] = if c == 0 { 1.0 } else { 0.0 } - bary[1][c] - bary[2][c] - bary[3][c];
    }
    let m = qm * inv;
    let offset = q[0] - m * p[0];
    let src = [0, 1, 2].map(|r| [offset[r], m[(r, 0)], m[(r, 1)], m[(r, 2)]]);
    let mut lo = [0usize; 3];
    let mut hi = [0usize; 3];
    for a in 0..3 {
        // Widened by the sample tolerance: a vertex at 38.9999999 still covers voxel 39.
        let min = (p.iter().map(|v| v[a]).fold(f64::INFINITY, f64::min) - SAMPLE_TOLERANCE).ceil().max(0.0);
        let max = (p.iter().map(|v| v[a]).fold(f64::NEG_INFINITY, f64::max) + SAMPLE_TOLERANCE)
            .floor()
            .min((dims[a] - 1) as f64);
        if min > max {
            return None;
        }
        lo[a] = min as usize;
        hi[a] = max as usize;
    }
    let inv_c = bary.map(|b| if b[1] != 0.0 { 1.0 / b[1] } else { 0.0 });
    Some(TetMap { lo, hi, bary, src, verts: p.map(|v| [v.x, v.y, v.z]), inv_c, src_inside: false })
}

/// The default output grid: the deformed nodes' box at the source's spacing and direction,
/// snapped to the source lattice (so an identity warp is a plain copy).
pub fn default_grid(source: &Volume, deformed: &[Vector3<f64>]) -> Grid {
    let g = source.grid();
    let (mut lo, mut hi) = (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY));
    for p in deformed {
        let ijk = g.index_from_world(*p);
        lo = lo.inf(&ijk);
        hi = hi.sup(&ijk);
    }
    let lo = lo.map(|v| (v - 1e-9).ceil());
    let hi = hi.map(|v| (v + 1e-9).floor());
    let dims = [0, 1, 2].map(|a| ((hi[a] - lo[a]).max(0.0) as usize) + 1);
    Grid { dims, spacing: g.spacing, origin: g.world_from_index(lo).into(), direction: g.direction }
}

/// Source samples and how to read them, in precision T.
pub struct Sampler<'a> {
    data: &'a [f32],
    dims: [usize; 3],
    sampling: Sampling,
    background: f32,
    displacements: Vec<CompiledDisplacement>,
    source: Grid,
}

impl<'a> Sampler<'a> {
    pub fn new(source: &'a Volume, options: &WarpOptions) -> Result<Self, WarpError> {
        let displacements = bspline::compile_all(&options.displacements)
            .map_err(|(index, why)| WarpError::BadDisplacement { index, why })?;
        Ok(Self {
            data: source.data(),
            dims: source.dims(),
            sampling: options.sampling,
            background: options.background,
            displacements,
            source: source.grid(),
        })
    }

    /// Value at a continuous source index, after the displacement volumes.
    #[inline]
    pub fn at<T: Real>(&self, x: T, y: T, z: T) -> T {
        if self.displacements.is_empty() {
            return self.at_index(x, y, z);
        }
        let world = self.source.world_from_index(Vector3::new(x.to_f64(), y.to_f64(), z.to_f64()));
        let moved = self.source.index_from_world(backward_all(&self.displacements, &world));
        self.at_index(T::of(moved.x), T::of(moved.y), T::of(moved.z))
    }

    fn is_plain_trilinear(&self) -> bool {
        self.sampling == Sampling::Trilinear && self.displacements.is_empty()
    }

    /// Trilinear samples along a run of output voxels, source index base + step·i: the hot
    /// loop of the warp, with the limits and strides hoisted out of it.
    fn trilinear_run<T: Real>(&self, out: &mut [T], base: [T; 3], step: [T; 3], i0: usize, src_inside: bool) {
        let [nx, ny, nz] = self.dims;
        let top = [nx.saturating_sub(2), ny.saturating_sub(2), nz.saturating_sub(2)];
        let sx = usize::from(nx > 1);
        let sy = if ny > 1 { nx } else { 0 };
        let sz = if nz > 1 { nx * ny } else { 0 };
        let background = T::of(self.background as f64);
        let data = self.data;
        let (top, nx, nxy) = (top.map(|t| t as i32), nx as i32, (nx * ny) as i32);
        // The run is affine in n. A rest tet inside the source box samples inside it (only
        // round-off can leave, and the clamps absorb it); otherwise find the sub-run whose
        // sample points lie in the box, so the loop needs no per-voxel bounds test.
        let len = out.len();
        let run = if src_inside { Some((0, len - 1)) } else { self.in_box_subrun(base, step, i0, len) };
        let Some((first, last)) = run else {
            out.fill(background);
            return;
        };
        out[..first].fill(background);
        out[last + 1..].fill(background);
        for (n, slot) in out[first..=last].iter_mut().enumerate() {
            let fi = T::of_i32((i0 + first + n) as i32);
            let (x, y, z) = (base[0] + step[0] * fi, base[1] + step[1] * fi, base[2] + step[2] * fi);
            let (i, j, k) =
                (x.trunc_i32().clamp(0, top[0]), y.trunc_i32().clamp(0, top[1]), z.trunc_i32().clamp(0, top[2]));
            let b = (i + nx * j + nxy * k) as usize;
            // One bounds check for the whole cell instead of one per corner.
            let cell = &data[b..=b + sx + sy + sz];
            *slot = defvol_core::volume::lerp_cube(
                |o| T::of_f32(cell[o]),
                [sx, sy, sz],
                [x - T::of_i32(i), y - T::of_i32(j), z - T::of_i32(k)],
            );
        }
    }

    /// The sub-run [first, last] of `len` samples at base + step·(i0 + n) that lies within
    /// [`SAMPLE_TOLERANCE`] of the source's voxel-centre box, if any.
    fn in_box_subrun<T: Real>(&self, base: [T; 3], step: [T; 3], i0: usize, len: usize) -> Option<(usize, usize)> {
        let limit = self.dims.map(|n| (n - 1) as f64);
        let (mut first, mut last) = (0.0f64, len as f64 - 1.0);
        for a in 0..3 {
            let (b0, s0, lim) = (
                (base[a] + step[a] * T::of_i32(i0 as i32)).to_f64() + SAMPLE_TOLERANCE,
                step[a].to_f64(),
                limit[a] + 2.0 * SAMPLE_TOLERANCE,
            );
            if s0 > 0.0 {
                first = first.max((-b0 / s0).ceil());
                last = last.min(((lim - b0) / s0).floor());
            } else if s0 < 0.0 {
                first = first.max(((lim - b0) / s0).ceil());
                last = last.min((-b0 / s0).floor());
            } else if !(0.0..=lim).contains(&b0) {
                return None;
            }
        }
        let tol = T::of(SAMPLE_TOLERANCE);
        let inside = |n: usize| {
            let fi = T::of_i32((i0 + n) as i32);
            (0..3).all(|a| {
                let c = base[a] + step[a] * fi;
                c >= -tol && c <= T::of(limit[a]) + tol
            })
        };
        // Settle the rounding of the divisions on the evaluated test, as spans do.
        let mut first = (first.max(0.0) as usize).min(len);
        let mut last = if last < 0.0 { 0 } else { (last as usize).min(len.saturating_sub(1)) };
        while first < len && first <= last && !inside(first) {
            first += 1;
        }
        while last > first && !inside(last) {
            last -= 1;
        }
        (first < len && first <= last && inside(first)).then_some((first, last))
    }

    #[inline]
    fn at_index<T: Real>(&self, x: T, y: T, z: T) -> T {
        match self.sampling {
            Sampling::Trilinear => trilinear(self.data, self.dims, x, y, z, T::of(SAMPLE_TOLERANCE))
                .unwrap_or(T::of(self.background as f64)),
            Sampling::Tricubic => tricubic(self.data, self.dims, x, y, z).unwrap_or(T::of(self.background as f64)),
        }
    }
}

/// Output grid and its initial contents.
fn initial_value<T: Real>(
    sampler: &Sampler,
    identity: &(Matrix3<f64>, Vector3<f64>),
    keep_uncovered: bool,
    i: usize,
    j: usize,
    k: usize,
) -> T {
    if !keep_uncovered {
        return T::of(sampler.background as f64);
    }
    let s = identity.0 * Vector3::new(i as f64, j as f64, k as f64) + identity.1;
    sampler.at(T::of(s.x), T::of(s.y), T::of(s.z))
}

/// Rasterizes `maps` into the output slice k (x-fastest rows), restricted to the inclusive
/// box `[lo, hi]` in (i, j). The CPU twin of `warp.wgsl`.
#[allow(clippy::too_many_arguments)]
fn rasterize_slice<T: Real>(
    slice: &mut [T],
    nx: usize,
    k: usize,
    tets: &[u32],
    maps: &[Option<TetMap>],
    sampler: &Sampler,
    scheme: Scheme,
    lo: [usize; 2],
    hi: [usize; 2],
) -> WarpStats {
    let mut stats = WarpStats::default();
    for &t in tets {
        let Some(m) = &maps[t as usize] else { continue };
        if k < m.lo[2] || k > m.hi[2] {
            continue;
        }
        let (j0, j1) = (m.lo[1].max(lo[1]), m.hi[1].min(hi[1]));
        let (i0, i1) = (m.lo[0].max(lo[0]), m.hi[0].min(hi[0]));
        if j0 > j1 || i0 > i1 {
            continue;
        }
        match scheme {
            Scheme::Spans => {
                let Some((s0, s1)) = m.section_rows(k) else { continue };
                for j in s0.max(j0)..=s1.min(j1) {
                    let a = m.row(j, k);
                    let Some((s0, s1)) = m.span(&a) else { continue };
                    let (s0, s1) = (s0.max(i0), s1.min(i1));
                    if s0 > s1 {
                        continue;
                    }
                    write_run(&mut slice[j * nx..], m, j, k, s0, s1, sampler);
                    let n = (s1 - s0 + 1) as u64;
                    stats.candidates += n;
                    stats.inside += n;
                }
            }
            Scheme::Bbox => {
                for j in j0..=j1 {
                    let a = m.row(j, k);
                    for i in i0..=i1 {
                        stats.candidates += 1;
                        if m.inside(&a, i) {
                            write_run(&mut slice[j * nx..], m, j, k, i, i, sampler);
                            stats.inside += 1;
                        }
                    }
                }
            }
            Scheme::Culling => {
                // Coarse points every CELL voxels from the tet's box corner; the cell test
                // needs masks at its 8 corners (4 in this slice's plane pair).
                let kc0 = m.lo[2] + (k - m.lo[2]) / CELL * CELL;
                let kc1 = kc0 + CELL;
                let mask = |i: usize, j: usize, kk: usize| -> u8 {
                    let a = m.row(j, kk);
                    let mut bits = 0u8;
                    for q in 0..4 {
                        let b = a[q] + m.bary[q][1] * i as f64;
                        // b here is b_q + ε; inside needs b ≥ 0, which bounds b_q + ε ≤ 1 + 4ε.
                        bits |= u8::from(b < 0.0) << (2 * q);
                        bits |= u8::from(b > 1.0 + 4.0 * INSIDE_TOLERANCE) << (2 * q + 1);
                    }
                    bits
                };
                let mut jc = m.lo[1];
                while jc <= m.hi[1] {
                    let mut ic = m.lo[0];
                    while ic <= m.hi[0] {
                        let corners = [(ic, jc), (ic + CELL, jc), (ic, jc + CELL), (ic + CELL, jc + CELL)];
                        let culled =
                            corners.iter().fold(0xFFu8, |acc, &(i, j)| acc & mask(i, j, kc0) & mask(i, j, kc1));
                        if culled == 0 {
                            for j in jc.max(j0)..=(jc + CELL - 1).min(j1) {
                                let a = m.row(j, k);
                                for i in ic.max(i0)..=(ic + CELL - 1).min(i1) {
                                    stats.candidates += 1;
                                    if m.inside(&a, i) {
                                        write_run(&mut slice[j * nx..], m, j, k, i, i, sampler);
                                        stats.inside += 1;
                                    }
                                }
                            }
                        }
                        ic += CELL;
                    }
                    jc += CELL;
                }
            }
        }
    }
    stats
}

/// Coarse cell size of the culling scheme (the seed's 8x8x8).
pub const CELL: usize = 8;

/// Samples the source for output voxels i0..=i1 of row (j, k); `row` starts at i = 0.
#[inline]
fn write_run<T: Real>(row: &mut [T], m: &TetMap, j: usize, k: usize, i0: usize, i1: usize, sampler: &Sampler) {
    let (jf, kf) = (j as f64, k as f64);
    let base = m.src.map(|s| T::of(s[0] + s[2] * jf + s[3] * kf));
    let step = m.src.map(|s| T::of(s[1]));
    if sampler.is_plain_trilinear() {
        sampler.trilinear_run(&mut row[i0..=i1], base, step, i0, m.src_inside);
        return;
    }
    for (i, out) in row[i0..=i1].iter_mut().enumerate() {
        let fi = T::of((i0 + i) as f64);
        *out = sampler.at(base[0] + step[0] * fi, base[1] + step[1] * fi, base[2] + step[2] * fi);
    }
}

/// Which tets overlap each output slice, in tet order.
fn slice_bins(maps: &[Option<TetMap>], nz: usize) -> Vec<Vec<u32>> {
    let mut bins = vec![Vec::new(); nz];
    for (t, m) in maps.iter().enumerate() {
        if let Some(m) = m {
            for bin in &mut bins[m.lo[2]..=m.hi[2]] {
                bin.push(t as u32);
            }
        }
    }
    bins
}

fn check_size(grid: &Grid, bytes_per_voxel: u64, options: &WarpOptions) -> Result<(), WarpError> {
    let needed = grid.len() as u64 * bytes_per_voxel;
    if needed > options.max_bytes {
        return Err(WarpError::TooLarge {
            dims: grid.dims,
            needed_mib: needed.div_ceil(1 << 20),
            limit_mib: options.max_bytes >> 20,
        });
    }
    Ok(())
}

/// Warps `source` through `rest` → `deformed` onto `grid`, in precision T (f32: the fast
/// path; f64: the reference). Positions are in the source's physical units.
pub fn warp_samples<T: Real>(
    source: &Volume,
    rest: &TetMesh,
    deformed: &[Vector3<f64>],
    grid: &Grid,
    options: &WarpOptions,
) -> Result<(Vec<T>, WarpStats), WarpError> {
    check_size(grid, std::mem::size_of::<T>() as u64, options)?;
    let mut out = vec![T::zero(); grid.len()];
    let stats = warp_into(source, rest, deformed, grid, options, &mut out)?;
    Ok((out, stats))
}

/// As [`warp_samples`], into a caller's buffer of `grid.len()` samples (reused from frame
/// to frame, or a shared-memory sample being published).
pub fn warp_into<T: Real>(
    source: &Volume,
    rest: &TetMesh,
    deformed: &[Vector3<f64>],
    grid: &Grid,
    options: &WarpOptions,
    out: &mut [T],
) -> Result<WarpStats, WarpError> {
    check_size(grid, std::mem::size_of::<T>() as u64, options)?;
    if out.len() != grid.len() {
        return Err(WarpError::BufferSize { got: out.len(), expected: grid.len() });
    }
    let maps = tet_maps(rest, deformed, &source.grid(), grid)?;
    let sampler = Sampler::new(source, options)?;
    let identity = grid.index_map_to(&source.grid());
    let [nx, ny, nz] = grid.dims;
    let bins = slice_bins(&maps, nz);
    let mut stats = out
        .par_chunks_mut(nx * ny)
        .enumerate()
        .map(|(k, slice)| {
            if options.keep_uncovered {
                for j in 0..ny {
                    for i in 0..nx {
                        slice[i + nx * j] = initial_value(&sampler, &identity, true, i, j, k);
                    }
                }
            } else {
                slice.fill(T::of(options.background as f64));
            }
            rasterize_slice(slice, nx, k, &bins[k], &maps, &sampler, options.scheme, [0, 0], [nx - 1, ny - 1])
        })
        .reduce(WarpStats::default, |mut a, b| {
            a += b;
            a
        });
    stats.voxels = grid.len() as u64;
    stats.skipped_tets = maps.iter().filter(|m| m.is_none()).count() as u64;
    Ok(stats)
}

/// The f32 warp as a volume on `grid`.
pub fn warp(
    source: &Volume,
    rest: &TetMesh,
    deformed: &[Vector3<f64>],
    grid: &Grid,
    options: &WarpOptions,
) -> Result<(Volume, WarpStats), WarpError> {
    let (data, stats) = warp_samples::<f32>(source, rest, deformed, grid, options)?;
    Ok((Volume::from_grid(grid, data, "warped volume")?, stats))
}

/// Displacement volumes alone (no mesh): out(p) = src(backward(p)) on `grid`.
pub fn displace(source: &Volume, grid: &Grid, options: &WarpOptions) -> Result<Volume, WarpError> {
    check_size(grid, 4, options)?;
    let sampler = Sampler::new(source, options)?;
    let identity = grid.index_map_to(&source.grid());
    let [nx, ny, _] = grid.dims;
    let mut out = vec![0f32; grid.len()];
    out.par_chunks_mut(nx * ny).enumerate().for_each(|(k, slice)| {
        for j in 0..ny {
            for i in 0..nx {
                slice[i + nx * j] = initial_value(&sampler, &identity, true, i, j, k);
            }
        }
    });
    Ok(Volume::from_grid(grid, out, "displaced volume")?)
}

/// A box of output voxels, inclusive.
type Region = ([usize; 3], [usize; 3]);

/// Advances whose moved regions are remembered: a buffer that held a warp up to this many
/// advances ago is brought up to date region by region, an older one whole.
const HISTORY: usize = 64;

/// A warp kept up to date as the mesh moves, written wherever its consumer wants it.
///
/// [`IncrementalWarp::advance`] takes new deformed positions and notes the region of the
/// tets with a node that moved more than `tolerance`; [`IncrementalWarp::write_into`] then
/// brings any buffer to the current warp: one that holds an earlier warp of this sequence
/// (its owner says which) is re-warped only inside the regions moved since, any other is
/// warped whole. A rotating set of shared-memory samples is therefore written in place,
/// each only where the volume changed since it last went out, and never copied.
pub struct IncrementalWarp {
    source: Arc<Volume>,
    rest: Arc<TetMesh>,
    grid: Grid,
    options: WarpOptions,
    positions: Vec<Vector3<f64>>,
    maps: Vec<Option<TetMap>>,
    /// Advances so far: the warp the positions describe.
    sequence: u64,
    /// The moved region of each recent advance (`None`: nothing moved), oldest first.
    history: std::collections::VecDeque<(u64, Option<Region>)>,
}

impl IncrementalWarp {
    /// The warp of `deformed` (sequence 0); nothing is written until [`Self::write_into`].
    pub fn new(
        source: Arc<Volume>,
        rest: Arc<TetMesh>,
        deformed: &[Vector3<f64>],
        grid: Grid,
        options: WarpOptions,
    ) -> Result<Self, WarpError> {
        check_size(&grid, 4, &options)?;
        Sampler::new(&source, &options)?;
        let maps = tet_maps(&rest, deformed, &source.grid(), &grid)?;
        Ok(Self {
            source,
            rest,
            grid,
            options,
            positions: deformed.to_vec(),
            maps,
            sequence: 0,
            history: Default::default(),
        })
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// The warp the last positions describe.
    pub fn sequence(&self) -> u64 {
        self.sequence
    }

    /// Tets skipped as inverted, degenerate or off the grid at the current positions.
    pub fn skipped_tets(&self) -> u64 {
        self.maps.iter().filter(|m| m.is_none()).count() as u64
    }

    /// Takes new deformed positions: the box covering the old and new extents of every tet
    /// with a node that moved more than `tolerance` is what changed. Returns the new sequence.
    pub fn advance(&mut self, deformed: &[Vector3<f64>], tolerance: f64) -> Result<u64, WarpError> {
        if deformed.len() != self.positions.len() {
            return Err(WarpError::NodeCount { got: deformed.len(), expected: self.positions.len() });
        }
        let moved: Vec<bool> = self.positions.iter().zip(deformed).map(|(a, b)| (a - b).norm() > tolerance).collect();
        // A node that moved less keeps the place the warp last gave it, so that the tets
        // around it keep their maps: what an earlier volume holds of them stays this warp's,
        // and slow drift is caught once it adds up to the tolerance.
        let applied: Vec<Vector3<f64>> = self
            .positions
            .iter()
            .zip(deformed)
            .zip(&moved)
            .map(|((old, new), m)| if *m { *new } else { *old })
            .collect();
        let maps = tet_maps(&self.rest, &applied, &self.source.grid(), &self.grid)?;
        let mut region: Option<Region> = None;
        let mut grow = |lo_in: [usize; 3], hi_in: [usize; 3]| {
            let (lo, hi) = region.get_or_insert((lo_in, hi_in));
            for a in 0..3 {
                lo[a] = lo[a].min(lo_in[a]);
                hi[a] = hi[a].max(hi_in[a]);
            }
        };
        for (t, tet) in self.rest.tets().iter().enumerate() {
            if !tet.iter().any(|n| moved[*n as usize]) {
                continue;
            }
            for m in [&self.maps[t], &maps[t]].into_iter().flatten() {
                grow(m.lo, m.hi);
            }
            // Inverted tets have no map: cover their nodes' positions too.
            if self.maps[t].is_none() || maps[t].is_none() {
                for p in tet.iter().flat_map(|n| [self.positions[*n as usize], applied[*n as usize]]) {
                    let ijk = self.grid.index_from_world(p);
                    let c = [0, 1, 2].map(|a| ijk[a].clamp(0.0, (self.grid.dims[a] - 1) as f64));
                    grow(c.map(|v| v.floor() as usize), c.map(|v| v.ceil() as usize));
                }
            }
        }
        self.positions = applied;
        self.maps = maps;
        self.sequence += 1;
        self.history.push_back((self.sequence, region));
        if self.history.len() > HISTORY {
            self.history.pop_front();
        }
        Ok(self.sequence)
    }

    /// Brings `out` to the current warp. `holds`: the sequence of the warp `out` holds, if
    /// it holds one of this warp's (its owner's knowledge); then only the regions moved
    /// since are re-warped, else all of it. Returns the work done (`voxels`: those
    /// re-warped; zero when `out` was up to date).
    pub fn write_into(&self, out: &mut [f32], holds: Option<u64>) -> Result<WarpStats, WarpError> {
        if out.len() != self.grid.len() {
            return Err(WarpError::BufferSize { got: out.len(), expected: self.grid.len() });
        }
        let whole: Region = ([0; 3], self.grid.dims.map(|d| d - 1));
        let oldest_known = self.history.front().map_or(self.sequence, |(s, _)| s - 1);
        let region = match holds {
            Some(s) if s == self.sequence => return Ok(WarpStats::default()),
            Some(s) if s < self.sequence && s >= oldest_known => {
                let mut union: Option<Region> = None;
                for (_, moved) in self.history.iter().filter(|(q, _)| *q > s) {
                    if let Some((lo, hi)) = moved {
                        let (ulo, uhi) = union.get_or_insert((*lo, *hi));
                        for a in 0..3 {
                            ulo[a] = ulo[a].min(lo[a]);
                            uhi[a] = uhi[a].max(hi[a]);
                        }
                    }
                }
                match union {
                    Some(region) => region,
                    None => return Ok(WarpStats::default()),
                }
            }
            _ => whole,
        };
        let mut stats = self.rewarp(out, region)?;
        if region == whole {
            stats.skipped_tets = self.skipped_tets();
        }
        Ok(stats)
    }

    /// Re-warps the box `[lo, hi]` of `out`: its initial values, then every tet over it.
    fn rewarp(&self, out: &mut [f32], (lo, hi): Region) -> Result<WarpStats, WarpError> {
        let sampler = Sampler::new(&self.source, &self.options)?;
        let identity = self.grid.index_map_to(&self.source.grid());
        let [nx, ny, _] = self.grid.dims;
        let bins = slice_bins(&self.maps, self.grid.dims[2]);
        let (maps, options) = (&self.maps, &self.options);
        let background = options.background;
        let mut stats = out[lo[2] * nx * ny..(hi[2] + 1) * nx * ny]
            .par_chunks_mut(nx * ny)
            .enumerate()
            .map(|(dk, slice)| {
                let k = lo[2] + dk;
                for j in lo[1]..=hi[1] {
                    let row = &mut slice[nx * j + lo[0]..=nx * j + hi[0]];
                    if options.keep_uncovered {
                        for (di, v) in row.iter_mut().enumerate() {
                            *v = initial_value(&sampler, &identity, true, lo[0] + di, j, k);
                        }
                    } else {
                        row.fill(background);
                    }
                }
                rasterize_slice(slice, nx, k, &bins[k], maps, &sampler, options.scheme, [lo[0], lo[1]], [hi[0], hi[1]])
            })
            .reduce(WarpStats::default, |mut a, b| {
                a += b;
                a
            });
        stats.voxels = ((hi[0] - lo[0] + 1) * (hi[1] - lo[1] + 1) * (hi[2] - lo[2] + 1)) as u64;
        Ok(stats)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use defvol_core::mesh::generate::{self, CellSplit};
    use defvol_core::volume::phantom;

    /// Three buffers taking turns, as shared-memory samples do: each is brought from the
    /// warp it last held to the current one, and always equals a full warp.
    #[test]
    fn buffers_taking_turns_always_hold_the_current_warp() {
        let source = Arc::new(phantom::phantom([48, 32, 24], 5.0).unwrap());
        let (lo, hi) = source.bounds();
        let mesh = Arc::new(generate::lattice_for_box(lo, hi, 600, CellSplit::Five).unwrap());
        let options = WarpOptions { keep_uncovered: true, ..Default::default() };
        let grid = source.grid();
        let mut warp =
            IncrementalWarp::new(source.clone(), mesh.clone(), mesh.nodes(), grid.clone(), options.clone()).unwrap();
        let mut buffers: Vec<(Vec<f32>, Option<u64>)> = (0..3).map(|_| (vec![f32::NAN; grid.len()], None)).collect();
        let centre = (lo + hi) / 2.0;
        for step in 1..=9 {
            // A probe pressing in at a point that wanders: a local change each step.
            let tip = centre
                + Vector3::new(40.0 * (step as f64 * 0.7).sin(), 20.0 * (step as f64 * 0.4).cos(), hi.z - centre.z);
            let pressed: Vec<Vector3<f64>> = mesh
                .nodes()
                .iter()
                .map(|p| {
                    let d = (p - tip).norm();
                    if d < 40.0 {
                        p - Vector3::z() * (3.0 * step as f64 / 9.0 * (1.0 - d / 40.0))
                    } else {
                        *p
                    }
                })
                .collect();
            let sequence = warp.advance(&pressed, 1e-9).unwrap();
            let (buffer, holds) = &mut buffers[step % 3];
            let stats = warp.write_into(buffer, *holds).unwrap();
            *holds = Some(sequence);
            let (full, _) = super::warp(&source, &mesh, &pressed, &grid, &options).unwrap();
            assert!(
                buffer.iter().zip(full.data()).all(|(a, b)| a.to_bits() == b.to_bits()),
                "step {step}: the buffer differs from a full warp"
            );
            if step > 3 {
                assert!(
                    stats.voxels < grid.len() as u64,
                    "step {step}: a buffer three warps behind is re-warped in part, not whole ({stats:?})"
                );
            } else {
                assert_eq!(stats.voxels, grid.len() as u64, "step {step}: a fresh buffer is warped whole");
            }
        }
        // Up to date: nothing to do.
        let (buffer, holds) = &mut buffers[0];
        assert_eq!(warp.write_into(buffer, *holds).unwrap().voxels, 0);
    }
}
