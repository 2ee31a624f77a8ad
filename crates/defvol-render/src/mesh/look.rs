//! What the tet raycaster reads inside a tet when it shows the source volume (built by
//! `source.rs`): per tet the affine map from deformed positions to the source's index
//! space, and the march of samples on one grid along the ray, composited as the volume
//! raycaster composites. `tet_raycast.wgsl` holds the GPU twin (`source_cross`,
//! `source_finish`).

use std::sync::Arc;

use nalgebra::Vector3;
use rayon::prelude::*;

use super::field::{linear_field, V3};
use crate::transfer::Tables;
use crate::volume::{RaycastParams, Sampler, Shading};
use defvol_core::volume::bspline::{backward_all, CompiledDisplacement};
#[cfg(target_arch = "x86_64")]
use defvol_core::volume::lanes::{CellLookup, Trilinear8};
use defvol_core::volume::{tricubic, Grid, Sampling, Volume};

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
    pub(crate) grid: Grid,
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
pub(crate) struct March<'a> {
    o: V3,
    d: V3,
    light: V3,
    t0: f32,
    k: u32,
    front: Option<f32>,
    /// Where samples wait to be read together (unshaded trilinear samples, AVX2).
    queue: Option<Queue<'a>>,
}

/// A ray's samples queued across the tets it crosses, read eight at a time and
/// composited once `BATCH` wait or the walk ends: a crossing holds a few samples (about
/// five at 1 mm in the benchmark's 4k-tet mesh), too few to fill the sampler's lanes, and
/// read per crossing they left most lanes idle.
pub(crate) struct Queue<'a> {
    #[cfg(target_arch = "x86_64")]
    sampler: Trilinear8<'a>,
    #[cfg(not(target_arch = "x86_64"))]
    sampler: std::marker::PhantomData<&'a ()>,
    /// Source index of each sample, per axis (a run's last eight lanes may write past
    /// `BATCH`, into the spare room).
    q: [[f32; QUEUE_ROOM]; 3],
    /// Its place on the ray's grid of samples.
    k: [u32; QUEUE_ROOM],
    /// Whether its segment (or point sample) adds; else it is only the next one's front.
    adds: [bool; BATCH],
    len: usize,
}

/// The queue's slots: `BATCH` and the eight a run's last group of lanes may overrun.
const QUEUE_ROOM: usize = BATCH + 8;

/// Samples read at once (eight-lane groups where AVX2 serves) before compositing them: a
/// ray that turns opaque wastes at most this many minus one.
const BATCH: usize = 16;
// The sampler stores whole groups of eight lanes into a batch.
const _: () = assert!(BATCH.is_multiple_of(8));

/// A ray's samples in one tet, on the source's index: the k-th at `base + step·k`, at ray
/// parameter `t0 + (k + offset)·dt`.
struct SampleLine {
    base: V3,
    step: V3,
    map: TetMap,
    t0: f32,
    dt: f32,
    offset: f32,
}

impl SampleLine {
    #[inline]
    fn t(&self, k: u32) -> f32 {
        self.t0 + (k as f32 + self.offset) * self.dt
    }

    #[inline]
    fn q(&self, k: u32) -> V3 {
        self.base + self.step * k as f32
    }

    /// One past the last sample at or before `t_out`, from sample `k` on.
    fn end(&self, k: u32, t_out: f32) -> u32 {
        let guess = (t_out - self.t0) / self.dt - self.offset;
        // Truncation is the floor from 0 up; `floor` would be a libm call on baseline x86-64.
        let mut end = if guess.is_finite() { (guess.max(0.0) as u32 + 1).max(k) } else { k };
        while end > k && self.t(end - 1) > t_out {
            end -= 1;
        }
        while self.t(end) <= t_out {
            end += 1;
        }
        end
    }
}

#[inline]
fn apply(map: &TetMap, x: &V3) -> V3 {
    let row = |r: &[f32; 4]| r[0] * x.x + r[1] * x.y + r[2] * x.z + r[3];
    V3::new(row(&map[0]), row(&map[1]), row(&map[2]))
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
        if !self.in_box(&q) {
            return None;
        }
        let (data, dims) = (self.volume.data(), self.volume.dims());
        match self.sampling {
            Sampling::Trilinear => Some(crate::volume::sample_clamped(data, dims, &q)),
            Sampling::Tricubic => tricubic(data, dims, q.x, q.y, q.z),
        }
    }

    /// The source clamped to its box (the forward difference's samples at the border).
    #[inline]
    fn clamped(&self, q: &V3) -> f32 {
        crate::volume::sample_clamped(self.volume.data(), self.volume.dims(), q)
    }

    /// Lambert factor at rest index q in a tet with `map`, lit from `light` (deformed world).
    fn shade(&self, q: &V3, map: &TetMap, light: &V3) -> f32 {
        let ambient = self.params.ambient as f32;
        match self.params.shading {
            Shading::None => 1.0,
            Shading::Gradient => {
                let gi = crate::volume::gradient_clamped(self.volume.data(), self.volume.dims(), q);
                // ∇ₓf = Gᵀ ∇_q f: the source's gradient carried through the tet's map.
                let g = V3::new(
                    map[0][0] * gi.x + map[1][0] * gi.y + map[2][0] * gi.z,
                    map[0][1] * gi.x + map[1][1] * gi.y + map[2][1] * gi.z,
                    map[0][2] * gi.x + map[1][2] * gi.y + map[2][2] * gi.z,
                );
                crate::volume::lambert(&g, light, ambient)
            }
            Shading::ForwardDifference => {
                // One world unit toward the light, in the source's index: G·l.
                let l = V3::new(
                    map[0][0] * light.x + map[0][1] * light.y + map[0][2] * light.z,
                    map[1][0] * light.x + map[1][1] * light.y + map[1][2] * light.z,
                    map[2][0] * light.x + map[2][1] * light.y + map[2][2] * light.z,
                );
                crate::volume::lit_by_drop(self.clamped(q) - self.clamped(&(q + l)), self.gradient_scale, ambient)
            }
        }
    }

    /// Adds a segment's premultiplied colour and α, shaded at q.
    #[allow(clippy::too_many_arguments)]
    fn add(&self, acc: &mut [f32; 4], depth: &mut f32, e: [f32; 4], q: &V3, map: &TetMap, light: &V3, t_mid: f32) {
        if e[3] <= 1e-5 {
            return;
        }
        blend(acc, depth, e, self.shade(q, map, light), t_mid);
    }

    /// A ray from anchored `o` along `d` entering the mesh at `t0`.
    pub(crate) fn march(&self, o: &V3, d: &V3, t0: f32) -> March<'_> {
        March { queue: self.queue(), ..self.march_without_queue(o, d, t0) }
    }

    /// A march already `k` samples past `t0` (`front`: the last one's value, where it lay
    /// in the source), without a queue: what the eight-lane walk hands to [`Self::finish`].
    pub(crate) fn resumed(&self, o: &V3, d: &V3, t0: f32, k: u32, front: Option<f32>) -> March<'_> {
        March { k, front, queue: None, ..self.march_without_queue(o, d, t0) }
    }

    fn march_without_queue(&self, o: &V3, d: &V3, t0: f32) -> March<'_> {
        let light = self.params.light.map_or(-d, |l| Vector3::from(l).normalize().cast::<f32>());
        March { o: *o, d: *d, light, t0, k: 0, front: None, queue: None }
    }

    /// Whether rays may walk eight at a time through this source (`super::source_lanes`):
    /// trilinear, undisplaced, AVX2 present and the source in the eight-lane sampler's
    /// reach; shaded or not.
    pub(crate) fn lanes_serve(&self) -> bool {
        #[cfg(target_arch = "x86_64")]
        return self.displacements.is_empty()
            && self.sampling == Sampling::Trilinear
            && Trilinear8::new(self.volume.data(), &CellLookup::for_dims(self.volume.dims())).is_some();
        #[cfg(not(target_arch = "x86_64"))]
        false
    }

    /// An empty queue where its samples serve: trilinear, undisplaced, unshaded, AVX2.
    fn queue(&self) -> Option<Queue<'_>> {
        #[cfg(target_arch = "x86_64")]
        if self.displacements.is_empty() && self.sampling == Sampling::Trilinear && self.params.shading == Shading::None
        {
            let cell = CellLookup::for_dims(self.volume.dims());
            return Trilinear8::new(self.volume.data(), &cell).map(|sampler| Queue {
                sampler,
                q: [[0.0; QUEUE_ROOM]; 3],
                k: [0; QUEUE_ROOM],
                adds: [false; BATCH],
                len: 0,
            });
        }
        None
    }

    /// Queues sample `k` of `ray` (`adds`: see [`Queue::adds`]), compositing the queue once
    /// full; whether the ray is now opaque enough to stop.
    fn enqueue(
        &self,
        march: &mut March,
        ray: &SampleLine,
        k: u32,
        adds: bool,
        acc: &mut [f32; 4],
        depth: &mut f32,
    ) -> bool {
        let Some(queue) = &mut march.queue else { return false };
        let (q, at) = (ray.q(k), queue.len);
        for a in 0..3 {
            queue.q[a][at] = q[a];
        }
        (queue.k[at], queue.adds[at], queue.len) = (k, adds, at + 1);
        queue.len == BATCH && self.flush(march, acc, depth)
    }

    /// Queues samples `k..end` of `ray`, all adding, as [`Self::enqueue`] one by one
    /// would; whether the ray is now opaque enough to stop.
    fn enqueue_run(
        &self,
        march: &mut March,
        ray: &SampleLine,
        mut k: u32,
        end: u32,
        acc: &mut [f32; 4],
        depth: &mut f32,
    ) -> bool {
        while k < end {
            let Some(queue) = &mut march.queue else { return false };
            k += queue.push_run(ray, k, end);
            if queue.len == BATCH && self.flush(march, acc, depth) {
                return true;
            }
        }
        false
    }

    /// Reads and composites the queued samples as [`Self::composite`] would have one by
    /// one (the same bits: the same sampler lanes, lookups and order); whether the ray is
    /// now opaque enough to stop (the rest of the queue is dropped).
    pub(crate) fn flush(&self, march: &mut March, acc: &mut [f32; 4], depth: &mut f32) -> bool {
        let Some(queue) = &mut march.queue else { return false };
        let n = std::mem::take(&mut queue.len);
        let mut values = [0.0f32; BATCH];
        queue.sample(&mut values, n);
        let preintegrated = self.params.preintegrated;
        let (step, offset) = (self.params.step as f32, if preintegrated { 0.0 } else { 0.5 });
        let inside = queue.inside(self.volume.dims(), n);
        // Every entry looked up before any is composited, eight wide: independent loads
        // from a table larger than the core's cache, which the core then overlaps (one per
        // sample, each waited for, was costly: see docs/perf/journal.md#small-code-generation-fixes).
        let mut entries = [[0.0f32; 4]; BATCH];
        if preintegrated {
            let mut fronts = [0.0f32; BATCH];
            fronts[0] = march.front.unwrap_or(values[0]);
            fronts[1..].copy_from_slice(&values[..BATCH - 1]);
            queue.segments(&self.tables, &fronts, &values, &mut entries[..n]);
        } else {
            for i in 0..n {
                entries[i] = self.tables.sample_step(values[i]);
            }
        }
        for i in 0..n {
            let k = queue.k[i];
            let t = march.t0 + (k as f32 + offset) * step;
            let front_inside = if i == 0 { march.front.is_some() } else { inside[i - 1] };
            let adds = queue.adds[i] && inside[i] && (!preintegrated || (front_inside && k > 0));
            if adds && entries[i][3] > 1e-5 {
                // Unshaded: `add`'s shade is exactly 1.
                blend(acc, depth, entries[i], 1.0, if preintegrated { t - 0.5 * step } else { t });
            }
            if preintegrated {
                march.front = inside[i].then_some(values[i]);
            }
            if acc[3] >= self.params.early_termination as f32 {
                return true;
            }
        }
        false
    }

    /// The samples of `march` up to `t_out` inside `tet`.
    pub(crate) fn cross(&self, march: &mut March, tet: usize, t_out: f32, acc: &mut [f32; 4], depth: &mut f32) {
        let ray = self.samples_in(march, tet);
        let end = ray.end(march.k, t_out);
        if march.queue.is_some() {
            self.queue_crossing(march, &ray, self.visible[tet] != 0, end, acc, depth);
            return;
        }
        if self.visible[tet] == 0 {
            // Nothing to see here: only the segment coming in from the tet before (its front
            // there) adds anything; the last sample inside is kept, the next one's front.
            if march.k < end && self.params.preintegrated && march.front.is_some() {
                let value = self.value(&ray.q(march.k));
                if self.composite(&ray, march, value, acc, depth) {
                    return;
                }
            }
            if march.k < end {
                if self.params.preintegrated {
                    march.front = self.value(&ray.q(end - 1));
                }
                march.k = end;
            }
            return;
        }
        // Trilinear samples without displacement volumes lie on a line: read them in batches.
        let lanes = (self.displacements.is_empty() && self.sampling == Sampling::Trilinear)
            .then(|| Sampler::new(self.volume.data(), self.volume.dims()));
        let mut values = [0.0f32; BATCH];
        while march.k < end {
            let values = &mut values[..(end - march.k).min(BATCH as u32) as usize];
            if let Some(sampler) = &lanes {
                sampler.along(ray.base, ray.step, march.k as usize, values);
            }
            for value in values.iter() {
                let q = ray.q(march.k);
                let value = if lanes.is_some() { self.in_box(&q).then_some(*value) } else { self.value(&q) };
                if self.composite(&ray, march, value, acc, depth) {
                    return;
                }
            }
        }
    }

    /// Queues the samples of `march` before `end` in a tet (as [`Self::cross`] composites
    /// them: in one that is not `visible`, only the first, against the front, and the last,
    /// the next front).
    fn queue_crossing(
        &self,
        march: &mut March,
        ray: &SampleLine,
        visible: bool,
        end: u32,
        acc: &mut [f32; 4],
        depth: &mut f32,
    ) {
        let first = march.k;
        march.k = end.max(first);
        if first >= end {
            return;
        }
        if visible {
            self.enqueue_run(march, ray, first, end, acc, depth);
        } else if self.params.preintegrated && !self.enqueue(march, ray, first, true, acc, depth) && end - 1 > first {
            self.enqueue(march, ray, end - 1, false, acc, depth);
        }
    }

    /// Where the samples of `march` lie in `tet`'s source index space.
    fn samples_in(&self, march: &March, tet: usize) -> SampleLine {
        let step = self.params.step as f32;
        let offset = if self.params.preintegrated { 0.0 } else { 0.5 };
        let map = self.maps[tet];
        let first = march.t0 + offset * step;
        let base = apply(&map, &(march.o + march.d * first));
        let along = apply(&map, &(march.o + march.d * (first + step))) - base;
        SampleLine { base, step: along, map, t0: march.t0, dt: step, offset }
    }

    /// Composites sample `march.k` (its value, `None` outside the source) and moves past it;
    /// whether the ray is now opaque enough to stop.
    fn composite(
        &self,
        ray: &SampleLine,
        march: &mut March,
        value: Option<f32>,
        acc: &mut [f32; 4],
        depth: &mut f32,
    ) -> bool {
        let k = march.k;
        let t = ray.t(k);
        if self.params.preintegrated {
            if let (Some(front), Some(back), true) = (march.front, value, k > 0) {
                let middle = ray.base + ray.step * (k as f32 - 0.5);
                let e = self.tables.segment(front, back);
                self.add(acc, depth, e, &middle, &ray.map, &march.light, t - 0.5 * ray.dt);
            }
            march.front = value;
        } else if let Some(v) = value {
            self.add(acc, depth, self.tables.sample_step(v), &ray.q(k), &ray.map, &march.light, t);
        }
        march.k += 1;
        acc[3] >= self.params.early_termination as f32
    }

    /// Whether continuous index q lies in the voxel-centre box (within the edge tolerance).
    #[inline]
    fn in_box(&self, q: &V3) -> bool {
        let dims = self.volume.dims();
        (0..3).all(|a| q[a] >= -EDGE_TOLERANCE && q[a] <= (dims[a] - 1) as f32 + EDGE_TOLERANCE)
    }

    /// The shorter last segment, from the last sample to `t_end` (the ray leaves the mesh
    /// or meets a tool), inside `tet`.
    pub(crate) fn finish(&self, march: &mut March, tet: usize, t_end: f32, acc: &mut [f32; 4], depth: &mut f32) {
        if self.flush(march, acc, depth) {
            return;
        }
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

/// Adds premultiplied colour and α `e`, lit by `shade`, behind what the ray gathered; the
/// depth is where opacity first passes ½ (`t_mid`, the segment's middle).
#[inline(always)]
fn blend(acc: &mut [f32; 4], depth: &mut f32, e: [f32; 4], shade: f32, t_mid: f32) {
    let weight = 1.0 - acc[3];
    for c in 0..3 {
        acc[c] += weight * e[c] * shade;
    }
    acc[3] += weight * e[3];
    if depth.is_infinite() && acc[3] >= 0.5 {
        *depth = t_mid;
    }
}

impl Queue<'_> {
    /// Queues samples `k..end` of `ray` (adding) up to the queue's end: how many it took.
    /// Their positions are [`SampleLine::q`]'s bits (the same product and sum per lane).
    fn push_run(&mut self, ray: &SampleLine, k: u32, end: u32) -> u32 {
        let at = self.len;
        let take = (end - k).min((BATCH - at) as u32);
        #[cfg(target_arch = "x86_64")]
        // SAFETY: a `Trilinear8` (the queue's sampler) exists only where the CPU has AVX2.
        unsafe {
            self.push_run_avx2(ray, k, take)
        };
        #[cfg(not(target_arch = "x86_64"))]
        for i in 0..take {
            let q = ray.q(k + i);
            for a in 0..3 {
                self.q[a][at + i as usize] = q[a];
            }
            self.k[at + i as usize] = k + i;
        }
        self.adds[at..at + take as usize].fill(true);
        self.len = at + take as usize;
        take
    }

    /// [`Self::push_run`]'s positions and places, eight lanes a loop, each stored whole
    /// (the last group's spare lanes land in slots no one reads before they are written).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn push_run_avx2(&mut self, ray: &SampleLine, k: u32, take: u32) {
        use std::arch::x86_64::*;
        const LANES: usize = 8;
        let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        for g in 0..(take as usize).div_ceil(LANES) {
            let at = self.len + g * LANES;
            let places = _mm256_add_epi32(_mm256_set1_epi32((k as usize + g * LANES) as i32), lane);
            let along = _mm256_cvtepi32_ps(places);
            // SAFETY: at < BATCH, so at + 8 ≤ QUEUE_ROOM slots lie in each row.
            unsafe {
                for a in 0..3 {
                    let q =
                        _mm256_add_ps(_mm256_set1_ps(ray.base[a]), _mm256_mul_ps(_mm256_set1_ps(ray.step[a]), along));
                    _mm256_storeu_ps(self.q[a].as_mut_ptr().add(at), q);
                }
                _mm256_storeu_si256(self.k.as_mut_ptr().add(at).cast(), places);
            }
        }
    }

    /// `Tables::segment(fronts[i], backs[i])` into `out[i]`; both hold `BATCH` values.
    fn segments(&self, tables: &Tables, fronts: &[f32; BATCH], backs: &[f32; BATCH], out: &mut [[f32; 4]]) {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: a `Trilinear8` (the queue's sampler) exists only where the CPU has AVX2.
        unsafe {
            crate::volume::packet::segments_into(tables, fronts, backs, out)
        };
        #[cfg(not(target_arch = "x86_64"))]
        for ((entry, &front), &back) in out.iter_mut().zip(fronts).zip(backs) {
            *entry = tables.segment(front, back);
        }
    }

    /// Whether each of the first `n` queued points lies in the voxel-centre box of a
    /// source of `dims` samples: [`SourceLook::in_box`]'s comparisons, eight lanes at a
    /// time (false past `n`).
    fn inside(&self, dims: [usize; 3], n: usize) -> [bool; BATCH] {
        let top = dims.map(|d| (d - 1) as f32 + EDGE_TOLERANCE);
        #[cfg(target_arch = "x86_64")]
        // SAFETY: a `Trilinear8` (the queue's sampler) exists only where the CPU has AVX2.
        let inside = unsafe { self.inside_avx2(top) };
        #[cfg(not(target_arch = "x86_64"))]
        let inside: [bool; BATCH] =
            std::array::from_fn(|i| (0..3).all(|a| self.q[a][i] >= -EDGE_TOLERANCE && self.q[a][i] <= top[a]));
        std::array::from_fn(|i| i < n && inside[i])
    }

    /// [`Self::inside`] for the whole queue.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn inside_avx2(&self, top: [f32; 3]) -> [bool; BATCH] {
        use std::arch::x86_64::*;
        const LANES: usize = 8;
        let mut inside = [false; BATCH];
        for g in 0..BATCH / LANES {
            let mut all = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
            for (a, top) in top.iter().enumerate() {
                // SAFETY: g·8 + 8 ≤ BATCH floats lie in each axis's row.
                let q = unsafe { _mm256_loadu_ps(self.q[a].as_ptr().add(g * LANES)) };
                let low = _mm256_cmp_ps::<_CMP_GE_OQ>(q, _mm256_set1_ps(-EDGE_TOLERANCE));
                let high = _mm256_cmp_ps::<_CMP_LE_OQ>(q, _mm256_set1_ps(*top));
                all = _mm256_and_ps(all, _mm256_and_ps(low, high));
            }
            let mask = _mm256_movemask_ps(all);
            for (l, slot) in inside[g * LANES..][..LANES].iter_mut().enumerate() {
                *slot = mask >> l & 1 == 1;
            }
        }
        inside
    }

    /// The first `n` queued samples into `out` (and whatever the rest of their last
    /// eight lanes read).
    fn sample(&self, out: &mut [f32; BATCH], n: usize) {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: a `Trilinear8` exists only where the CPU has AVX2.
        unsafe {
            self.sample_avx2(out, n)
        };
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (out, n);
    }

    /// [`Self::sample`], eight lanes a loop, each stored whole: spare lanes read points
    /// queued before, or the origin (inside the clamps), and no one reads them back. A
    /// store of the first few lanes only was a `memcpy` call per loop.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn sample_avx2(&self, out: &mut [f32; BATCH], n: usize) {
        use std::arch::x86_64::{_mm256_loadu_ps, _mm256_storeu_ps};
        const LANES: usize = 8;
        for g in 0..n.min(BATCH).div_ceil(LANES) {
            // SAFETY: g·8 + 8 ≤ BATCH floats lie in each axis's row and in `out`.
            unsafe {
                let at = [0, 1, 2].map(|a| _mm256_loadu_ps(self.q[a].as_ptr().add(g * LANES)));
                _mm256_storeu_ps(out.as_mut_ptr().add(g * LANES), self.sampler.sample(at));
            }
        }
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;

    /// A run pushed eight lanes at a time fills the queue's slots with the positions and
    /// places one-by-one `SampleLine::q` gives, to the bit, from any queue length, and
    /// takes no more than the queue holds.
    #[test]
    fn a_pushed_run_holds_the_one_by_one_samples_bits() {
        let data = vec![0.0f32; 4 * 4 * 4];
        let cell = CellLookup::for_dims([4, 4, 4]);
        let Some(sampler) = Trilinear8::new(&data, &cell) else {
            assert!(!defvol_core::volume::lanes::lanes_available(), "AVX2 is here but no sampler was made");
            return;
        };
        let mut queue = Queue { sampler, q: [[0.0; QUEUE_ROOM]; 3], k: [0; QUEUE_ROOM], adds: [false; BATCH], len: 0 };
        let ray = SampleLine {
            base: V3::new(3.7, -1.23, 10.31),
            step: V3::new(0.371, 0.917, -0.113),
            map: [[0.0; 4]; 3],
            t0: 0.0,
            dt: 1.0,
            offset: 0.0,
        };
        for (len, k, end) in [(0, 0, 3), (0, 1000, 1016), (5, 77, 90), (13, 4, 40), (15, 9, 10), (2, 123_457, 123_470)]
        {
            queue.len = len;
            queue.adds = [false; BATCH];
            let take = queue.push_run(&ray, k, end);
            assert_eq!(take, (end - k).min((BATCH - len) as u32), "from {len} queued, samples {k}..{end}");
            assert_eq!(queue.len, len + take as usize);
            for i in 0..take as usize {
                let want = ray.q(k + i as u32);
                for a in 0..3 {
                    assert_eq!(queue.q[a][len + i].to_bits(), want[a].to_bits(), "sample {}, axis {a}", k + i as u32);
                }
                assert_eq!(queue.k[len + i], k + i as u32);
            }
            assert!(queue.adds[..len].iter().all(|&a| !a) && queue.adds[len..queue.len].iter().all(|&a| a));
        }
    }
}
