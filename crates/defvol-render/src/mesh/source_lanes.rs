//! The source seen through the mesh eight rays at a time (AVX2, pre-integrated or point
//! sampled, shaded or not, trilinear and undisplaced): each lane its own ray in its own
//! tet, a lane's step one sample of its ray. The samples' positions, trilinear reads, box
//! test, table lookups, shading and compositing run once for eight, as the volume
//! raycaster's packets run them; a lane whose samples in its tet are done walks on to the
//! next tet (exit face, link, the tet's map onto the source) while the others wait in the
//! same step. A lane whose walk ends goes back to the one-ray code (the last, shorter
//! segment; entries, re-entries) and takes its strip's next ray when its own is done. Each
//! lane does the one-ray walk's arithmetic (`SourceLook::cross`, `flush`) in the same
//! order, so the pictures are the same bits.

use std::arch::x86_64::*;

use defvol_core::volume::lanes::{CellLookup, Trilinear8};

use super::cpu::{StripRay, TetRaycaster, MAX_WALK};
use super::entry::TileFaces;
use super::field::V3;
use super::geometry::TetGeometry;
use super::lanes::{composite8, leave8};
use super::look::{SourceLook, TetMap, EDGE_TOLERANCE};
use crate::volume::packet::{
    forward_difference8, interpolate8, lambert8, lanes_i32, segment8, store, sum3, Gradient8, ShadeBy,
};

/// Rays side by side.
const LANES: usize = 8;
/// Lanes done with their tet's samples that walk on together (sooner where no lane has a
/// sample left; the others wait): a walk step's gathers cost the same for one lane as for
/// eight, and a lane walks on every five samples or so (the benchmark's 4k-tet bend at
/// 1 mm), so walking each at once took a walk step in three steps of four. Waiting for
/// three: about 0.93 of the time (in-process, 0.89-0.92 of the one-ray walk against
/// 0.95-0.98).
const TET_STEP_LANES: u32 = 3;
/// Floats in a [`TetGeometry`] (its planes first) and in a [`TetMap`].
const GEOMETRY_FLOATS: i32 = (std::mem::size_of::<TetGeometry>() / 4) as i32;
const MAP_FLOATS: i32 = (std::mem::size_of::<TetMap>() / 4) as i32;

/// The lanes' walks, a vector each (lane l in element l). A lane in a tet (`in_tet`) has
/// its exit `t_out` and its samples there: `first..end` on the ray's grid
/// (`t0 + (k + offset)·step`), at `base + along·k` in the source; `visible` as the tet's
/// source visibility.
#[derive(Clone, Copy)]
struct Walk8 {
    busy: __m256,
    o: [__m256; 3],
    d: [__m256; 3],
    t_stop: __m256,
    tet: __m256i,
    face: __m256i,
    exit: __m256i,
    t_in: __m256,
    t_out: __m256,
    in_tet: __m256,
    stalled: __m256i,
    steps: __m256i,
    t0: __m256,
    k: __m256i,
    first: __m256i,
    end: __m256i,
    visible: __m256,
    base: [__m256; 3],
    along: [__m256; 3],
    /// The last sample's value, and whether it lay in the source (the next segment's front).
    front: __m256,
    front_in: __m256,
    acc: [__m256; 4],
    depth: __m256,
}

/// Lanes whose walk ended in a step (bit l for lane l): where each stopped, and those that
/// left the mesh or met a tool (the last, shorter segment is still to add).
struct Ended {
    lanes: i32,
    t: __m256,
    leaving: i32,
}

/// What a strip's lanes read: the source, its sampler and tables.
struct Reads<'a> {
    look: &'a SourceLook,
    sampler: Trilinear8<'a>,
    /// The source's voxel-centre box's far corner (plus the edge tolerance).
    top: [__m256; 3],
    /// Pre-integrated segments (the samples from the ray's entry on), else point samples
    /// (at the middles of their steps).
    preintegrated: bool,
    /// Where a sample lies in its step: 0 pre-integrated, ½ point sampled.
    offset: __m256,
    step: __m256,
    shade: Option<Shade8<'a>>,
}

/// `SourceLook::shade` for the lanes: the picture's shading and its light (each ray's
/// own, toward the eye, where none is set).
struct Shade8<'a> {
    gradients: Gradient8<'a>,
    by: ShadeBy,
    light: Option<[__m256; 3]>,
    ambient: f32,
    gradient_scale: f32,
}

impl TetRaycaster {
    /// Casts every ray of a strip of tiles (`tiles`: their faces) through the source to its
    /// end: each `ray.acc` and `ray.depth` as [`TetRaycaster::cast`] leaves them. False
    /// (nothing cast) where the lanes do not serve.
    ///
    /// # Safety
    /// AVX2 must be present and the mesh within `LANES_MAX_TETS` tets.
    #[target_feature(enable = "avx2")]
    pub(crate) unsafe fn cast_source_strip(&self, tiles: &[TileFaces], rays: &mut [StripRay]) -> bool {
        let Some(look) = self.source.as_ref().filter(|s| s.lanes_serve()) else { return false };
        let volume = &look.volume;
        let Some(sampler) = Trilinear8::new(volume.data(), &CellLookup::for_dims(volume.dims())) else {
            return false;
        };
        let dims = volume.dims();
        let top = [0, 1, 2].map(|a| _mm256_set1_ps((dims[a] - 1) as f32 + EDGE_TOLERANCE));
        let preintegrated = look.params.preintegrated;
        let offset = _mm256_set1_ps(if preintegrated { 0.0 } else { 0.5 });
        let step = _mm256_set1_ps(look.params.step as f32);
        // A shaded picture's gradients (where AVX2 serves, as the sampler's).
        let shade = match look.params.shading.in_lanes() {
            None => None,
            Some(by) => {
                let Some(gradients) = Gradient8::new(volume.data(), dims) else { return false };
                Some(Shade8 {
                    gradients,
                    by,
                    light: look.params.light.map(|l| {
                        let l = nalgebra::Vector3::from(l).normalize().cast::<f32>();
                        [0, 1, 2].map(|a| _mm256_set1_ps(l[a]))
                    }),
                    ambient: look.params.ambient as f32,
                    gradient_scale: look.gradient_scale,
                })
            }
        };
        let reads = Reads { look, sampler, top, preintegrated, offset, step, shade };
        let mut w = self.idle_lanes();
        let mut ray_of = [0usize; LANES];
        let mut next = 0;
        for lane in 0..LANES {
            self.take_source_ray(tiles, rays, &mut w, &mut ray_of, lane, &mut next);
        }
        while _mm256_movemask_ps(w.busy) != 0 {
            let ended = loop {
                let ended = self.source_step8(&reads, &mut w);
                if ended.lanes != 0 {
                    break ended;
                }
            };
            let t_end = store(ended.t);
            for lane in (0..LANES).filter(|l| ended.lanes & (1 << l) != 0) {
                if ended.leaving & (1 << lane) != 0 {
                    self.last_segment(look, &mut w, lane, t_end[lane]);
                }
                let ray = &mut rays[ray_of[lane]];
                for c in 0..4 {
                    ray.ray.acc[c] = store(w.acc[c])[lane];
                }
                ray.ray.depth = store(w.depth)[lane];
                let start = if self.walked_to(&mut ray.ray, t_end[lane]) {
                    self.next_start(&tiles[ray.tile], &mut ray.ray)
                } else {
                    None
                };
                match start {
                    Some(start) => start_walk(&mut w, lane, start),
                    None => self.take_source_ray(tiles, rays, &mut w, &mut ray_of, lane, &mut next),
                }
            }
        }
        true
    }

    /// Eight idle lanes (their tets 0, so that gathers for them read the mesh's first).
    #[target_feature(enable = "avx2")]
    fn idle_lanes(&self) -> Walk8 {
        let (zero, zero_i) = (_mm256_setzero_ps(), _mm256_setzero_si256());
        Walk8 {
            busy: zero,
            o: [zero; 3],
            d: [zero; 3],
            t_stop: zero,
            tet: zero_i,
            face: zero_i,
            exit: zero_i,
            t_in: zero,
            t_out: zero,
            in_tet: zero,
            stalled: zero_i,
            steps: zero_i,
            t0: zero,
            k: zero_i,
            first: zero_i,
            end: zero_i,
            visible: zero,
            base: [zero; 3],
            along: [zero; 3],
            front: zero,
            front_in: zero,
            acc: [zero; 4],
            depth: _mm256_set1_ps(f32::INFINITY),
        }
    }

    /// Gives `lane` the strip's next ray that enters the mesh (those that do not are
    /// finished as they are); the lane idles when none is left.
    #[target_feature(enable = "avx2")]
    fn take_source_ray(
        &self,
        tiles: &[TileFaces],
        rays: &mut [StripRay],
        w: &mut Walk8,
        ray_of: &mut [usize; LANES],
        lane: usize,
        next: &mut usize,
    ) {
        set_mask(&mut w.busy, lane, false);
        let Some((k, start)) = self.next_entering(tiles, rays, next) else { return };
        let ray = &rays[k].ray;
        ray_of[lane] = k;
        for c in 0..3 {
            set(&mut w.o[c], lane, ray.o[c]);
            set(&mut w.d[c], lane, ray.d[c]);
        }
        set(&mut w.t_stop, lane, ray.t_stop);
        for c in 0..4 {
            set(&mut w.acc[c], lane, ray.acc[c]);
        }
        set(&mut w.depth, lane, ray.depth);
        start_walk(w, lane, start);
    }

    /// [`super::look::SourceLook::finish`] for a lane that left the mesh or met a tool at
    /// `t_end`: the segment from its last sample there, added to what it gathered.
    #[target_feature(enable = "avx2")]
    fn last_segment(&self, look: &SourceLook, w: &mut Walk8, lane: usize, t_end: f32) {
        let (o, d) = (store_v3(&w.o, lane), store_v3(&w.d, lane));
        let front_in = _mm256_movemask_ps(w.front_in) & (1 << lane) != 0;
        let front = if front_in { Some(store(w.front)[lane]) } else { None };
        let k = lanes_i32(w.k)[lane] as u32;
        let mut march = look.resumed(&o, &d, store(w.t0)[lane], k, front);
        let mut acc = [0.0; 4];
        for (c, acc) in acc.iter_mut().enumerate() {
            *acc = store(w.acc[c])[lane];
        }
        let mut depth = store(w.depth)[lane];
        look.finish(&mut march, lanes_i32(w.tet)[lane] as usize, t_end, &mut acc, &mut depth);
        for c in 0..4 {
            set(&mut w.acc[c], lane, acc[c]);
        }
        set(&mut w.depth, lane, depth);
    }

    /// One step of every busy lane: the lanes done with their tet's samples walk to the
    /// next tet once [`TET_STEP_LANES`] are (`walk_steps`' loop body after `cross`, then up
    /// to it), then every lane with a sample left in its tet takes it (`flush`'s loop body).
    #[inline]
    #[target_feature(enable = "avx2")]
    fn source_step8(&self, reads: &Reads, w: &mut Walk8) -> Ended {
        let done = _mm256_andnot_ps(_mm256_castsi256_ps(_mm256_cmpgt_epi32(w.end, w.k)), w.busy);
        let mut ended = Ended { lanes: 0, t: _mm256_setzero_ps(), leaving: 0 };
        let waiting = _mm256_movemask_ps(done).count_ones();
        if waiting >= TET_STEP_LANES || (waiting > 0 && waiting == _mm256_movemask_ps(w.busy).count_ones()) {
            ended = self.next_tet8(reads, w, done);
        }
        let sampling = _mm256_and_ps(w.busy, _mm256_castsi256_ps(_mm256_cmpgt_epi32(w.end, w.k)));
        if _mm256_movemask_ps(sampling) != 0 {
            let opaque = sample8(reads, w, sampling);
            if _mm256_movemask_ps(opaque) != 0 {
                w.busy = _mm256_andnot_ps(opaque, w.busy);
                let opaque_bits = _mm256_movemask_ps(opaque);
                ended.t = _mm256_blendv_ps(ended.t, w.t_out, opaque);
                ended.lanes |= opaque_bits;
            }
        }
        ended
    }

    /// The lanes of `done` leave their tet (out of the mesh, at a tool, or on through the
    /// exit face's link) and walk into the next: its exit, its samples and map. Lanes whose
    /// walk ends are no longer busy.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn next_tet8(&self, reads: &Reads, w: &mut Walk8, done: __m256) -> Ended {
        // Leaving the tet the lane was in: out of the mesh or at a tool, else on.
        let leaving_tet = _mm256_and_ps(done, w.in_tet);
        let links = self.links.as_ptr().cast::<i32>();
        // SAFETY: every lane's tet is one of the mesh's (see `at` below), four links a tet,
        // its exit face one of them (0 where it has none yet).
        let link =
            unsafe { _mm256_i32gather_epi32::<4>(links, _mm256_add_epi32(_mm256_slli_epi32::<2>(w.tet), w.exit)) };
        let off = _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_setzero_si256(), link));
        let out = _mm256_or_ps(off, _mm256_cmp_ps::<_CMP_GE_OQ>(w.t_out, w.t_stop));
        let leaving = _mm256_and_ps(leaving_tet, out);
        let on = _mm256_andnot_ps(out, leaving_tet);
        let on_i = _mm256_castps_si256(on);
        w.tet = _mm256_blendv_epi8(w.tet, _mm256_srai_epi32::<2>(link), on_i);
        w.face = _mm256_blendv_epi8(w.face, _mm256_and_si256(link, _mm256_set1_epi32(3)), on_i);
        w.t_in = _mm256_blendv_ps(w.t_in, w.t_out, on);
        w.steps = _mm256_sub_epi32(w.steps, on_i);
        let walked_out =
            _mm256_and_ps(on, _mm256_castsi256_ps(_mm256_cmpeq_epi32(w.steps, _mm256_set1_epi32(MAX_WALK as i32))));
        // Entering: the lanes done that go on, and those starting a walk.
        let entering =
            _mm256_andnot_ps(_mm256_or_ps(leaving, walked_out), _mm256_or_ps(on, _mm256_andnot_ps(w.in_tet, done)));
        let base = _mm256_mullo_epi32(w.tet, _mm256_set1_epi32(GEOMETRY_FLOATS));
        let floats = self.geometry.as_ptr().cast::<f32>();
        // SAFETY: every lane's tet is one of the mesh's (a busy lane's the tet it walks, an
        // idle lane's the last it walked, or 0 before it walked: tets exist while any lane
        // is busy), at most LANES_MAX_TETS, so its floats' i32 indices lie in the geometry.
        let at = |k: i32| unsafe { _mm256_i32gather_ps::<4>(floats, _mm256_add_epi32(base, _mm256_set1_epi32(k))) };
        let leave = leave8(&at, (&w.o, &w.d), w.face, (w.t_in, w.t_stop), w.stalled);
        let (t_out, exit_k) = (leave.t_out, leave.exit);
        let none = _mm256_and_ps(entering, leave.none);
        // Only the lanes entering a tet count its step.
        let entering_i = _mm256_castps_si256(_mm256_andnot_ps(none, entering));
        w.stalled = _mm256_blendv_epi8(w.stalled, leave.stalled, entering_i);
        let stall = _mm256_and_ps(_mm256_castsi256_ps(entering_i), leave.stall);
        let into = _mm256_andnot_ps(stall, _mm256_castsi256_ps(entering_i));
        w.t_out = _mm256_blendv_ps(w.t_out, t_out, _mm256_or_ps(into, stall));
        w.exit = _mm256_blendv_epi8(w.exit, _mm256_and_si256(exit_k, _mm256_set1_epi32(3)), _mm256_castps_si256(into));
        self.samples_in8(reads, w, into);
        w.in_tet = _mm256_or_ps(w.in_tet, into);
        // Ended: left the mesh or at a tool (t_out, the last segment to add), MAX_WALK
        // tets crossed or no exit (t_in), stalled (t_out).
        let ended = _mm256_or_ps(_mm256_or_ps(leaving, walked_out), _mm256_or_ps(none, stall));
        w.busy = _mm256_andnot_ps(ended, w.busy);
        let t_end = _mm256_blendv_ps(w.t_out, w.t_in, _mm256_or_ps(none, walked_out));
        Ended { lanes: _mm256_movemask_ps(ended), t: t_end, leaving: _mm256_movemask_ps(leaving) }
    }

    /// `SourceLook::samples_in` and `SampleLine::end` for the lanes of `into`, just into a
    /// tet: where their samples lie in the source and which fall in the tet, the tet's
    /// visibility. Point sampled, a tet that is not visible has no samples to read
    /// (`SourceLook::queue_crossing`).
    #[inline]
    #[target_feature(enable = "avx2")]
    fn samples_in8(&self, reads: &Reads, w: &mut Walk8, into: __m256) {
        let look = reads.look;
        let maps = look.maps.as_ptr().cast::<f32>();
        let base = _mm256_mullo_epi32(w.tet, _mm256_set1_epi32(MAP_FLOATS));
        // SAFETY: as the geometry's in `next_tet8`: a map a tet, 12 floats.
        let at = |k: i32| unsafe { _mm256_i32gather_ps::<4>(maps, _mm256_add_epi32(base, _mm256_set1_epi32(k))) };
        let step = reads.step;
        let first = _mm256_add_ps(w.t0, _mm256_mul_ps(reads.offset, step));
        let second = _mm256_add_ps(first, step);
        let point = |t: __m256| [0, 1, 2].map(|a| _mm256_add_ps(w.o[a], _mm256_mul_ps(w.d[a], t)));
        let (x0, x1) = (point(first), point(second));
        for a in 0..3 {
            let r = [at(4 * a), at(4 * a + 1), at(4 * a + 2), at(4 * a + 3)];
            let apply = |x: &[__m256; 3]| {
                let xy = _mm256_add_ps(_mm256_mul_ps(r[0], x[0]), _mm256_mul_ps(r[1], x[1]));
                _mm256_add_ps(_mm256_add_ps(xy, _mm256_mul_ps(r[2], x[2])), r[3])
            };
            let (b, next) = (apply(&x0), apply(&x1));
            w.base[a as usize] = _mm256_blendv_ps(w.base[a as usize], b, into);
            w.along[a as usize] = _mm256_blendv_ps(w.along[a as usize], _mm256_sub_ps(next, b), into);
        }
        let visible = look.visible.as_ptr().cast::<i32>();
        // SAFETY: a visibility a tet.
        let seen = unsafe { _mm256_i32gather_epi32::<4>(visible, w.tet) };
        let seen = _mm256_castsi256_ps(_mm256_cmpgt_epi32(seen, _mm256_setzero_si256()));
        w.visible = _mm256_blendv_ps(w.visible, seen, into);
        let into_i = _mm256_castps_si256(into);
        w.first = _mm256_blendv_epi8(w.first, w.k, into_i);
        w.end = _mm256_blendv_epi8(w.end, sample_end8(w, reads, into), into_i);
        if !reads.preintegrated {
            let unseen = _mm256_castps_si256(_mm256_andnot_ps(w.visible, into));
            w.k = _mm256_blendv_epi8(w.k, w.end, unseen);
        }
    }
}

/// `SampleLine::end(k, t_out)` in every lane of `into`: one past the last sample at or
/// before the tet's exit, from the lane's next sample on.
#[inline]
#[target_feature(enable = "avx2")]
fn sample_end8(w: &Walk8, reads: &Reads, into: __m256) -> __m256i {
    let (step, offset) = (reads.step, reads.offset);
    let guess = _mm256_sub_ps(_mm256_div_ps(_mm256_sub_ps(w.t_out, w.t0), step), offset);
    let finite =
        _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_andnot_ps(_mm256_set1_ps(-0.0), guess), _mm256_set1_ps(f32::INFINITY));
    // Truncation from 0 up; capped where the i32 would wrap (far past any ray's samples).
    let whole =
        _mm256_cvttps_epi32(_mm256_min_ps(_mm256_max_ps(guess, _mm256_setzero_ps()), _mm256_set1_ps((1 << 30) as f32)));
    let one = _mm256_set1_epi32(1);
    let guessed = _mm256_max_epi32(_mm256_add_epi32(whole, one), w.k);
    let mut end = _mm256_blendv_epi8(w.k, guessed, _mm256_castps_si256(finite));
    let t = |e: __m256i| _mm256_add_ps(w.t0, _mm256_mul_ps(_mm256_add_ps(_mm256_cvtepi32_ps(e), offset), step));
    loop {
        let back = _mm256_and_ps(
            _mm256_and_ps(into, _mm256_castsi256_ps(_mm256_cmpgt_epi32(end, w.k))),
            _mm256_cmp_ps::<_CMP_GT_OQ>(t(_mm256_sub_epi32(end, one)), w.t_out),
        );
        if _mm256_movemask_ps(back) == 0 {
            break;
        }
        end = _mm256_add_epi32(end, _mm256_castps_si256(back));
    }
    loop {
        let on = _mm256_and_ps(into, _mm256_cmp_ps::<_CMP_LE_OQ>(t(end), w.t_out));
        if _mm256_movemask_ps(on) == 0 {
            break;
        }
        end = _mm256_sub_epi32(end, _mm256_castps_si256(on));
    }
    end
}

/// Sample k of each lane of `sampling` read, looked up against its front and composited
/// (`SourceLook::flush`'s loop body; in a tet that is not visible only the first sample
/// adds, and the last is the next front): the lanes now opaque enough to stop.
#[inline]
#[target_feature(enable = "avx2")]
fn sample8(reads: &Reads, w: &mut Walk8, sampling: __m256) -> __m256 {
    let look = reads.look;
    let kf = _mm256_cvtepi32_ps(w.k);
    let q = [0, 1, 2].map(|a| _mm256_add_ps(w.base[a], _mm256_mul_ps(w.along[a], kf)));
    // SAFETY: a `Trilinear8` exists only where the CPU has AVX2; its clamps keep any
    // point's corners in the source.
    let value = reads.sampler.sample(q);
    let mut inside = sampling;
    for (q, top) in q.iter().zip(&reads.top) {
        let low = _mm256_cmp_ps::<_CMP_GE_OQ>(*q, _mm256_set1_ps(-EDGE_TOLERANCE));
        inside = _mm256_and_ps(inside, _mm256_and_ps(low, _mm256_cmp_ps::<_CMP_LE_OQ>(*q, *top)));
    }
    let first = _mm256_castsi256_ps(_mm256_cmpeq_epi32(w.k, w.first));
    let counts = _mm256_and_ps(_mm256_or_ps(w.visible, first), inside);
    let step = reads.step;
    let t = _mm256_add_ps(w.t0, _mm256_mul_ps(_mm256_add_ps(kf, reads.offset), step));
    let (e, adds, t_mid) = if reads.preintegrated {
        // SAFETY: pre-integrated tables hold PREINTEGRATED_SIZE² segments (`Tables::new`).
        let e = unsafe { segment8(&look.tables, w.front, value) };
        let after_first = _mm256_castsi256_ps(_mm256_cmpgt_epi32(w.k, _mm256_setzero_si256()));
        let t_mid = _mm256_sub_ps(t, _mm256_mul_ps(_mm256_set1_ps(0.5), step));
        (e, _mm256_and_ps(counts, _mm256_and_ps(w.front_in, after_first)), t_mid)
    } else {
        // SAFETY: the stepped table holds LUT_SIZE entries (`Tables::new`).
        (unsafe { interpolate8(&look.tables, &look.tables.stepped, value) }, counts, t)
    };
    let adds = _mm256_and_ps(adds, _mm256_cmp_ps::<_CMP_GT_OQ>(e[3], _mm256_set1_ps(1e-5)));
    let shade = match &reads.shade {
        Some(shade) if _mm256_movemask_ps(adds) != 0 => {
            // Shaded where the one-ray walk shades: a segment's middle, or the point sample.
            let at = if reads.preintegrated {
                let back = _mm256_sub_ps(kf, _mm256_set1_ps(0.5));
                [0, 1, 2].map(|a| _mm256_add_ps(w.base[a], _mm256_mul_ps(w.along[a], back)))
            } else {
                q
            };
            Some(shade8(reads, shade, w, at))
        }
        _ => None,
    };
    composite8(&mut w.acc, &mut w.depth, (adds, shade), e, t_mid);
    w.front = _mm256_blendv_ps(w.front, value, sampling);
    w.front_in = _mm256_blendv_ps(w.front_in, inside, sampling);
    // The next sample: on, or in a tet that is not visible from the first to the last.
    let one = _mm256_set1_epi32(1);
    let last = _mm256_sub_epi32(w.end, one);
    let skip = _mm256_andnot_ps(w.visible, _mm256_and_ps(first, _mm256_castsi256_ps(_mm256_cmpgt_epi32(last, w.k))));
    let next = _mm256_blendv_epi8(_mm256_add_epi32(w.k, one), last, _mm256_castps_si256(skip));
    w.k = _mm256_blendv_epi8(w.k, next, _mm256_castps_si256(sampling));
    let termination = _mm256_set1_ps(look.params.early_termination as f32);
    _mm256_and_ps(sampling, _mm256_cmp_ps::<_CMP_GE_OQ>(w.acc[3], termination))
}

/// `SourceLook::shade` at source index `q` in each lane's tet, the same arithmetic: the
/// source's gradient carried through the tet's map, or the forward difference one world
/// unit toward the light, from samples at points clamped into the source's box.
#[inline(never)]
#[target_feature(enable = "avx2")]
fn shade8(reads: &Reads, shade: &Shade8, w: &Walk8, q: [__m256; 3]) -> __m256 {
    let maps = reads.look.maps.as_ptr().cast::<f32>();
    let base = _mm256_mullo_epi32(w.tet, _mm256_set1_epi32(MAP_FLOATS));
    // SAFETY: as in `samples_in8`: a map a tet, 12 floats, the lanes' tets the mesh's.
    let map = |a: usize, j: usize| unsafe {
        _mm256_i32gather_ps::<4>(maps, _mm256_add_epi32(base, _mm256_set1_epi32((4 * a + j) as i32)))
    };
    let light = shade.light.unwrap_or(w.d.map(|d| _mm256_xor_ps(d, _mm256_set1_ps(-0.0))));
    let at = |p: [__m256; 3]| reads.sampler.sample(shade.gradients.clamp(p));
    match shade.by {
        ShadeBy::Gradient => {
            let gi = shade.gradients.at(q);
            // ∇ₓf = Gᵀ ∇_q f.
            let g = [0, 1, 2].map(|j| sum3([0, 1, 2].map(|a| _mm256_mul_ps(map(a, j), gi[a]))));
            lambert8(g, light, shade.ambient)
        }
        ShadeBy::ForwardDifference => {
            // One world unit toward the light, in the source's index: G·l.
            let l = [0, 1, 2].map(|a| sum3([0, 1, 2].map(|j| _mm256_mul_ps(map(a, j), light[j]))));
            let ahead = [0, 1, 2].map(|a| _mm256_add_ps(q[a], l[a]));
            forward_difference8(_mm256_sub_ps(at(q), at(ahead)), shade.gradient_scale, shade.ambient)
        }
    }
}

/// Starts a walk in `lane` at (tet, entry face, t): its samples' grid from t.
#[target_feature(enable = "avx2")]
fn start_walk(w: &mut Walk8, lane: usize, (tet, face, t): (u32, u32, f32)) {
    set_i32(&mut w.tet, lane, tet as i32);
    set_i32(&mut w.face, lane, face as i32);
    set(&mut w.t_in, lane, t);
    set(&mut w.t0, lane, t);
    for v in [&mut w.k, &mut w.first, &mut w.end, &mut w.stalled, &mut w.steps] {
        set_i32(v, lane, 0);
    }
    set_mask(&mut w.in_tet, lane, false);
    set_mask(&mut w.front_in, lane, false);
    set_mask(&mut w.busy, lane, true);
}

/// Element `lane` of `v` set to `x`, by a blend with `x` in every element: storing the
/// vector, writing the element and loading the vector back stalled each load on the
/// store before it (see docs/perf/journal.md#a-lane-set-by-a-blend).
#[target_feature(enable = "avx2")]
fn set(v: &mut __m256, lane: usize, x: f32) {
    *v = _mm256_blendv_ps(*v, _mm256_set1_ps(x), _mm256_castsi256_ps(lane_mask(lane)));
}

#[target_feature(enable = "avx2")]
fn set_i32(v: &mut __m256i, lane: usize, x: i32) {
    *v = _mm256_blendv_epi8(*v, _mm256_set1_epi32(x), lane_mask(lane));
}

#[target_feature(enable = "avx2")]
fn set_mask(v: &mut __m256, lane: usize, on: bool) {
    set(v, lane, f32::from_bits(if on { u32::MAX } else { 0 }));
}

/// Lane `lane` of three vectors.
#[target_feature(enable = "avx2")]
fn store_v3(v: &[__m256; 3], lane: usize) -> V3 {
    V3::new(store(v[0])[lane], store(v[1])[lane], store(v[2])[lane])
}

/// All bits set in element `lane` alone.
#[inline]
#[target_feature(enable = "avx2")]
fn lane_mask(lane: usize) -> __m256i {
    _mm256_cmpeq_epi32(_mm256_set1_epi32(lane as i32), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `set` and `set_i32` change element `lane` alone, to the bits given (a NaN's payload
    /// and a negative zero kept), as writing that element of the lanes' array does.
    #[test]
    fn setting_a_lane_writes_that_element_alone() {
        if !defvol_core::volume::lanes::lanes_available() {
            eprintln!("skipped: no AVX2 on this CPU");
            return;
        }
        let start: [f32; LANES] = [1.5, -0.0, f32::INFINITY, 7.0, -3.25, 1e-30, 42.0, -8.0];
        let start_i = start.map(|v| v.to_bits() as i32);
        for lane in 0..LANES {
            for x in [2.5, -0.0, f32::from_bits(0x7fc0_1234), f32::NEG_INFINITY] {
                let (mut expected, mut expected_i) = (start, start_i);
                expected[lane] = x;
                expected_i[lane] = x.to_bits() as i32;
                // SAFETY: AVX2 is present (checked above); the arrays hold eight lanes.
                let (got, got_i) = unsafe {
                    let mut v = _mm256_loadu_ps(start.as_ptr());
                    let mut v_i = _mm256_loadu_si256(start_i.as_ptr().cast());
                    set(&mut v, lane, x);
                    set_i32(&mut v_i, lane, x.to_bits() as i32);
                    (store(v), lanes_i32(v_i))
                };
                assert_eq!(got.map(f32::to_bits), expected.map(f32::to_bits), "lane {lane}, x {x}");
                assert_eq!(got_i, expected_i, "lane {lane}, x {x}");
            }
        }
    }
}
