//! The pre-integrated walk eight rays at a time, each lane its own ray in its own tet
//! (AVX2): one ray's walk is a chain of dependent steps (planes → exit → link → the next
//! tet's planes), so a lone ray waits on it; eight rays side by side fill each other's
//! waits, and the exit's four faces, the scalar, the visibility test, the table lookup and
//! the compositing run once for eight. A lane whose walk ends goes back to the one-ray
//! code (`next_start`, `walked_to`: the entries, re-entries and the camera inside the mesh)
//! and takes the strip's next ray when its own is done. Each lane does the one-ray walk's
//! arithmetic in the same order (unfused), so the pictures are the same bits.

use std::arch::x86_64::*;

use super::cpu::{StripRay, TetRaycaster, LANES_MAX_TETS, MAX_STALL, MAX_WALK, NO_FACE};
use super::entry::TileFaces;
use super::geometry::TetGeometry;
use crate::volume::packet::{lanes_i32, load, load_i32, store, tet_segment8};

/// Rays side by side.
const LANES: usize = 8;
/// Floats in a [`TetGeometry`]: four planes, then the gradient.
const GEOMETRY_FLOATS: i32 = (std::mem::size_of::<TetGeometry>() / 4) as i32;

/// The lanes' walks, a value per lane: ray, tet, entry face, where the segment starts
/// and its scalar there, what the ray has gathered, and the runs the one-ray walk counts.
#[derive(Default)]
struct Lanes {
    ray: [usize; LANES],
    busy: [bool; LANES],
    o: [[f32; LANES]; 3],
    d: [[f32; LANES]; 3],
    t_stop: [f32; LANES],
    tet: [i32; LANES],
    face: [i32; LANES],
    t_in: [f32; LANES],
    s_in: [f32; LANES],
    acc: [[f32; LANES]; 4],
    depth: [f32; LANES],
    stalled: [i32; LANES],
    steps: [i32; LANES],
}

/// The lanes in registers while they walk.
#[derive(Clone, Copy)]
struct Walk8 {
    busy: __m256,
    o: [__m256; 3],
    d: [__m256; 3],
    t_stop: __m256,
    tet: __m256i,
    face: __m256i,
    t_in: __m256,
    s_in: __m256,
    acc: [__m256; 4],
    depth: __m256,
    stalled: __m256i,
    steps: __m256i,
}

impl TetRaycaster {
    /// Casts every ray of a strip of tiles (`tiles`: their faces) to its end: each
    /// `ray.acc` and `ray.depth` as [`TetRaycaster::cast`] leaves them.
    ///
    /// # Safety
    /// AVX2 must be present; the raycaster pre-integrates and shows no source.
    #[target_feature(enable = "avx2")]
    pub(crate) unsafe fn cast_strip(&self, tiles: &[TileFaces], rays: &mut [StripRay]) {
        debug_assert!(self.params.preintegrated && self.source.is_none() && self.tets().len() <= LANES_MAX_TETS);
        let mut lanes = Lanes::default();
        let mut next = 0;
        for lane in 0..LANES {
            self.take_ray(tiles, rays, &mut lanes, lane, &mut next);
        }
        while lanes.busy.iter().any(|&b| b) {
            let mut walk = lanes.load();
            let (ended, t_end) = loop {
                let (ended, t_end) = self.step8(&mut walk);
                if ended != 0 {
                    break (ended, t_end);
                }
            };
            walk.store(&mut lanes);
            let t_end = store(t_end);
            for lane in (0..LANES).filter(|l| ended & (1 << l) != 0) {
                let ray = &mut rays[lanes.ray[lane]];
                (ray.ray.acc, ray.ray.depth) = (lanes.acc.map(|c| c[lane]), lanes.depth[lane]);
                let start = if self.walked_to(&mut ray.ray, t_end[lane]) {
                    self.next_start(&tiles[ray.tile], &mut ray.ray)
                } else {
                    None
                };
                match start {
                    Some(start) => self.start_walk(&mut lanes, lane, start),
                    None => self.take_ray(tiles, rays, &mut lanes, lane, &mut next),
                }
            }
        }
    }

    /// Gives `lane` the strip's next ray that enters the mesh (those that do not are
    /// finished as they are); the lane idles when none is left.
    fn take_ray(&self, tiles: &[TileFaces], rays: &mut [StripRay], lanes: &mut Lanes, lane: usize, next: &mut usize) {
        lanes.busy[lane] = false;
        let Some((k, start)) = self.next_entering(tiles, rays, next) else { return };
        let ray = &rays[k].ray;
        lanes.ray[lane] = k;
        for c in 0..3 {
            (lanes.o[c][lane], lanes.d[c][lane]) = (ray.o[c], ray.d[c]);
        }
        lanes.t_stop[lane] = ray.t_stop;
        for c in 0..4 {
            lanes.acc[c][lane] = ray.acc[c];
        }
        lanes.depth[lane] = ray.depth;
        self.start_walk(lanes, lane, start);
    }

    /// Starts a walk in `lane` at (tet, entry face, t).
    fn start_walk(&self, lanes: &mut Lanes, lane: usize, (tet, face, t): (u32, u32, f32)) {
        let g = &self.geometry[tet as usize].gradient;
        let [o, d] = [lanes.o, lanes.d].map(|v| [v[0][lane], v[1][lane], v[2][lane]]);
        lanes.s_in[lane] = g[0] * (o[0] + d[0] * t) + g[1] * (o[1] + d[1] * t) + g[2] * (o[2] + d[2] * t) + g[3];
        (lanes.tet[lane], lanes.face[lane], lanes.t_in[lane]) = (tet as i32, face as i32, t);
        (lanes.stalled[lane], lanes.steps[lane], lanes.busy[lane]) = (0, 0, true);
    }

    /// One step of every busy lane (`walk_steps`' loop body, lane by lane): the lanes whose
    /// walk ended (bit l for lane l) and where each stopped.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn step8(&self, w: &mut Walk8) -> (i32, __m256) {
        let base = _mm256_mullo_epi32(w.tet, _mm256_set1_epi32(GEOMETRY_FLOATS));
        let floats = self.geometry.as_ptr().cast::<f32>();
        // SAFETY: every lane's tet is one of the mesh's (a busy lane's the tet it walks, an
        // idle lane's the last it walked, or 0 before it walked: tets exist while any lane
        // is busy), at most LANES_MAX_TETS, so its floats' i32 indices lie in the geometry.
        let at = |k: i32| unsafe { _mm256_i32gather_ps::<4>(floats, _mm256_add_epi32(base, _mm256_set1_epi32(k))) };
        let Leave8 { t_out, len, exit: exit_k, none, stalled, stall } =
            leave8(&at, (&w.o, &w.d), w.face, (w.t_in, w.t_stop), w.stalled);
        w.stalled = stalled;
        let s_out = scalar8(&at, w, t_out);
        let go = _mm256_andnot_ps(_mm256_or_ps(none, stall), w.busy);
        self.cross8(w, go, (len, t_out), s_out);
        let opaque = _mm256_cmp_ps::<_CMP_GE_OQ>(w.acc[3], _mm256_set1_ps(self.params.early_termination as f32));
        let exit_k = _mm256_and_si256(exit_k, _mm256_set1_epi32(3));
        let links = self.links.as_ptr().cast::<i32>();
        // SAFETY: as the geometry's: four links a tet.
        let link =
            unsafe { _mm256_i32gather_epi32::<4>(links, _mm256_add_epi32(_mm256_slli_epi32::<2>(w.tet), exit_k)) };
        let off = _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_setzero_si256(), link));
        let out = _mm256_or_ps(_mm256_or_ps(opaque, off), _mm256_cmp_ps::<_CMP_GE_OQ>(t_out, w.t_stop));
        let on = _mm256_andnot_ps(out, go);
        let on_i = _mm256_castps_si256(on);
        w.tet = _mm256_blendv_epi8(w.tet, _mm256_srai_epi32::<2>(link), on_i);
        w.face = _mm256_blendv_epi8(w.face, _mm256_and_si256(link, _mm256_set1_epi32(3)), on_i);
        w.t_in = _mm256_blendv_ps(w.t_in, t_out, on);
        w.s_in = _mm256_blendv_ps(w.s_in, s_out, on);
        w.steps = _mm256_sub_epi32(w.steps, on_i);
        let walked_out = _mm256_castsi256_ps(_mm256_cmpeq_epi32(w.steps, _mm256_set1_epi32(MAX_WALK as i32)));
        // Ended: no exit (where it came in), stalled, out, opaque or at a tool (t_out), or
        // MAX_WALK tets crossed (t_out, the tet it came to).
        let ended = _mm256_and_ps(_mm256_or_ps(_mm256_or_ps(none, stall), _mm256_or_ps(out, walked_out)), w.busy);
        (_mm256_movemask_ps(ended), _mm256_blendv_ps(t_out, w.t_in, none))
    }

    /// The segment [t_in, t_out] of the lanes in `go` whose scalar reaches the visible
    /// span: one table lookup composited, or (past the table's lengths, rare) the one-ray
    /// pieces.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn cross8(&self, w: &mut Walk8, go: __m256, (len, t_out): (__m256, __m256), s_out: __m256) {
        let (lo, hi) = (_mm256_set1_ps(self.visible.0), _mm256_set1_ps(self.visible.1));
        let above = _mm256_or_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(w.s_in, lo), _mm256_cmp_ps::<_CMP_GT_OQ>(s_out, lo));
        let below = _mm256_or_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(w.s_in, hi), _mm256_cmp_ps::<_CMP_LT_OQ>(s_out, hi));
        let seen = _mm256_and_ps(go, _mm256_and_ps(above, below));
        let max_len = _mm256_set1_ps(self.table.max_len);
        let positive = _mm256_cmp_ps::<_CMP_GT_OQ>(len, _mm256_setzero_ps());
        let short = _mm256_and_ps(seen, _mm256_and_ps(positive, _mm256_cmp_ps::<_CMP_LE_OQ>(len, max_len)));
        if _mm256_movemask_ps(short) != 0 {
            let back = _mm256_add_ps(w.s_in, _mm256_sub_ps(s_out, w.s_in));
            let e = tet_segment8(&self.table, w.s_in, back, len);
            let t_mid = _mm256_add_ps(w.t_in, _mm256_mul_ps(_mm256_set1_ps(0.5), len));
            composite8(&mut w.acc, &mut w.depth, (short, None), e, t_mid);
        }
        let long = _mm256_movemask_ps(_mm256_and_ps(seen, _mm256_cmp_ps::<_CMP_GT_OQ>(len, max_len)));
        if long != 0 {
            self.integrate_lanes(w, long, t_out, s_out);
        }
    }

    /// [`Self::cross8`]'s long segments, lane by lane.
    #[cold]
    #[target_feature(enable = "avx2")]
    fn integrate_lanes(&self, w: &mut Walk8, long: i32, t_out: __m256, s_out: __m256) {
        let mut acc = w.acc.map(|v| store(v));
        let mut depth = store(w.depth);
        let [t0, t1, s0, s1] = [w.t_in, t_out, w.s_in, s_out].map(|v| store(v));
        for l in (0..LANES).filter(|l| long & (1 << l) != 0) {
            let mut lane = acc.map(|c| c[l]);
            self.integrate(&mut lane, &mut depth[l], t0[l], t1[l], s0[l], s1[l]);
            for c in 0..4 {
                acc[c][l] = lane[c];
            }
        }
        w.acc = acc.map(|v| load(v));
        w.depth = load(depth);
    }
}

/// Where each lane's ray leaves its tet, as `walk_steps` works it out lane by lane.
pub(crate) struct Leave8 {
    /// `ahead(t_exit, t_in, t_stop)`, and `t_out - t_in`.
    pub(crate) t_out: __m256,
    pub(crate) len: __m256,
    /// The exit face, [`NO_FACE`] where none lies ahead (`none`).
    pub(crate) exit: __m256i,
    pub(crate) none: __m256,
    /// The stall count after this step (steps in a row that moved no further), and where it
    /// passed [`MAX_STALL`].
    pub(crate) stalled: __m256i,
    pub(crate) stall: __m256,
}

/// The exit ([`exit8`]), its clamp between `t_in` and `t_stop` and the stall count from
/// `stalled` in every lane: [`Leave8`]. `at(k)`: float k of each lane's geometry; `o`, `d`
/// the lanes' rays, `face` their entry faces.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn leave8(
    at: &impl Fn(i32) -> __m256,
    (o, d): (&[__m256; 3], &[__m256; 3]),
    face: __m256i,
    (t_in, t_stop): (__m256, __m256),
    stalled: __m256i,
) -> Leave8 {
    let (t_exit, exit) = exit8(at, o, d, face);
    let none = _mm256_castsi256_ps(_mm256_cmpeq_epi32(exit, _mm256_set1_epi32(NO_FACE as i32)));
    // ahead(): no earlier than t_in, no later than t_stop.
    let t = _mm256_blendv_ps(t_in, t_exit, _mm256_cmp_ps::<_CMP_GT_OQ>(t_exit, t_in));
    let t_out = _mm256_blendv_ps(t_stop, t, _mm256_cmp_ps::<_CMP_LT_OQ>(t, t_stop));
    let len = _mm256_sub_ps(t_out, t_in);
    let abs_in = _mm256_andnot_ps(_mm256_set1_ps(-0.0), t_in);
    let slack = _mm256_mul_ps(_mm256_set1_ps(1e-6), _mm256_add_ps(_mm256_set1_ps(1.0), abs_in));
    let still = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LE_OQ>(len, slack));
    let stalled = _mm256_and_si256(still, _mm256_sub_epi32(stalled, still));
    let stall = _mm256_castsi256_ps(_mm256_cmpgt_epi32(stalled, _mm256_set1_epi32(MAX_STALL as i32)));
    Leave8 { t_out, len, exit, none, stalled, stall }
}

/// `exit_face` in every lane: the face other than the entry face the ray moves out
/// through (denominator above 1e-7) with the smallest ray parameter, the first of equals;
/// [`NO_FACE`] where none lies ahead.
#[inline]
#[target_feature(enable = "avx2")]
fn exit8(at: &impl Fn(i32) -> __m256, o: &[__m256; 3], d: &[__m256; 3], face: __m256i) -> (__m256, __m256i) {
    let mut best_t = _mm256_set1_ps(f32::INFINITY);
    let mut best_k = _mm256_set1_epi32(NO_FACE as i32);
    for k in 0..4 {
        // Written out, not `map`ped: `array::map` calls a closure compiled for AVX2 instead
        // of inlining it.
        let p = [at(4 * k), at(4 * k + 1), at(4 * k + 2), at(4 * k + 3)];
        let dot = |v: &[__m256; 3]| {
            _mm256_add_ps(
                _mm256_add_ps(_mm256_mul_ps(p[0], v[0]), _mm256_mul_ps(p[1], v[1])),
                _mm256_mul_ps(p[2], v[2]),
            )
        };
        let denom = dot(d);
        let t = _mm256_div_ps(_mm256_sub_ps(p[3], dot(o)), denom);
        let k = _mm256_set1_epi32(k);
        let entry = _mm256_castsi256_ps(_mm256_cmpeq_epi32(face, k));
        let ahead = _mm256_andnot_ps(entry, _mm256_cmp_ps::<_CMP_GT_OQ>(denom, _mm256_set1_ps(1e-7)));
        let better = _mm256_and_ps(ahead, _mm256_cmp_ps::<_CMP_LT_OQ>(t, best_t));
        best_t = _mm256_blendv_ps(best_t, t, better);
        best_k = _mm256_blendv_epi8(best_k, k, _mm256_castps_si256(better));
    }
    (best_t, best_k)
}

/// The scalar at `t` in every lane's tet (its gradient, floats 16-19).
#[inline]
#[target_feature(enable = "avx2")]
fn scalar8(at: &impl Fn(i32) -> __m256, w: &Walk8, t: __m256) -> __m256 {
    let g = [at(16), at(17), at(18), at(19)];
    let term = |c: usize| _mm256_mul_ps(g[c], _mm256_add_ps(w.o[c], _mm256_mul_ps(w.d[c], t)));
    _mm256_add_ps(_mm256_add_ps(_mm256_add_ps(term(0), term(1)), term(2)), g[3])
}

/// `composite` in the lanes of `mask`: the entry `e` (four channels) behind what each has
/// gathered (`acc`), its colour times `shade` where shaded, the `depth` where opacity
/// first passes 0.5.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn composite8(
    acc: &mut [__m256; 4],
    depth: &mut __m256,
    (mask, shade): (__m256, Option<__m256>),
    e: [__m256; 4],
    t_mid: __m256,
) {
    let weight = _mm256_sub_ps(_mm256_set1_ps(1.0), acc[3]);
    for (c, (acc, e)) in acc.iter_mut().zip(e).enumerate() {
        let mut term = _mm256_mul_ps(weight, e);
        if let (Some(shade), true) = (shade, c < 3) {
            term = _mm256_mul_ps(term, shade);
        }
        *acc = _mm256_blendv_ps(*acc, _mm256_add_ps(*acc, term), mask);
    }
    let unset =
        _mm256_cmp_ps::<_CMP_EQ_OQ>(_mm256_andnot_ps(_mm256_set1_ps(-0.0), *depth), _mm256_set1_ps(f32::INFINITY));
    let half = _mm256_cmp_ps::<_CMP_GE_OQ>(acc[3], _mm256_set1_ps(0.5));
    *depth = _mm256_blendv_ps(*depth, t_mid, _mm256_and_ps(mask, _mm256_and_ps(unset, half)));
}

impl Lanes {
    #[inline]
    #[target_feature(enable = "avx2")]
    fn load(&self) -> Walk8 {
        let mut busy = [0i32; LANES];
        for (mask, &b) in busy.iter_mut().zip(&self.busy) {
            *mask = -i32::from(b);
        }
        let busy = _mm256_castsi256_ps(load_i32(busy));
        Walk8 {
            busy,
            o: [load(self.o[0]), load(self.o[1]), load(self.o[2])],
            d: [load(self.d[0]), load(self.d[1]), load(self.d[2])],
            t_stop: load(self.t_stop),
            tet: load_i32(self.tet),
            face: load_i32(self.face),
            t_in: load(self.t_in),
            s_in: load(self.s_in),
            acc: [load(self.acc[0]), load(self.acc[1]), load(self.acc[2]), load(self.acc[3])],
            depth: load(self.depth),
            stalled: load_i32(self.stalled),
            steps: load_i32(self.steps),
        }
    }
}

impl Walk8 {
    /// What the lanes' walks change, back into `lanes`.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn store(&self, lanes: &mut Lanes) {
        (lanes.tet, lanes.face) = (lanes_i32(self.tet), lanes_i32(self.face));
        (lanes.t_in, lanes.s_in) = (store(self.t_in), store(self.s_in));
        let acc = &self.acc;
        lanes.acc = [store(acc[0]), store(acc[1]), store(acc[2]), store(acc[3])];
        lanes.depth = store(self.depth);
        (lanes.stalled, lanes.steps) = (lanes_i32(self.stalled), lanes_i32(self.steps));
    }
}
