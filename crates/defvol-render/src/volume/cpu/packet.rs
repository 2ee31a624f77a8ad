//! The vector half of the volume raycaster's packets (`Caster::cast_packet` in `cpu.rs`):
//! eight rays in the AVX2 lanes, so the samples, the table lookups and the compositing all
//! run eight wide. Each lane does `Caster::composite`'s arithmetic in its order (unfused
//! multiplies and adds, the same clamps and truncations), so a packet's pixels are the
//! one-ray loop's bits; the macro-cell runs stay scalar, per lane, in `cpu.rs`.

use std::arch::x86_64::*;

use crate::transfer::{SegmentTable, Tables, LUT_SIZE, PREINTEGRATED_SIZE, SEGMENT_LENGTHS, SEGMENT_LEVELS};
use defvol_core::volume::lanes::Trilinear8;

/// Steps ahead whose cells a packet asks the cache for: a step (eight rays' samples, table
/// lookups and compositing) is too long for the core to run the next ones' loads early
/// on its own. 512², 1-1.25 mm, 2 threads, three alternating rounds on a 2-core AMD EPYC:
/// 5-10 % faster; 8 steps the same as 4.
const AHEAD: f32 = 4.0;

/// Rays in a packet.
pub(super) const LANES: usize = 8;

/// The packet's rays in the vector lanes: where their samples are, and what they gathered.
pub(super) struct Lanes<'a> {
    trilinear: Trilinear8<'a>,
    tables: &'a Tables,
    preintegrated: bool,
    /// Each ray's first sample and the step between samples.
    base: [__m256; 3],
    delta: [__m256; 3],
    t_near: __m256,
    step: __m256,
    termination: __m256,
    acc: [__m256; 4],
    depth: __m256,
}

impl<'a> Lanes<'a> {
    /// The lanes of rays whose first samples (a segment's back end or middle) are at
    /// `base`, `delta` apart, as `Ray::run` hands them to the sampler; pre-integrated or
    /// point-sampled segments of `step`, rays stopping once `termination` opaque.
    #[target_feature(enable = "avx2")]
    pub(super) fn new(
        (trilinear, tables, preintegrated): (Trilinear8<'a>, &'a Tables, bool),
        (base, delta): ([[f32; LANES]; 3], [[f32; LANES]; 3]),
        (t_near, step): ([f32; LANES], f32),
        termination: f32,
    ) -> Self {
        // The lookups read within tables of these sizes (checked once here, not
        // per step).
        assert_eq!(tables.stepped.len(), LUT_SIZE);
        assert!(!preintegrated || tables.preintegrated.len() == PREINTEGRATED_SIZE * PREINTEGRATED_SIZE);
        Self {
            trilinear,
            tables,
            preintegrated,
            base: base.map(|v| load(v)),
            delta: delta.map(|v| load(v)),
            t_near: load(t_near),
            step: _mm256_set1_ps(step),
            termination: _mm256_set1_ps(termination),
            acc: [_mm256_setzero_ps(); 4],
            depth: _mm256_set1_ps(f32::INFINITY),
        }
    }

    /// Segments k, k + 1, ... of the live lanes, all a step at a time, until every lane is
    /// done or has terminated. A lane at the end of its run (up to its `end`) asks
    /// `next(lane, k)` for its next one, `(k, end, front)`, in the loop (`front`: the
    /// scalar at the new run's front where it jumped, else the last back goes on; an empty
    /// run ends the lane), or `None` when it is done. Returns whether each lane terminated,
    /// and the scalar at its last segment's back.
    #[target_feature(enable = "avx2")]
    pub(super) fn runs(
        &mut self,
        (k, end, live): ([usize; LANES], [usize; LANES], [bool; LANES]),
        fronts: [f32; LANES],
        mut next: impl FnMut(usize, usize) -> Option<(usize, usize, Option<f32>)>,
    ) -> ([bool; LANES], [f32; LANES]) {
        let mut kv = load_i32(k.map(|k| k as i32));
        let mut end = load_i32(end.map(|e| e as i32));
        let mut running = _mm256_castsi256_ps(load_i32(live.map(|l| -i32::from(l))));
        let mut stopped = _mm256_setzero_ps();
        let mut front = load(fronts);
        let (tiny, one, half, infinity) =
            (_mm256_set1_ps(1e-5), _mm256_set1_ps(1.0), _mm256_set1_ps(0.5), _mm256_set1_ps(f32::INFINITY));
        loop {
            let kf = _mm256_cvtepi32_ps(kv);
            let at = [0, 1, 2].map(|a| _mm256_add_ps(self.base[a], _mm256_mul_ps(self.delta[a], kf)));
            let ahead = _mm256_add_ps(kf, _mm256_set1_ps(AHEAD));
            // Points past a lane's run or the volume only cost a wasted prefetch.
            self.trilinear
                .prefetch([0, 1, 2].map(|a| _mm256_add_ps(self.base[a], _mm256_mul_ps(self.delta[a], ahead))));
            let value = self.trilinear.sample(at);
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
            // `Ray::add` in the running lanes whose segment adds something.
            let adds = _mm256_and_ps(running, _mm256_cmp_ps::<_CMP_GT_OQ>(color[3], tiny));
            let weight = _mm256_sub_ps(one, self.acc[3]);
            for (acc, color) in self.acc.iter_mut().zip(color) {
                *acc = _mm256_blendv_ps(*acc, _mm256_add_ps(*acc, _mm256_mul_ps(weight, color)), adds);
            }
            let middle =
                _mm256_add_ps(_mm256_add_ps(self.t_near, _mm256_mul_ps(kf, self.step)), _mm256_mul_ps(half, self.step));
            let first_past_half = _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_EQ_OQ>(self.depth, infinity),
                _mm256_cmp_ps::<_CMP_GE_OQ>(self.acc[3], half),
            );
            self.depth = _mm256_blendv_ps(self.depth, middle, _mm256_and_ps(adds, first_past_half));
            let stops = _mm256_and_ps(adds, _mm256_cmp_ps::<_CMP_GE_OQ>(self.acc[3], self.termination));
            stopped = _mm256_or_ps(stopped, stops);
            // k + 1 where running (a running lane's mask is -1).
            kv = _mm256_sub_epi32(kv, _mm256_castps_si256(running));
            running = _mm256_andnot_ps(stops, running);
            let within = _mm256_and_ps(running, _mm256_castsi256_ps(_mm256_cmpgt_epi32(end, kv)));
            let running_bits = _mm256_movemask_ps(running);
            let ended = running_bits & !_mm256_movemask_ps(within);
            if ended != 0 {
                // The lanes whose run is over take their next one here: leaving the loop
                // for them stopped every lane every 1.4 steps (512², 1.25 mm, counted).
                let (mut ks, mut ends, mut live) =
                    (lanes_i32(kv), lanes_i32(end), lanes_i32(_mm256_castps_si256(running)));
                let mut fronts = store(front);
                for l in (0..LANES).filter(|l| ended >> l & 1 == 1) {
                    match next(l, ks[l] as usize) {
                        Some((k, e, f)) => {
                            (ks[l], ends[l]) = (k as i32, e as i32);
                            if let Some(f) = f {
                                fronts[l] = f;
                            }
                            // A jump past the last full segment: done.
                            if k >= e {
                                live[l] = 0;
                            }
                        }
                        None => live[l] = 0,
                    }
                }
                (kv, end, front) = (load_i32(ks), load_i32(ends), load(fronts));
                running = _mm256_castsi256_ps(load_i32(live));
            }
            if _mm256_movemask_ps(running) == 0 {
                break;
            }
        }
        let stopped = _mm256_movemask_ps(stopped);
        (std::array::from_fn(|l| stopped >> l & 1 == 1), store(front))
    }

    /// Each lane's premultiplied colour and α, and its depth.
    #[target_feature(enable = "avx2")]
    pub(super) fn colour(&self) -> ([[f32; LANES]; 4], [f32; LANES]) {
        (self.acc.map(|v| store(v)), store(self.depth))
    }
}

#[inline]
#[target_feature(enable = "avx2")]
fn load(v: [f32; LANES]) -> __m256 {
    // SAFETY: v holds eight floats.
    unsafe { _mm256_loadu_ps(v.as_ptr()) }
}

#[inline]
#[target_feature(enable = "avx2")]
fn load_i32(v: [i32; LANES]) -> __m256i {
    // SAFETY: v holds eight i32.
    unsafe { _mm256_loadu_si256(v.as_ptr().cast()) }
}

#[inline]
#[target_feature(enable = "avx2")]
fn store(v: __m256) -> [f32; LANES] {
    let mut out = [0.0f32; LANES];
    // SAFETY: out holds eight floats.
    unsafe { _mm256_storeu_ps(out.as_mut_ptr(), v) };
    out
}

/// `x.clamp(0, top)` for finite x.
#[inline]
#[target_feature(enable = "avx2")]
fn clamp8(x: __m256, top: f32) -> __m256 {
    _mm256_min_ps(_mm256_max_ps(x, _mm256_setzero_ps()), _mm256_set1_ps(top))
}

/// The lanes of `v` as eight i32 or f32.
#[inline]
#[target_feature(enable = "avx2")]
fn lanes_i32(v: __m256i) -> [i32; LANES] {
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
unsafe fn interpolate8(tables: &Tables, table: &[[f32; 4]], s: __m256) -> [__m256; 4] {
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
unsafe fn segment8(tables: &Tables, front: __m256, back: __m256) -> [__m256; 4] {
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
/// groups of eight: the same clamps, truncations and lerps in the same order, so the same
/// bits (the last group's spare lanes read the inputs past `out`'s length, which must hold
/// a whole group). A tet walk's queued segments: independent lookups, whose index
/// arithmetic the lanes share and whose loads they issue together.
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
    let (n, depth) = (SEGMENT_LEVELS, SEGMENT_LENGTHS);
    assert!(table.entries.len() == n * n * depth);
    let groups = out.len().div_ceil(LANES);
    assert!([fronts, backs, lengths].iter().all(|v| v.len() >= groups * LANES));
    let (lo, scale) = (_mm256_set1_ps(table.lo), _mm256_set1_ps(table.level_scale));
    let level = |s| clamp8(_mm256_mul_ps(_mm256_sub_ps(s, lo), scale), (n - 1) as f32);
    let (highest, longest) = (_mm256_set1_epi32(n as i32 - 2), _mm256_set1_epi32(depth as i32 - 2));
    let ptr = table.entries.as_ptr();
    for g in 0..groups {
        let at = g * LANES;
        // SAFETY: at + LANES ≤ groups · LANES floats, which the three slices hold.
        let [front, back, length] = [fronts, backs, lengths].map(|v| unsafe { _mm256_loadu_ps(v.as_ptr().add(at)) });
        let (x, y) = (level(front), level(back));
        let z = clamp8(_mm256_mul_ps(length, _mm256_set1_ps(table.length_scale)), (depth - 1) as f32);
        let i = _mm256_min_epi32(_mm256_cvttps_epi32(x), highest);
        let j = _mm256_min_epi32(_mm256_cvttps_epi32(y), highest);
        let l = _mm256_min_epi32(_mm256_cvttps_epi32(z), longest);
        let fraction = |v, i| store(_mm256_sub_ps(v, _mm256_cvtepi32_ps(i)));
        let (fx, fy, fz) = (fraction(x, i), fraction(y, j), fraction(z, l));
        let (n_, depth_) = (_mm256_set1_epi32(n as i32), _mm256_set1_epi32(depth as i32));
        let first = _mm256_add_epi32(_mm256_mullo_epi32(_mm256_add_epi32(_mm256_mullo_epi32(i, n_), j), depth_), l);
        let first = lanes_i32(first);
        for (lane, slot) in out[at..].iter_mut().take(LANES).enumerate() {
            let at = first[lane] as usize;
            // SAFETY: 0 ≤ i, j ≤ n - 2 and 0 ≤ l ≤ depth - 2, so entries (i, j, l) to
            // (i + 1, j + 1, l + 1) lie in the table; slot holds four floats.
            unsafe {
                let near = |at: usize| lerp4(entry(ptr, at), entry(ptr, at + 1), fz[lane]);
                let (a, b) = (near(at), near(at + depth));
                let (c, d) = (near(at + n * depth), near(at + (n + 1) * depth));
                let e = lerp4(lerp4(a, b, fy[lane]), lerp4(c, d, fy[lane]), fx[lane]);
                _mm_storeu_ps(slot.as_mut_ptr(), e);
            }
        }
    }
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
