//! Per tet and per voxel, the arithmetic both paths share, line by line the twin of
//! `warp.wgsl`: each tet's affine maps and exact row spans in output index space, the
//! source sampler, and the rasterization of one output slice.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::bspline::{self, backward_all, CompiledDisplacement};
use crate::{Sampling, Scheme, WarpError, WarpOptions, WarpStats};
use defvol_core::math::Real;
use defvol_core::mesh::TetMesh;
use defvol_core::volume::lanes::{trilinear_bricked, trilinear_lanes, Bricks, CellLookup, RunStream};
use defvol_core::volume::{tricubic, trilinear, Grid, Volume, SAMPLE_TOLERANCE};

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
                lo = lo.max(ceil(-a[m] * self.inv_c[m]));
            } else if c < 0.0 {
                hi = hi.min(floor(-a[m] * self.inv_c[m]));
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

    /// The spans of rows j..j+4 of slice k, each exactly [`Self::span`] of its row, four
    /// rows a vector where AVX serves (`None` where it does not: the caller takes rows one
    /// by one).
    pub fn spans4(&self, j: usize, k: usize) -> Option<[Option<(usize, usize)>; 4]> {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX.
            return Some(unsafe { rows4::spans_avx(self, j, k) });
        }
        let _ = (j, k);
        None
    }

    /// Pushes the spans of rows j..j + rows (at most four) of slice k, clipped to
    /// `[i0, i1]`, onto `stream` as [`rows4::push_spans_avx`] does; how many voxels, or
    /// `None` (nothing pushed) where AVX does not serve.
    fn push_spans4(
        &self,
        [j, k]: [usize; 2],
        rows: usize,
        clip: [usize; 2],
        at: [usize; 2],
        stream: &mut RunStream,
    ) -> Option<u64> {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX.
            return Some(unsafe { rows4::push_spans_avx(self, [j, k], rows, clip, at, stream) });
        }
        let _ = (j, k, rows, clip, at, stream);
        None
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
        let j0 = (ceil(lo) - 1.0).max(self.lo[1] as f64);
        let j1 = (floor(hi) + 1.0).min(self.hi[1] as f64);
        (j0 <= j1).then_some((j0 as usize, j1 as usize))
    }
}

/// [`TetMap::span`] for four rows at once, lane for lane its arithmetic: the row offsets as
/// [`TetMap::row`] adds them, the bounds from the same products rounded up or down, then
/// settled on the same evaluated predicate, each lane stepping until its own test holds.
#[cfg(target_arch = "x86_64")]
mod rows4 {
    use super::{TetMap, INSIDE_TOLERANCE};
    use defvol_core::volume::lanes::RunStream;
    use std::arch::x86_64::*;

    /// Whether each lane's voxel `i` is inside: every plane's `a + c·i ≥ 0`.
    #[inline]
    #[target_feature(enable = "avx")]
    fn inside(m: &TetMap, a: &[__m256d; 4], i: __m256d) -> __m256d {
        let mut all = _mm256_castsi256_pd(_mm256_set1_epi64x(-1));
        for (q, a) in a.iter().enumerate() {
            let b = _mm256_add_pd(*a, _mm256_mul_pd(_mm256_set1_pd(m.bary[q][1]), i));
            all = _mm256_and_pd(all, _mm256_cmp_pd::<_CMP_GE_OQ>(b, _mm256_setzero_pd()));
        }
        all
    }

    /// Steps each live lane's bound `at` by `delta` (±1) while its voxel is outside and it
    /// has not passed the lane's other bound, `other`.
    #[inline]
    #[target_feature(enable = "avx")]
    fn settle(m: &TetMap, a: &[__m256d; 4], dead: __m256d, mut at: __m256d, other: __m256d, delta: f64) -> __m256d {
        loop {
            let open = match delta > 0.0 {
                true => _mm256_cmp_pd::<_CMP_LE_OQ>(at, other),
                false => _mm256_cmp_pd::<_CMP_GE_OQ>(at, other),
            };
            let step = _mm256_andnot_pd(inside(m, a, at), _mm256_andnot_pd(dead, open));
            if _mm256_movemask_pd(step) == 0 {
                return at;
            }
            at = _mm256_add_pd(at, _mm256_and_pd(step, _mm256_set1_pd(delta)));
        }
    }

    /// # Safety
    /// The CPU must have AVX.
    #[target_feature(enable = "avx")]
    pub(super) unsafe fn spans_avx(m: &TetMap, j: usize, k: usize) -> [Option<(usize, usize)>; 4] {
        let (lo, hi, live) = bounds(m, j, k);
        let (mut los, mut his) = ([0.0f64; 4], [0.0f64; 4]);
        // SAFETY: four f64 each.
        unsafe {
            _mm256_storeu_pd(los.as_mut_ptr(), lo);
            _mm256_storeu_pd(his.as_mut_ptr(), hi);
        }
        [0, 1, 2, 3].map(|l| (live >> l & 1 == 1).then_some((los[l] as usize, his[l] as usize)))
    }

    /// Each row's span bounds and which rows have any (bit l: row j + l).
    #[inline]
    #[target_feature(enable = "avx")]
    fn bounds(m: &TetMap, j: usize, k: usize) -> (__m256d, __m256d, i32) {
        let jf = _mm256_add_pd(_mm256_set1_pd(j as f64), _mm256_setr_pd(0.0, 1.0, 2.0, 3.0));
        let kf = _mm256_set1_pd(k as f64);
        let a = m.bary.map(|b| {
            let row = _mm256_add_pd(_mm256_set1_pd(b[0]), _mm256_mul_pd(_mm256_set1_pd(b[2]), jf));
            _mm256_add_pd(_mm256_add_pd(row, _mm256_mul_pd(_mm256_set1_pd(b[3]), kf)), _mm256_set1_pd(INSIDE_TOLERANCE))
        });
        let (box_lo, box_hi) = (_mm256_set1_pd(m.lo[0] as f64), _mm256_set1_pd(m.hi[0] as f64));
        let (mut lo, mut hi) = (box_lo, box_hi);
        // Lanes a plane parallel to the rows leaves outside: empty.
        let mut dead = _mm256_setzero_pd();
        for (q, a) in a.iter().enumerate() {
            let c = m.bary[q][1];
            let t = _mm256_mul_pd(_mm256_sub_pd(_mm256_setzero_pd(), *a), _mm256_set1_pd(m.inv_c[q]));
            if c > 0.0 {
                lo = _mm256_max_pd(_mm256_ceil_pd(t), lo);
            } else if c < 0.0 {
                hi = _mm256_min_pd(_mm256_floor_pd(t), hi);
            } else {
                dead = _mm256_or_pd(dead, _mm256_cmp_pd::<_CMP_LT_OQ>(*a, _mm256_setzero_pd()));
            }
        }
        let one = _mm256_set1_pd(1.0);
        let clamp = |v: __m256d| _mm256_min_pd(_mm256_max_pd(v, box_lo), box_hi);
        let lo = clamp(_mm256_sub_pd(lo, one));
        let hi = clamp(_mm256_add_pd(hi, one));
        // Each lane's lower bound up to its first inside voxel, then its upper bound down.
        let lo = settle(m, &a, dead, lo, hi, 1.0);
        let hi = settle(m, &a, dead, hi, lo, -1.0);
        let live = _mm256_movemask_pd(_mm256_andnot_pd(dead, _mm256_cmp_pd::<_CMP_LE_OQ>(lo, hi)));
        (lo, hi, live)
    }

    /// Pushes the spans of rows j..j + rows (at most four) of slice k, clipped to
    /// `[i0, i1]`, onto `stream` (row j's voxel 0 at `to` in the output, rows `nx` apart),
    /// each with its row's base point as [`super::run_base`] computes it; how many voxels.
    ///
    /// # Safety
    /// The CPU must have AVX.
    #[target_feature(enable = "avx")]
    pub(super) unsafe fn push_spans_avx(
        m: &TetMap,
        [j, k]: [usize; 2],
        rows: usize,
        [i0, i1]: [usize; 2],
        [to, nx]: [usize; 2],
        stream: &mut RunStream,
    ) -> u64 {
        let (lo, hi, live) = bounds(m, j, k);
        // The spans clipped, as i32 (within the grid), and the rows that keep voxels.
        let (lo, hi) = (_mm256_max_pd(lo, _mm256_set1_pd(i0 as f64)), _mm256_min_pd(hi, _mm256_set1_pd(i1 as f64)));
        let kept = live & ((1 << rows) - 1) & _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(lo, hi));
        let (mut first, mut len) = ([0i32; 4], [0i32; 4]);
        let (lo, hi) = (_mm256_cvttpd_epi32(lo), _mm256_cvttpd_epi32(hi));
        // SAFETY: four i32 each.
        unsafe {
            _mm_storeu_si128(first.as_mut_ptr().cast(), lo);
            _mm_storeu_si128(len.as_mut_ptr().cast(), _mm_add_epi32(_mm_sub_epi32(hi, lo), _mm_set1_epi32(1)));
        }
        let jf = _mm256_add_pd(_mm256_set1_pd(j as f64), _mm256_setr_pd(0.0, 1.0, 2.0, 3.0));
        let kf = _mm256_set1_pd(k as f64);
        let base = m.src.map(|s| {
            let row = _mm256_add_pd(_mm256_set1_pd(s[0]), _mm256_mul_pd(_mm256_set1_pd(s[2]), jf));
            let mut out = [0f32; 4];
            // SAFETY: four f32.
            unsafe {
                _mm_storeu_ps(
                    out.as_mut_ptr(),
                    _mm256_cvtpd_ps(_mm256_add_pd(row, _mm256_mul_pd(_mm256_set1_pd(s[3]), kf))),
                )
            };
            out
        });
        let to = [0, 1, 2, 3].map(|l| to + l * nx + first[l] as usize);
        stream.push4(base, first, len, to, kept as u32)
    }
}

/// ⌊x⌋ in a few instructions (x86-64's baseline has no rounding instruction, and `floor`
/// is a libm call there), exact within ±2⁶³; beyond, it saturates, which the span and
/// section bounds clamp to the tet's box anyway.
#[inline]
fn floor(x: f64) -> f64 {
    let t = x as i64 as f64;
    if t > x {
        t - 1.0
    } else {
        t
    }
}

/// ⌈x⌉, as [`floor`].
#[inline]
fn ceil(x: f64) -> f64 {
    -floor(-x)
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

/// Source samples and how to read them, in precision T.
pub struct Sampler<'a> {
    data: &'a [f32],
    dims: [usize; 3],
    sampling: Sampling,
    background: f32,
    displacements: Vec<CompiledDisplacement>,
    source: Grid,
    /// How a run finds its cells, fixed by the source's dims.
    cell: CellLookup,
    /// Eight-lane runs where the CPU has them ([`crate::WarpPath::Fast`]).
    lanes: bool,
    /// The source in bricks, which the lanes read where they run.
    bricks: Option<&'a Bricks>,
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
            cell: CellLookup::for_dims(source.dims()),
            lanes: options.path == crate::WarpPath::Fast,
            // Only plain trilinear runs take the lanes: no copy for the other samplings.
            bricks: (options.path == crate::WarpPath::Fast
                && options.sampling == Sampling::Trilinear
                && options.displacements.is_empty())
            .then(|| source.bricks())
            .flatten(),
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

    /// The bricks a tet's spans are sampled from as one stream: plain trilinear on the
    /// fast path, a rest tet inside the source (no box tests). Whatever the direction: run
    /// by run, runs along the source's rows read row-major windows faster than bricks,
    /// but as a stream the bricks win there too (see docs/perf/journal.md#bricks-as-a-stream).
    fn streams(&self, m: &TetMap) -> Option<&'a Bricks> {
        self.bricks.filter(|_| self.lanes && m.src_inside)
    }

    fn is_plain_trilinear(&self) -> bool {
        self.sampling == Sampling::Trilinear && self.displacements.is_empty()
    }

    /// Trilinear samples along a run of output voxels, source index base + step·i: the hot
    /// loop of the warp, with the limits and strides hoisted out of it.
    /// `ahead`: the offset to the run the caller samples next, whose cells a run along the
    /// source's rows prefetches (bricked runs take none: no gain measured).
    fn trilinear_run<T: Real>(
        &self,
        out: &mut [T],
        [base, step]: [[T; 3]; 2],
        i0: usize,
        src_inside: bool,
        ahead: [f32; 3],
    ) {
        let cell = &self.cell;
        let background = T::of(self.background as f64);
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
        let start = i0 + first;
        let inside = &mut out[first..=last];
        let done = match T::as_f32_mut(inside).filter(|_| self.lanes) {
            Some(lanes) => {
                let (base, step) = (base.map(|v| v.to_f64() as f32), step.map(|v| v.to_f64() as f32));
                // Bricks pay where a run crosses rows and slices (a rotated source); along
                // its rows the row-major samples are read in order already.
                let across = step[1].abs() + step[2].abs() > 0.5;
                match self.bricks.filter(|_| across) {
                    Some(bricks) => trilinear_bricked(bricks, lanes, base, step, start as i32),
                    None => trilinear_lanes(self.data, cell, lanes, base, step, start as i32, Some(ahead)),
                }
            }
            None => 0,
        };
        let (data, [sx, sy, sz]) = (self.data, cell.strides.map(|s| s as usize));
        for (n, slot) in inside.iter_mut().enumerate().skip(done) {
            let fi = T::of_i32((start + n) as i32);
            let (x, y, z) = (base[0] + step[0] * fi, base[1] + step[1] * fi, base[2] + step[2] * fi);
            let (i, j, k) = (
                x.trunc_i32().clamp(0, cell.top[0]),
                y.trunc_i32().clamp(0, cell.top[1]),
                z.trunc_i32().clamp(0, cell.top[2]),
            );
            let b = (i + cell.nx * j + cell.nxy * k) as usize;
            // One bounds check for the whole cell instead of one per corner.
            let corners = &data[b..=b + sx + sy + sz];
            *slot = defvol_core::volume::lerp_cube(
                |o| T::of_f32(corners[o]),
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
pub(crate) fn initial_value<T: Real>(
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

/// Rasterizes `maps` into a slab of output slices from k0 (x-fastest rows, slices of
/// `nx` x `ny`), restricted to the inclusive box `[lo, hi]` in (i, j). Tet by tet, in tet
/// order (a later tet wins a shared face's voxels, as on the GPU), each through all its
/// slices in the slab: its source footprint is read while still in cache. A tet whose
/// runs take the bricks has all its spans in the slab sampled as one [`RunStream`].
#[allow(clippy::too_many_arguments)]
pub(crate) fn rasterize_slab<T: Real>(
    slab: &mut [T],
    [nx, ny]: [usize; 2],
    k0: usize,
    tets: &[u32],
    maps: &[Option<TetMap>],
    sampler: &Sampler,
    scheme: Scheme,
    lo: [usize; 2],
    hi: [usize; 2],
) -> WarpStats {
    let mut stats = WarpStats::default();
    let last = k0 + slab.len() / (nx * ny) - 1;
    let mut stream = RunStream::default();
    for &t in tets {
        let Some(m) = &maps[t as usize] else { continue };
        if scheme == Scheme::Spans {
            if let (Some(bricks), Some(out)) = (sampler.streams(m), T::as_f32_mut(slab)) {
                if let Some(n) = stream_tet(&mut stream, out, [nx, ny], [k0, last], m, bricks, [lo, hi]) {
                    stats.candidates += n;
                    stats.inside += n;
                    continue;
                }
            }
        }
        for k in m.lo[2].max(k0)..=m.hi[2].min(last) {
            let slice = &mut slab[(k - k0) * nx * ny..(k - k0 + 1) * nx * ny];
            rasterize_tet_slice(slice, nx, k, m, sampler, scheme, lo, hi, &mut stats);
        }
    }
    stats
}

/// Calls `run(j, s0, s1)` for each row j of slice k with inside voxels s0..=s1 within the
/// box `[lo, hi]` in (i, j). Rows in fours: with `lanes`, a four's spans are found at once.
fn for_each_span(
    m: &TetMap,
    k: usize,
    lanes: bool,
    lo: [usize; 2],
    hi: [usize; 2],
    mut run: impl FnMut(usize, usize, usize),
) {
    let Some((s0, s1)) = m.section_rows(k) else { return };
    let (first, last) = (s0.max(lo[1]), s1.min(hi[1]));
    for j4 in (first..=last).step_by(4) {
        let rows = (last + 1 - j4).min(4);
        let four = lanes
            .then(|| m.spans4(j4, k))
            .flatten()
            .unwrap_or_else(|| [0, 1, 2, 3].map(|r| (r < rows).then(|| m.span(&m.row(j4 + r, k))).flatten()));
        for (j, span) in (j4..).zip(&four[..rows]) {
            let Some((s0, s1)) = *span else { continue };
            let (s0, s1) = (s0.max(lo[0]), s1.min(hi[0]));
            if s0 <= s1 {
                run(j, s0, s1);
            }
        }
    }
}

/// Rasterizes one tet into the slices k0..=last of a slab as one [`RunStream`] of its
/// spans; how many voxels it wrote, or None (nothing written) where the CPU lacks the lanes.
fn stream_tet(
    stream: &mut RunStream,
    slab: &mut [f32],
    [nx, ny]: [usize; 2],
    [k0, last]: [usize; 2],
    m: &TetMap,
    bricks: &Bricks,
    [lo, hi]: [[usize; 2]; 2],
) -> Option<u64> {
    let (i0, i1) = (m.lo[0].max(lo[0]), m.hi[0].min(hi[0]));
    let (j0, j1) = (m.lo[1].max(lo[1]), m.hi[1].min(hi[1]));
    if j0 > j1 || i0 > i1 {
        return Some(0);
    }
    stream.clear();
    let mut voxels = 0;
    for k in m.lo[2].max(k0)..=m.hi[2].min(last) {
        let Some((s0, s1)) = m.section_rows(k) else { continue };
        let (first, last) = (s0.max(j0), s1.min(j1));
        for j4 in (first..=last).step_by(4) {
            let (rows, at) = ((last + 1 - j4).min(4), [(k - k0) * nx * ny + j4 * nx, nx]);
            voxels += m.push_spans4([j4, k], rows, [i0, i1], at, stream)?;
        }
    }
    let step = m.src.map(|s| s[1] as f32);
    stream.sample_into(bricks, step, slab).then_some(voxels)
}

/// The source point of output voxel i = 0 of row (j, k), in precision T.
#[inline]
fn run_base<T: Real>(m: &TetMap, j: usize, k: usize) -> [T; 3] {
    let (jf, kf) = (j as f64, k as f64);
    m.src.map(|s| T::of(s[0] + s[2] * jf + s[3] * kf))
}

/// Rasterizes one tet into output slice k, within the box `[lo, hi]` in (i, j). The CPU
/// twin of `warp.wgsl`.
#[allow(clippy::too_many_arguments)]
fn rasterize_tet_slice<T: Real>(
    slice: &mut [T],
    nx: usize,
    k: usize,
    m: &TetMap,
    sampler: &Sampler,
    scheme: Scheme,
    lo: [usize; 2],
    hi: [usize; 2],
    stats: &mut WarpStats,
) {
    let (j0, j1) = (m.lo[1].max(lo[1]), m.hi[1].min(hi[1]));
    let (i0, i1) = (m.lo[0].max(lo[0]), m.hi[0].min(hi[0]));
    if j0 > j1 || i0 > i1 {
        return;
    }
    match scheme {
        Scheme::Spans => for_each_span(m, k, sampler.lanes, [i0, j0], [i1, j1], |j, s0, s1| {
            write_run(&mut slice[j * nx..], m, j, k, s0, s1, sampler);
            let n = (s1 - s0 + 1) as u64;
            stats.candidates += n;
            stats.inside += n;
        }),
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
                    let culled = corners.iter().fold(0xFFu8, |acc, &(i, j)| acc & mask(i, j, kc0) & mask(i, j, kc1));
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

/// Coarse cell size of the culling scheme (the seed's 8x8x8).
pub const CELL: usize = 8;

/// How many rows ahead a run prefetches the source cells of.
const ROWS_AHEAD: f64 = 2.0;

/// Samples the source for output voxels i0..=i1 of row (j, k); `row` starts at i = 0.
#[inline]
pub(crate) fn write_run<T: Real>(
    row: &mut [T],
    m: &TetMap,
    j: usize,
    k: usize,
    i0: usize,
    i1: usize,
    sampler: &Sampler,
) {
    let base = run_base::<T>(m, j, k);
    let step = m.src.map(|s| T::of(s[1]));
    if sampler.is_plain_trilinear() {
        // The same tet's row ROWS_AHEAD on is sampled soon after: its cells are fetched
        // while this row computes (a short run would otherwise wait on its first cells).
        let ahead = m.src.map(|s| (ROWS_AHEAD * s[2]) as f32);
        sampler.trilinear_run(&mut row[i0..=i1], [base, step], i0, m.src_inside, ahead);
        return;
    }
    for (i, out) in row[i0..=i1].iter_mut().enumerate() {
        let fi = T::of((i0 + i) as f64);
        *out = sampler.at(base[0] + step[0] * fi, base[1] + step[1] * fi, base[2] + step[2] * fi);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 300 tets with random vertices in a 24³ grid (an LCG from `seed`), half of them on
    /// lattice points (their faces then pass through voxel centres: the ties); the
    /// degenerate ones left out.
    fn random_tets(seed: u64) -> Vec<TetMap> {
        let mut state = seed;
        let mut next = move || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64 * 24.0
        };
        (0..300)
            .filter_map(|t| {
                let on_lattice = t % 2 == 0;
                let nodes: Vec<Vector3<f64>> = (0..4)
                    .map(|_| Vector3::new(next(), next(), next()).map(|v| if on_lattice { v.round() } else { v }))
                    .collect();
                tet_map(&[0, 1, 2, 3], &nodes, &nodes, [25, 25, 25])
            })
            .collect()
    }

    /// On random tets, ties included, every row's span, found from its estimated bounds, is
    /// exactly the run of voxels the predicate holds for.
    #[test]
    fn row_spans_are_exactly_the_voxels_inside() {
        let (mut rows, mut ties) = (0, 0);
        for (t, m) in random_tets(0x9E37_79B9_7F4A_7C15).iter().enumerate() {
            for k in m.lo[2]..=m.hi[2] {
                for j in m.lo[1]..=m.hi[1] {
                    let a = m.row(j, k);
                    let inside: Vec<usize> = (m.lo[0]..=m.hi[0]).filter(|&i| m.inside(&a, i)).collect();
                    let expected = inside.first().map(|&first| (first, *inside.last().unwrap_or(&first)));
                    if let Some((first, last)) = expected {
                        assert_eq!(inside.len(), last - first + 1, "a row's inside voxels are a run");
                        ties += usize::from(a.iter().any(|offset| (offset - INSIDE_TOLERANCE).fract() == 0.0));
                    }
                    assert_eq!(m.span(&a), expected, "tet {t}, row ({j}, {k})");
                    rows += 1;
                }
            }
        }
        assert!(rows > 10_000 && ties > 100, "{rows} rows, {ties} on a tie");
    }

    /// Four rows at a time (AVX) give each row's span exactly, on random tets, ties
    /// included, from every row of every slice of the box and one past it.
    #[test]
    fn four_rows_at_a_time_give_each_rows_span() {
        let mut compared = 0;
        for (t, m) in random_tets(0x2545_F491_4F6C_DD1D).iter().enumerate() {
            for k in m.lo[2]..=m.hi[2] {
                for j in m.lo[1]..=m.hi[1] + 1 {
                    let Some(four) = m.spans4(j, k) else {
                        eprintln!("skipped: no AVX on this CPU");
                        return;
                    };
                    for (r, span) in four.iter().enumerate() {
                        assert_eq!(*span, m.span(&m.row(j + r, k)), "tet {t}, row ({}, {k})", j + r);
                        compared += 1;
                    }
                }
            }
        }
        assert!(compared > 40_000, "{compared} rows compared");
    }
}
