//! The vector half of the volume raycaster's packets (`Caster::cast_packet` in `cpu.rs`):
//! eight rays in the AVX2 lanes, so the samples, the table lookups, the shading and the
//! compositing all run eight wide. Each lane does `Caster::composite`'s arithmetic in its
//! order (unfused multiplies and adds, the same clamps and truncations), so a packet's
//! pixels are the one-ray loop's bits. The macro-cell walk (`Caster::run_end`) runs in the
//! lanes too: done per lane in scalar code, it stopped the vector loop at three steps in
//! four (512², 1.25 mm) and the time per frame was a third longer.

use std::arch::x86_64::*;

use nalgebra::Matrix3;

use crate::camera::Rays;
use crate::transfer::{SegmentTable, Tables, LUT_SIZE, PREINTEGRATED_SIZE, SEGMENT_LENGTHS, SEGMENT_LEVELS};
use defvol_core::volume::lanes::Trilinear8;

/// Steps ahead whose cells a packet asks the cache for: a step (eight rays' samples, table
/// lookups and compositing) is too long for the core to run the next ones' loads early
/// on its own; further ahead gains nothing (see docs/perf/journal.md#packets-prefetch).
const AHEAD: f32 = 4.0;

/// Rays in a packet.
pub(super) const LANES: usize = 8;

/// A packet's pixels: two rows of four from `corner` (lane l at (l % 4, l / 4) past it),
/// those past the picture's edge left out (`size`: the columns and rows from `corner` to
/// that edge). Two rows of four lie closer together than one row of eight, so their rays
/// leave their macro cells at nearer steps and read nearer voxels; the same pixels (see
/// docs/perf/journal.md#packets-of-two-rows-of-four).
#[derive(Debug, Clone, Copy)]
pub(super) struct Block {
    pub(super) corner: (usize, usize),
    pub(super) size: (usize, usize),
}

impl Block {
    pub(super) const COLUMNS: usize = 4;
    pub(super) const ROWS: usize = LANES / Self::COLUMNS;

    /// Lane `l`'s pixel, where it lies in the picture.
    pub(super) fn pixel(&self, l: usize) -> Option<(usize, usize)> {
        let (column, row) = (l % Self::COLUMNS, l / Self::COLUMNS);
        (column < self.size.0 && row < self.size.1).then_some((self.corner.0 + column, self.corner.1 + row))
    }
}

/// The macro cells a packet walks (`MacroCells` in `cpu.rs`): which may hold a visible
/// sample, and how many lie along each axis.
pub(super) struct CellWalk<'a> {
    pub(super) visible: &'a [bool],
    pub(super) dims: [usize; 3],
    /// Voxels along a cell's edge: the walk's [`CELL_SHIFT`], checked when handed in.
    pub(super) edge: usize,
}

/// A macro cell's edge as a shift (8 voxels, `CELL` in `cpu.rs`): a constant in the walk's
/// code, where a shift read at run time slows the packets.
const CELL_SHIFT: i32 = 3;

/// The packet's rays in index space, lane for lane, as `Caster::composite` takes them: a
/// lane without a ray has no full segments.
pub(super) struct PacketRays {
    pub(super) o: [[f32; LANES]; 3],
    pub(super) d: [[f32; LANES]; 3],
    pub(super) t_near: [f32; LANES],
    pub(super) full: [usize; LANES],
}

/// What a packet's rays came to, lane for lane.
pub(super) struct PacketEnd {
    /// Opaque enough to stop.
    pub(super) terminated: [bool; LANES],
    /// The scalar at the last full segment's back where it is the front of the last,
    /// shorter segment (not where the ray jumped past its full segments).
    pub(super) front: [Option<f32>; LANES],
    /// Premultiplied colour and α.
    pub(super) acc: [[f32; 4]; LANES],
    pub(super) depth: [f32; LANES],
}

/// [`super::Sampler::gradient`] at eight points, the same arithmetic: each lane's 32 voxels
/// gathered (its cell's corners and their neighbours a voxel out along each axis, clamped
/// into the grid), their central differences interpolated in its cell: cheaper than six
/// clamped trilinear samples a step (see docs/perf/journal.md#gradients-of-eight-points).
#[derive(Clone, Copy)]
pub(crate) struct Gradient8<'a> {
    data: &'a [f32],
    /// The voxel-centre box's top per axis (as a float where points are clamped).
    top: [f32; 3],
    last: [i32; 3],
    /// The highest cell per axis (dims - 2, at least 0).
    cell_top: [i32; 3],
    /// Steps between voxels along each axis.
    strides: [i32; 3],
}

impl<'a> Gradient8<'a> {
    /// The gradients of x-fastest `data` over `dims`, where AVX2 serves and `data` holds
    /// the grid (whose indices an i32 reaches).
    pub(crate) fn new(data: &'a [f32], dims: [usize; 3]) -> Option<Self> {
        let fits = data.len() == dims.iter().product::<usize>() && !data.is_empty() && data.len() <= i32::MAX as usize;
        if !(fits && defvol_core::volume::lanes::lanes_available()) {
            return None;
        }
        Some(Self {
            data,
            top: dims.map(|n| (n - 1) as f32),
            last: dims.map(|n| n as i32 - 1),
            cell_top: dims.map(|n| n.saturating_sub(2) as i32),
            strides: [1, dims[0], dims[0] * dims[1]].map(|s| s as i32),
        })
    }

    /// The points `p` (x, y, z lanes) clamped onto the grid's voxel-centre box, as
    /// `Sampler::at` clamps them (the forward difference's samples read there too).
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(crate) fn clamp(&self, p: [__m256; 3]) -> [__m256; 3] {
        [0, 1, 2].map(|a| clamp8(p[a], self.top[a]))
    }

    /// The gradients at the eight points `p` (x, y, z lanes), value per voxel.
    ///
    /// # Safety
    /// As [`Trilinear8::sample`]: a `Gradient8` exists only where the CPU has AVX2.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(crate) fn at(&self, p: [__m256; 3]) -> [__m256; 3] {
        let (zero, one) = (_mm256_setzero_si256(), _mm256_set1_epi32(1));
        let v = self.clamp(p);
        let cell = [0, 1, 2].map(|a| _mm256_min_epi32(_mm256_cvttps_epi32(v[a]), _mm256_set1_epi32(self.cell_top[a])));
        let f = [0, 1, 2].map(|a| _mm256_sub_ps(v[a], _mm256_cvtepi32_ps(cell[a])));
        // Per axis the voxels before, at, after and two after the cell's first, clamped.
        let rows = [0, 1, 2].map(|a| {
            let (i, last, stride) = (cell[a], _mm256_set1_epi32(self.last[a]), _mm256_set1_epi32(self.strides[a]));
            let row = |v: __m256i| _mm256_mullo_epi32(v, stride);
            [
                row(_mm256_max_epi32(_mm256_sub_epi32(i, one), zero)),
                row(i),
                row(_mm256_min_epi32(_mm256_add_epi32(i, one), last)),
                row(_mm256_min_epi32(_mm256_add_epi32(i, _mm256_set1_epi32(2)), last)),
            ]
        });
        let mut gradient = [_mm256_setzero_ps(); 3];
        for (a, gradient) in gradient.iter_mut().enumerate() {
            // Corner c's central difference along a: its voxels one step on and one back.
            let mut d = [_mm256_setzero_ps(); 8];
            for (c, d) in d.iter_mut().enumerate() {
                let (mut on, mut back) = (zero, zero);
                for (b, rows) in rows.iter().enumerate() {
                    let corner = c >> b & 1;
                    let (to, from) = if a == b { (2 + corner, corner) } else { (1 + corner, 1 + corner) };
                    (on, back) = (_mm256_add_epi32(on, rows[to]), _mm256_add_epi32(back, rows[from]));
                }
                // SAFETY: each index is of a voxel clamped into the grid, which `data` holds
                // (checked in `new`).
                let (on, back) = unsafe {
                    (
                        _mm256_i32gather_ps::<4>(self.data.as_ptr(), on),
                        _mm256_i32gather_ps::<4>(self.data.as_ptr(), back),
                    )
                };
                *d = _mm256_sub_ps(on, back);
            }
            let (c00, c10) = (lerp8(d[0], d[1], f[0]), lerp8(d[2], d[3], f[0]));
            let (c01, c11) = (lerp8(d[4], d[5], f[0]), lerp8(d[6], d[7], f[0]));
            *gradient = _mm256_mul_ps(lerp8(lerp8(c00, c10, f[1]), lerp8(c01, c11, f[1]), f[2]), _mm256_set1_ps(0.5));
        }
        gradient
    }
}

/// The shaded kinds of `Shading`, as the lanes take them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum ShadeBy {
    Gradient,
    ForwardDifference,
}

/// `(t[0] + t[1]) + t[2]`.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn sum3(t: [__m256; 3]) -> __m256 {
    _mm256_add_ps(_mm256_add_ps(t[0], t[1]), t[2])
}

/// `volume::lambert` in the lanes, term by term: two-sided Lambert for world gradients
/// `w` lit from `light`, 1 where a gradient is too short for a normal.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn lambert8(w: [__m256; 3], light: [__m256; 3], ambient: f32) -> __m256 {
    let len = _mm256_sqrt_ps(sum3(w.map(|w| _mm256_mul_ps(w, w))));
    let dot = sum3([0, 1, 2].map(|a| _mm256_mul_ps(w[a], light[a])));
    let cosine = _mm256_andnot_ps(_mm256_set1_ps(-0.0), _mm256_div_ps(dot, len));
    let lit = _mm256_cmp_ps::<_CMP_GT_OQ>(len, _mm256_set1_ps(1e-12));
    let shaded = _mm256_add_ps(_mm256_set1_ps(ambient), _mm256_mul_ps(_mm256_set1_ps(1.0 - ambient), cosine));
    _mm256_blendv_ps(_mm256_set1_ps(1.0), shaded, lit)
}

/// `volume::lit_by_drop` in the lanes: the light a sample gets from the value's `drop`
/// one world unit toward the light (full at `scale`).
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn forward_difference8(drop: __m256, scale: f32, ambient: f32) -> __m256 {
    let scaled = _mm256_div_ps(drop, _mm256_set1_ps(scale));
    // `clamp(0, 1)`, a NaN kept: max and min return their second operand on NaN.
    let clamped = _mm256_min_ps(_mm256_set1_ps(1.0), _mm256_max_ps(_mm256_setzero_ps(), scaled));
    _mm256_add_ps(_mm256_set1_ps(ambient), _mm256_mul_ps(_mm256_set1_ps(1.0 - ambient), clamped))
}

/// `a + (b - a)·t`, `lerp_cube`'s step.
#[inline]
#[target_feature(enable = "avx2")]
fn lerp8(a: __m256, b: __m256, t: __m256) -> __m256 {
    _mm256_add_ps(a, _mm256_mul_ps(_mm256_sub_ps(b, a), t))
}

/// `Caster::shade` for the packet's lanes: the picture's shading (gradient or forward
/// difference) and each lane's light.
pub(super) struct PacketShading<'a> {
    pub(super) gradients: Gradient8<'a>,
    pub(super) by: ShadeBy,
    pub(super) ambient: f32,
    pub(super) gradient_scale: f32,
    /// An index-space gradient to a world one (`IndexSpace::gradient_to_world`).
    pub(super) to_world: [[f32; 3]; 3],
    /// Toward each lane's light: world frame, and in index space as `Caster::cast` takes it.
    pub(super) light: [[f32; LANES]; 3],
    pub(super) light_index: [[f32; LANES]; 3],
}

/// The packet's rays in the vector lanes: where their samples are, how they walk the macro
/// cells, and what they gathered.
pub(super) struct Lanes<'a> {
    trilinear: Trilinear8<'a>,
    tables: &'a Tables,
    preintegrated: bool,
    cells: Option<CellWalk<'a>>,
    shading: Option<PacketShading<'a>>,
    /// The rays (`o + d·t`), where they enter, and their full segments.
    o: [__m256; 3],
    d: [__m256; 3],
    t_near: __m256,
    full: __m256i,
    /// Each ray's first sample and the step between samples.
    base: [__m256; 3],
    delta: [__m256; 3],
    step: __m256,
    termination: __m256,
}

impl<'a> Lanes<'a> {
    /// The lanes of `rays`, sampled as `Ray::run` hands them to the sampler (at a segment's
    /// back end pre-integrated, at its middle point-sampled); segments of `step`, rays
    /// stopping once `termination` opaque, skipping the macro cells `cells` leaves dark,
    /// the samples that add shaded by `shading`.
    #[target_feature(enable = "avx2")]
    pub(super) fn new(
        (trilinear, tables, preintegrated): (Trilinear8<'a>, &'a Tables, bool),
        (cells, shading): (Option<CellWalk<'a>>, Option<PacketShading<'a>>),
        rays: &PacketRays,
        (step, termination): (f32, f32),
    ) -> Self {
        // The lookups read within tables of these sizes (checked once here, not
        // per step).
        assert_eq!(tables.stepped.len(), LUT_SIZE);
        assert!(!preintegrated || tables.preintegrated.len() == PREINTEGRATED_SIZE * PREINTEGRATED_SIZE);
        if let Some(cells) = &cells {
            assert_eq!(cells.visible.len(), cells.dims.iter().product::<usize>());
            assert_eq!(cells.edge, 1 << CELL_SHIFT);
        }
        let (o, d, t_near) = (rays.o.map(|v| load(v)), rays.d.map(|v| load(v)), load(rays.t_near));
        let step8 = _mm256_set1_ps(step);
        // `Caster::samples_along`'s first point and step, the same arithmetic.
        let first = _mm256_add_ps(t_near, _mm256_set1_ps((if preintegrated { 1.0 } else { 0.5 }) * step));
        Self {
            trilinear,
            tables,
            preintegrated,
            cells,
            shading,
            o,
            d,
            t_near,
            // More segments than an i32 holds cannot fit a ray through the volume.
            full: load_i32(rays.full.map(|f| f.min(i32::MAX as usize) as i32)),
            base: [0, 1, 2].map(|a| _mm256_add_ps(o[a], _mm256_mul_ps(d[a], first))),
            delta: d.map(|d| _mm256_mul_ps(d, step8)),
            step: step8,
            termination: _mm256_set1_ps(termination),
        }
    }

    /// Every lane's full segments front to back, eight lanes a step, each lane walking its
    /// macro cells in the vector as `Caster::run_end` walks them: a lane at the end of its
    /// run takes the next one in the same step while the others go on. A lane that jumped
    /// over dark cells reads its new front first (pre-integrated), in a step that adds
    /// nothing.
    #[target_feature(enable = "avx2")]
    pub(super) fn runs(&self) -> PacketEnd {
        let zero = _mm256_setzero_si256();
        let mut k = zero;
        // With no macro cells, one run takes every full segment.
        let mut end = if self.cells.is_some() { zero } else { self.full };
        let mut running = _mm256_castsi256_ps(_mm256_cmpgt_epi32(self.full, zero));
        // A lane with no full segment reads no front: its one segment reads its own.
        let mut lost_front = _mm256_xor_ps(running, _mm256_castsi256_ps(_mm256_set1_epi32(-1)));
        // Lanes reading their front (pre-integrated): at the start and after a jump.
        let mut pending = if self.preintegrated { running } else { _mm256_setzero_ps() };
        let mut stopped = _mm256_setzero_ps();
        let mut front = _mm256_setzero_ps();
        let mut acc = [_mm256_setzero_ps(); 4];
        let mut depth = _mm256_set1_ps(f32::INFINITY);
        let (tiny, one, half, infinity) =
            (_mm256_set1_ps(1e-5), _mm256_set1_ps(1.0), _mm256_set1_ps(0.5), _mm256_set1_ps(f32::INFINITY));
        // The next step's samples (each lane going on from its segment), read before this
        // step's lookups and compositing so that their loads overlap them. Read again where
        // a lane jumped or reads its front; two steps ahead spill registers (see
        // docs/perf/journal.md#packets-read-the-next-step-ahead).
        let (mut ahead_value, mut stale) = (_mm256_setzero_ps(), true);
        while _mm256_movemask_ps(running) != 0 {
            let at_end = _mm256_andnot_ps(_mm256_castsi256_ps(_mm256_cmpgt_epi32(end, k)), running);
            if _mm256_movemask_ps(at_end) != 0 {
                // Past the full segments: done; else the next run (with no macro cells a
                // run's end is the last full segment).
                let walking = _mm256_and_ps(at_end, _mm256_castsi256_ps(_mm256_cmpgt_epi32(self.full, k)));
                running = _mm256_andnot_ps(_mm256_andnot_ps(walking, at_end), running);
                if let Some(cells) = &self.cells {
                    let (next_k, next_end, jumped) = self.next_run(cells, k);
                    let walking = _mm256_castps_si256(walking);
                    k = _mm256_blendv_epi8(k, next_k, walking);
                    end = _mm256_blendv_epi8(end, next_end, walking);
                    let jumped = _mm256_and_ps(jumped, _mm256_castsi256_ps(walking));
                    stale |= _mm256_movemask_ps(jumped) != 0;
                    // A jump past the last full segment ends the lane; the last, shorter
                    // segment reads its own front.
                    let past = _mm256_andnot_ps(_mm256_castsi256_ps(_mm256_cmpgt_epi32(self.full, k)), jumped);
                    running = _mm256_andnot_ps(past, running);
                    lost_front = _mm256_or_ps(lost_front, past);
                    if self.preintegrated {
                        pending = _mm256_or_ps(pending, _mm256_andnot_ps(past, jumped));
                    }
                }
                if _mm256_movemask_ps(running) == 0 {
                    break;
                }
            }
            // A pending lane samples its segment's front: the previous segment's back.
            let kp = _mm256_add_epi32(k, _mm256_castps_si256(pending));
            let kf = _mm256_cvtepi32_ps(kp);
            let value = if stale || _mm256_movemask_ps(pending) != 0 { self.resample(kp) } else { ahead_value };
            stale = false;
            let adding = _mm256_andnot_ps(pending, running);
            ahead_value = self.sample_at(_mm256_sub_epi32(k, _mm256_castps_si256(adding)));
            let color = if self.preintegrated {
                // SAFETY: the table's size was checked in `new`.
                let color = unsafe { segment8(self.tables, front, value) };
                // Lanes done keep their last back: the last, shorter segment's front.
                front = _mm256_blendv_ps(front, value, running);
                color
            } else {
                // SAFETY: the table's size was checked in `new`.
                unsafe { interpolate8(self.tables, &self.tables.stepped, value) }
            };
            // `Ray::add` in the lanes whose segment adds something, shaded at its middle.
            let adds = _mm256_and_ps(adding, _mm256_cmp_ps::<_CMP_GT_OQ>(color[3], tiny));
            let middle =
                _mm256_add_ps(_mm256_add_ps(self.t_near, _mm256_mul_ps(kf, self.step)), _mm256_mul_ps(half, self.step));
            let light = match &self.shading {
                Some(shading) if _mm256_movemask_ps(adds) != 0 => Some(self.shade8(shading, middle)),
                _ => None,
            };
            let weight = _mm256_sub_ps(one, acc[3]);
            for (c, (acc, color)) in acc.iter_mut().zip(color).enumerate() {
                let mut term = _mm256_mul_ps(weight, color);
                if let (Some(light), true) = (light, c < 3) {
                    term = _mm256_mul_ps(term, light);
                }
                *acc = _mm256_blendv_ps(*acc, _mm256_add_ps(*acc, term), adds);
            }
            let first_past_half =
                _mm256_and_ps(_mm256_cmp_ps::<_CMP_EQ_OQ>(depth, infinity), _mm256_cmp_ps::<_CMP_GE_OQ>(acc[3], half));
            depth = _mm256_blendv_ps(depth, middle, _mm256_and_ps(adds, first_past_half));
            let stops = _mm256_and_ps(adds, _mm256_cmp_ps::<_CMP_GE_OQ>(acc[3], self.termination));
            stopped = _mm256_or_ps(stopped, stops);
            // k + 1 where a segment was added (such a lane's mask is -1).
            k = _mm256_sub_epi32(k, _mm256_castps_si256(adding));
            running = _mm256_andnot_ps(stops, running);
            pending = _mm256_setzero_ps();
        }
        let (stopped, lost_front) = (_mm256_movemask_ps(stopped), _mm256_movemask_ps(lost_front));
        let (fronts, acc, depth) = (store(front), acc.map(|v| store(v)), store(depth));
        PacketEnd {
            terminated: std::array::from_fn(|l| stopped >> l & 1 == 1),
            front: std::array::from_fn(|l| (self.preintegrated && lost_front >> l & 1 == 0).then_some(fronts[l])),
            acc: std::array::from_fn(|l| [acc[0][l], acc[1][l], acc[2][l], acc[3][l]]),
            depth,
        }
    }

    /// `Caster::shade` at each lane's `o + d·t`, the same arithmetic: Lambert on the
    /// gradient's normal, or the forward difference toward the light from samples at
    /// points clamped into the box.
    #[inline(never)]
    #[target_feature(enable = "avx2")]
    fn shade8(&self, shading: &PacketShading, t: __m256) -> __m256 {
        let p = [0, 1, 2].map(|a| _mm256_add_ps(self.o[a], _mm256_mul_ps(self.d[a], t)));
        let at = |q: [__m256; 3]| self.trilinear.sample(shading.gradients.clamp(q));
        match shading.by {
            ShadeBy::Gradient => {
                // `Caster::shade`: the world gradient, term by term.
                let g = shading.gradients.at(p);
                let w =
                    shading.to_world.map(|row| sum3([0, 1, 2].map(|j| _mm256_mul_ps(_mm256_set1_ps(row[j]), g[j]))));
                lambert8(w, shading.light.map(|l| load(l)), shading.ambient)
            }
            ShadeBy::ForwardDifference => {
                let toward = shading.light_index.map(|l| load(l));
                let ahead = [0, 1, 2].map(|a| _mm256_add_ps(p[a], toward[a]));
                forward_difference8(_mm256_sub_ps(at(p), at(ahead)), shading.gradient_scale, shading.ambient)
            }
        }
    }

    /// [`Self::sample_at`] out of the loop's way, for the few steps whose samples were not read
    /// ahead: a packet's first, and those after a jump or reading a front.
    #[cold]
    #[inline(never)]
    #[target_feature(enable = "avx2")]
    fn resample(&self, k: __m256i) -> __m256 {
        self.sample_at(k)
    }

    /// The samples of segments `k`, with a prefetch of the cells `AHEAD` segments on.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn sample_at(&self, k: __m256i) -> __m256 {
        let kf = _mm256_cvtepi32_ps(k);
        let at = [0, 1, 2].map(|a| _mm256_add_ps(self.base[a], _mm256_mul_ps(self.delta[a], kf)));
        let ahead = _mm256_add_ps(kf, _mm256_set1_ps(AHEAD));
        // Points past a lane's run or the volume only cost a wasted prefetch.
        self.trilinear.prefetch([0, 1, 2].map(|a| _mm256_add_ps(self.base[a], _mm256_mul_ps(self.delta[a], ahead))));
        self.trilinear.sample(at)
    }

    /// `Caster::run_end` from segment `k` in every lane, the same arithmetic: the run's
    /// first segment and its end, and whether the lane jumped over a dark cell.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn next_run(&self, cells: &CellWalk, k: __m256i) -> (__m256i, __m256i, __m256) {
        let zero = _mm256_setzero_ps();
        let kf = _mm256_cvtepi32_ps(k);
        let t0 = _mm256_add_ps(self.t_near, _mm256_mul_ps(kf, self.step));
        let p = [0, 1, 2].map(|a| _mm256_add_ps(self.o[a], _mm256_mul_ps(self.d[a], t0)));
        let cell = p.map(|p| _mm256_srli_epi32::<CELL_SHIFT>(_mm256_cvttps_epi32(_mm256_max_ps(p, zero))));
        // `MacroCells::exit`: the nearest of the cell's far faces ahead on each moving axis.
        let mut exit = _mm256_set1_ps(f32::INFINITY);
        for a in 0..3 {
            let ahead = _mm256_and_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(self.d[a], zero), _mm256_set1_ps(1.0));
            let bound = _mm256_mul_ps(
                _mm256_add_ps(_mm256_cvtepi32_ps(cell[a]), ahead),
                _mm256_set1_ps((1 << CELL_SHIFT) as f32),
            );
            let to = _mm256_add_ps(t0, _mm256_div_ps(_mm256_sub_ps(bound, p[a]), self.d[a]));
            let moving = _mm256_cmp_ps::<_CMP_NEQ_OQ>(self.d[a], zero);
            exit = _mm256_blendv_ps(exit, _mm256_min_ps(exit, to), moving);
        }
        // `MacroCells::visible_at`, the cell clamped into the grid.
        let c = [0, 1, 2].map(|a| _mm256_min_epi32(cell[a], _mm256_set1_epi32(cells.dims[a] as i32 - 1)));
        let (nx, ny) = (_mm256_set1_epi32(cells.dims[0] as i32), _mm256_set1_epi32(cells.dims[1] as i32));
        let index =
            _mm256_add_epi32(c[0], _mm256_mullo_epi32(nx, _mm256_add_epi32(c[1], _mm256_mullo_epi32(ny, c[2]))));
        let index = lanes_i32(index);
        // SAFETY: each index is of a cell clamped into the grid, which `visible` covers
        // (checked in `new`).
        let visible = std::array::from_fn(|l| -i32::from(unsafe { *cells.visible.get_unchecked(index[l] as usize) }));
        let visible = _mm256_castsi256_ps(load_i32(visible));
        // The segments before the cell's exit, capped where `as usize` would saturate
        // (far past any ray's full segments).
        let before = _mm256_div_ps(_mm256_sub_ps(exit, self.t_near), self.step);
        let cap = _mm256_set1_ps((1 << 30) as f32);
        let whole = |v| _mm256_cvttps_epi32(_mm256_min_ps(v, cap));
        let ceil = whole(_mm256_round_ps::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(before));
        let floor = whole(_mm256_round_ps::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(before));
        let (one, next) = (_mm256_set1_epi32(1), _mm256_add_epi32(k, _mm256_set1_epi32(1)));
        // Visible: every segment that starts inside the cell.
        let visible_end = _mm256_min_epi32(_mm256_max_epi32(ceil, next), self.full);
        // Dark: past the segments wholly inside it, then the one that crosses out.
        let jumped = _mm256_andnot_ps(visible, _mm256_castsi256_ps(_mm256_cmpgt_epi32(floor, k)));
        let dark_k = _mm256_blendv_epi8(k, floor, _mm256_castps_si256(jumped));
        let dark_end = _mm256_min_epi32(_mm256_add_epi32(dark_k, one), self.full);
        let visible_i = _mm256_castps_si256(visible);
        (_mm256_blendv_epi8(dark_k, k, visible_i), _mm256_blendv_epi8(dark_end, visible_end, visible_i), jumped)
    }
}

/// Eight rays of a perspective camera set up at once ([`setup8`]): their world directions,
/// and in the volume's index space their directions and where they are inside its box.
pub(super) struct Setup8 {
    pub(super) direction: [[f64; LANES]; 3],
    pub(super) d: [[f64; LANES]; 3],
    pub(super) near: [f64; LANES],
    pub(super) far: [f64; LANES],
    pub(super) inside: [bool; LANES],
}

/// `Rays::ray` (of a perspective camera's `view`), `IndexSpace::ray` and `clip` in `cpu.rs`
/// for the rays through a [`Block`]'s eight pixels (those past the picture's edge too), a
/// row of four lanes of f64 at a time with their operations in their order (nalgebra's
/// `normalize` divides by the norm, its matrix products add a row's terms first to last),
/// so the same bits. `o` is the eye in index space (the same for every ray), `top` the
/// box's far corner (n - 1 on each axis). One ray at a time the set-up was a large part of
/// a frame (see docs/perf/journal.md#small-code-generation-fixes).
#[target_feature(enable = "avx2")]
pub(super) fn setup8(
    view: &Rays,
    index_from_world: &Matrix3<f64>,
    (o, top): ([f64; 3], [f64; 3]),
    (px0, py): (usize, usize),
) -> Setup8 {
    const { assert!(Block::COLUMNS == 4, "a row of a block is one vector of f64") };
    let set = _mm256_set1_pd;
    let mut out = Setup8 {
        direction: [[0.0; LANES]; 3],
        d: [[0.0; LANES]; 3],
        near: [0.0; LANES],
        far: [0.0; LANES],
        inside: [false; LANES],
    };
    let (width, height) = (view.camera.width, view.camera.height);
    for row in 0..Block::ROWS {
        let v = (((py + row) as f64 + 0.5) / height as f64) * 2.0 - 1.0;
        let (y, z) = (set(v * view.tangent), set(1.0));
        let px = std::array::from_fn::<f64, 4, _>(|l| (px0 + l) as f64);
        // SAFETY: px holds four f64.
        let px = unsafe { _mm256_loadu_pd(px.as_ptr()) };
        let u = _mm256_sub_pd(
            _mm256_mul_pd(_mm256_div_pd(_mm256_add_pd(px, set(0.5)), set(width as f64)), set(2.0)),
            set(1.0),
        );
        let x = _mm256_mul_pd(_mm256_mul_pd(u, set(view.tangent)), set(view.aspect));
        let norm =
            _mm256_sqrt_pd(_mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(x, x), _mm256_mul_pd(y, y)), _mm256_mul_pd(z, z)));
        let unit = [x, y, z].map(|c| _mm256_div_pd(c, norm));
        let world = times(&view.rotation, unit);
        let d = times(index_from_world, world);
        let (mut near, mut far) = (_mm256_setzero_pd(), set(f64::INFINITY));
        let mut inside = _mm256_castsi256_pd(_mm256_set1_epi64x(-1));
        let magnitude = _mm256_castsi256_pd(_mm256_set1_epi64x(i64::MAX));
        for a in 0..3 {
            // An axis the ray runs along leaves the interval as it is, or misses the box.
            let along = _mm256_cmp_pd::<_CMP_LT_OQ>(_mm256_and_pd(d[a], magnitude), set(1e-300));
            if o[a] < 0.0 || o[a] > top[a] {
                inside = _mm256_andnot_pd(along, inside);
            }
            let t0 = _mm256_div_pd(set(0.0 - o[a]), d[a]);
            let t1 = _mm256_div_pd(set(top[a] - o[a]), d[a]);
            near = _mm256_blendv_pd(_mm256_max_pd(near, _mm256_min_pd(t0, t1)), near, along);
            far = _mm256_blendv_pd(_mm256_min_pd(far, _mm256_max_pd(t0, t1)), far, along);
        }
        inside = _mm256_and_pd(inside, _mm256_cmp_pd::<_CMP_LE_OQ>(near, far));
        let at = Block::COLUMNS * row;
        let put = |to: &mut [f64], v: __m256d| {
            // SAFETY: to holds eight f64 from `at`, which is 0 or 4.
            unsafe { _mm256_storeu_pd(to[at..at + 4].as_mut_ptr(), v) }
        };
        for a in 0..3 {
            put(&mut out.direction[a], world[a]);
            put(&mut out.d[a], d[a]);
        }
        put(&mut out.near, near);
        put(&mut out.far, far);
        let inside = _mm256_movemask_pd(inside);
        for l in 0..4 {
            out.inside[at + l] = inside >> l & 1 == 1;
        }
    }
    out
}

/// `m · v` for four vectors, as nalgebra takes a 3x3 matrix times a vector: column by
/// column, so each row's terms are added first to last.
#[inline]
#[target_feature(enable = "avx2")]
fn times(m: &Matrix3<f64>, v: [__m256d; 3]) -> [__m256d; 3] {
    let term = |i: usize, j: usize| _mm256_mul_pd(_mm256_set1_pd(m[(i, j)]), v[j]);
    std::array::from_fn(|i| _mm256_add_pd(_mm256_add_pd(term(i, 0), term(i, 1)), term(i, 2)))
}

#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn load(v: [f32; LANES]) -> __m256 {
    // SAFETY: v holds eight floats.
    unsafe { _mm256_loadu_ps(v.as_ptr()) }
}

#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn load_i32(v: [i32; LANES]) -> __m256i {
    // SAFETY: v holds eight i32.
    unsafe { _mm256_loadu_si256(v.as_ptr().cast()) }
}

#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn store(v: __m256) -> [f32; LANES] {
    let mut out = [0.0f32; LANES];
    // SAFETY: out holds eight floats.
    unsafe { _mm256_storeu_ps(out.as_mut_ptr(), v) };
    out
}

/// `x.clamp(0, top)` for finite x (a NaN to 0, as `Sampler::at` clamps).
#[inline]
#[target_feature(enable = "avx2")]
fn clamp8(x: __m256, top: f32) -> __m256 {
    _mm256_min_ps(_mm256_max_ps(x, _mm256_setzero_ps()), _mm256_set1_ps(top))
}

/// The lanes of `v` as eight i32 or f32.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn lanes_i32(v: __m256i) -> [i32; LANES] {
    let mut out = [0i32; LANES];
    // SAFETY: out holds eight i32.
    unsafe { _mm256_storeu_si256(out.as_mut_ptr().cast(), v) };
    out
}

/// Eight RGBA entries (lane l's in `rgba[l]`) as four channels of eight lanes.
#[inline]
#[target_feature(enable = "avx2")]
fn channels(rgba: [__m128; LANES]) -> [__m256; 4] {
    // Lanes l and l + 4 share a register, then each 128-bit half is a 4x4 transpose.
    let m = [0, 1, 2, 3].map(|l| _mm256_insertf128_ps::<1>(_mm256_castps128_ps256(rgba[l]), rgba[l + 4]));
    let (rg01, ba01) = (_mm256_unpacklo_ps(m[0], m[1]), _mm256_unpackhi_ps(m[0], m[1]));
    let (rg23, ba23) = (_mm256_unpacklo_ps(m[2], m[3]), _mm256_unpackhi_ps(m[2], m[3]));
    [
        _mm256_shuffle_ps::<0x44>(rg01, rg23),
        _mm256_shuffle_ps::<0xEE>(rg01, rg23),
        _mm256_shuffle_ps::<0x44>(ba01, ba23),
        _mm256_shuffle_ps::<0xEE>(ba01, ba23),
    ]
}

/// `a + (b - a)·f` on an entry's four channels, unfused, as `transfer.rs`'s `lerp4` takes it.
#[inline]
#[target_feature(enable = "avx2")]
fn lerp4(a: __m128, b: __m128, f: f32) -> __m128 {
    _mm_add_ps(a, _mm_mul_ps(_mm_sub_ps(b, a), _mm_set1_ps(f)))
}

/// The RGBA entry `at` entries past `ptr`.
///
/// # Safety
/// The entry must lie in the table at `ptr`.
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn entry(ptr: *const [f32; 4], at: usize) -> __m128 {
    // SAFETY: the caller's.
    unsafe { _mm_loadu_ps(ptr.add(at).cast()) }
}

/// `Tables::interpolate` in the lanes: `table` (`LUT_SIZE` entries over [lo, hi]) at `s`.
/// Each lane's two entries are read whole (16 bytes each, where gathers would fetch their
/// floats one channel at a time) and lerped per channel, then the lanes turned into
/// channels.
///
/// # Safety
/// `table` must hold `LUT_SIZE` entries.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn interpolate8(tables: &Tables, table: &[[f32; 4]], s: __m256) -> [__m256; 4] {
    let x = _mm256_mul_ps(_mm256_sub_ps(s, _mm256_set1_ps(tables.lo)), _mm256_set1_ps(tables.lut_scale));
    let x = clamp8(x, (LUT_SIZE - 1) as f32);
    let i = _mm256_min_epi32(_mm256_cvttps_epi32(x), _mm256_set1_epi32(LUT_SIZE as i32 - 2));
    let (f, i) = (store(_mm256_sub_ps(x, _mm256_cvtepi32_ps(i))), lanes_i32(i));
    let ptr = table.as_ptr();
    // SAFETY: 0 ≤ i ≤ LUT_SIZE - 2, so entries i and i + 1 lie in the table.
    channels(std::array::from_fn(|l| unsafe {
        let at = i[l] as usize;
        lerp4(entry(ptr, at), entry(ptr, at + 1), f[l])
    }))
}

/// `Tables::segment` in the lanes: the pre-integrated segments from `front` to `back`,
/// each lane's four entries read whole as in [`interpolate8`].
///
/// # Safety
/// The pre-integrated table must hold `PREINTEGRATED_SIZE`² entries.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn segment8(tables: &Tables, front: __m256, back: __m256) -> [__m256; 4] {
    // SAFETY: the caller's.
    channels(unsafe { segment8_entries(tables, front, back) })
}

/// `Tables::segment(fronts[i], backs[i])` into `out[i]` for every i, in groups of eight
/// (the same bits; the last group's spare lanes read `fronts` and `backs` past `out`'s
/// length, which must hold a whole group). One ray's queued samples: independent lookups,
/// whose index arithmetic the lanes share and whose loads they issue together.
///
/// # Safety
/// AVX2 must be present (a `Trilinear8` shows it is).
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn segments_into(tables: &Tables, fronts: &[f32], backs: &[f32], out: &mut [[f32; 4]]) {
    assert!(tables.preintegrated.len() == PREINTEGRATED_SIZE * PREINTEGRATED_SIZE);
    let groups = out.len().div_ceil(LANES);
    assert!(fronts.len() >= groups * LANES && backs.len() >= groups * LANES);
    for g in 0..groups {
        let at = g * LANES;
        // SAFETY: at + LANES ≤ groups · LANES floats, which both slices hold.
        let (front, back) =
            unsafe { (_mm256_loadu_ps(fronts.as_ptr().add(at)), _mm256_loadu_ps(backs.as_ptr().add(at))) };
        // SAFETY: the table's size is checked above.
        let entries = unsafe { segment8_entries(tables, front, back) };
        for (slot, entry) in out[at..].iter_mut().zip(entries) {
            // SAFETY: slot holds four floats.
            unsafe { _mm_storeu_ps(slot.as_mut_ptr(), entry) };
        }
    }
}

/// `SegmentTable::lookup(fronts[i], backs[i], lengths[i])` into `out[i]` for every i, in
/// groups of eight (the last group's spare lanes read the inputs past `out`'s length,
/// which must hold a whole group). A tet walk's queued segments: independent lookups,
/// whose index arithmetic the lanes share and whose loads they issue together.
///
/// # Safety
/// AVX2 must be present.
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn tet_segments_into(
    table: &SegmentTable,
    fronts: &[f32],
    backs: &[f32],
    lengths: &[f32],
    out: &mut [[f32; 4]],
) {
    let groups = out.len().div_ceil(LANES);
    assert!([fronts, backs, lengths].iter().all(|v| v.len() >= groups * LANES));
    for g in 0..groups {
        let at = g * LANES;
        // SAFETY: at + LANES ≤ groups · LANES floats, which the three slices hold.
        let [front, back, length] = [fronts, backs, lengths].map(|v| unsafe { _mm256_loadu_ps(v.as_ptr().add(at)) });
        for (slot, entry) in out[at..].iter_mut().zip(tet_segment8_entries(table, front, back, length)) {
            // SAFETY: slot holds four floats.
            unsafe { _mm_storeu_ps(slot.as_mut_ptr(), entry) };
        }
    }
}

/// `SegmentTable::lookup(front[l], back[l], length[l])` in every lane l, as four channels
/// of eight lanes (the eight-lane tet walk's segments).
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn tet_segment8(table: &SegmentTable, front: __m256, back: __m256, length: __m256) -> [__m256; 4] {
    channels(tet_segment8_entries(table, front, back, length))
}

/// `SegmentTable::lookup` in every lane, lane l's entry in `[l]`: the same clamps,
/// truncations and lerps in the same order, so the same bits.
#[inline]
#[target_feature(enable = "avx2")]
fn tet_segment8_entries(table: &SegmentTable, front: __m256, back: __m256, length: __m256) -> [__m128; LANES] {
    let (n, depth) = (SEGMENT_LEVELS, SEGMENT_LENGTHS);
    assert!(table.entries.len() == n * n * depth);
    let (lo, scale) = (_mm256_set1_ps(table.lo), _mm256_set1_ps(table.level_scale));
    let level = |s| clamp8(_mm256_mul_ps(_mm256_sub_ps(s, lo), scale), (n - 1) as f32);
    let (highest, longest) = (_mm256_set1_epi32(n as i32 - 2), _mm256_set1_epi32(depth as i32 - 2));
    let ptr = table.entries.as_ptr();
    let (x, y) = (level(front), level(back));
    let z = clamp8(_mm256_mul_ps(length, _mm256_set1_ps(table.length_scale)), (depth - 1) as f32);
    let i = _mm256_min_epi32(_mm256_cvttps_epi32(x), highest);
    let j = _mm256_min_epi32(_mm256_cvttps_epi32(y), highest);
    let l = _mm256_min_epi32(_mm256_cvttps_epi32(z), longest);
    let fraction = |v, i| store(_mm256_sub_ps(v, _mm256_cvtepi32_ps(i)));
    let (fx, fy, fz) = (fraction(x, i), fraction(y, j), fraction(z, l));
    let (n_, depth_) = (_mm256_set1_epi32(n as i32), _mm256_set1_epi32(depth as i32));
    let first =
        lanes_i32(_mm256_add_epi32(_mm256_mullo_epi32(_mm256_add_epi32(_mm256_mullo_epi32(i, n_), j), depth_), l));
    // A loop, not `array::from_fn`: its closure, compiled for AVX2, was called once per
    // lane rather than inlined.
    let mut out = [_mm_setzero_ps(); LANES];
    for (lane, out) in out.iter_mut().enumerate() {
        let at = first[lane] as usize;
        // SAFETY: 0 ≤ i, j ≤ n - 2 and 0 ≤ l ≤ depth - 2, so entries (i, j, l) to
        // (i + 1, j + 1, l + 1) lie in the table.
        unsafe {
            let (a, b) = (
                lerp4(entry(ptr, at), entry(ptr, at + 1), fz[lane]),
                lerp4(entry(ptr, at + depth), entry(ptr, at + depth + 1), fz[lane]),
            );
            let (c, d) = (
                lerp4(entry(ptr, at + n * depth), entry(ptr, at + n * depth + 1), fz[lane]),
                lerp4(entry(ptr, at + (n + 1) * depth), entry(ptr, at + (n + 1) * depth + 1), fz[lane]),
            );
            *out = lerp4(lerp4(a, b, fy[lane]), lerp4(c, d, fy[lane]), fx[lane]);
        }
    }
    out
}

/// [`segment8`]'s entries, lane l's premultiplied colour and α in `[l]`.
///
/// # Safety
/// The pre-integrated table must hold `PREINTEGRATED_SIZE`² entries.
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn segment8_entries(tables: &Tables, front: __m256, back: __m256) -> [__m128; LANES] {
    let n = PREINTEGRATED_SIZE;
    let (lo, scale) = (_mm256_set1_ps(tables.pre_lo), _mm256_set1_ps(tables.pre_scale));
    let level = |s| clamp8(_mm256_mul_ps(_mm256_sub_ps(s, lo), scale), (n - 1) as f32);
    let (x, y) = (level(front), level(back));
    let highest = _mm256_set1_epi32(n as i32 - 2);
    let (i, j) = (_mm256_min_epi32(_mm256_cvttps_epi32(x), highest), _mm256_min_epi32(_mm256_cvttps_epi32(y), highest));
    let (fx, fy) = (store(_mm256_sub_ps(x, _mm256_cvtepi32_ps(i))), store(_mm256_sub_ps(y, _mm256_cvtepi32_ps(j))));
    let at = lanes_i32(_mm256_add_epi32(_mm256_mullo_epi32(i, _mm256_set1_epi32(n as i32)), j));
    let ptr = tables.preintegrated.as_ptr();
    // SAFETY: 0 ≤ i, j ≤ n - 2, so entries (i, j) to (i + 1, j + 1) lie in the table.
    std::array::from_fn(|l| unsafe {
        let at = at[l] as usize;
        let near = lerp4(entry(ptr, at), entry(ptr, at + 1), fy[l]);
        lerp4(near, lerp4(entry(ptr, at + n), entry(ptr, at + n + 1), fy[l]), fx[l])
    })
}
