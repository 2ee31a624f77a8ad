//! Eight rays at once (AVX2, detected at run time) for the composite, unshaded picture:
//! the rays sit in the vector lanes instead of one ray's samples, so the table lookups and
//! the compositing run eight wide as the samples do. Each lane does `Caster::composite`'s
//! arithmetic in its order (unfused multiplies and adds, the same clamps and truncations)
//! and walks the macro cells by the same runs (`Caster::run_end`, per lane, as each run
//! ends), so a packet's pixels are the scalar loop's bits.

use std::arch::x86_64::*;

use nalgebra::Vector3;

use super::{segments, Caster, Clipped, Mode, Ray, Setup, Shading};
use crate::camera::Camera;
use crate::transfer::{Tables, LUT_SIZE, PREINTEGRATED_SIZE};
use defvol_core::volume::lanes::Trilinear8;

/// Rays in a packet.
pub(super) const LANES: usize = 8;

/// What a packet needs beyond the caster: the eight-point sampler.
pub(super) struct Packets<'a> {
    trilinear: Trilinear8<'a>,
}

impl<'a> Packets<'a> {
    /// Packets for `caster` where they give its pictures: composite, unshaded, and AVX2
    /// present with the volume inside the eight-point sampler's reach.
    pub(super) fn new(caster: &Caster<'a>) -> Option<Self> {
        let params = caster.params;
        if params.mode != Mode::Composite || params.shading != Shading::None {
            return None;
        }
        Trilinear8::new(caster.volume.data(), &caster.sampler.cell).map(|trilinear| Self { trilinear })
    }

    /// The pixels (px0 + l, py) for l < `count` (at most [`LANES`]): colour and depth, as
    /// `Caster::cast` gives them.
    pub(super) fn cast(
        &self,
        caster: &Caster,
        camera: &Camera,
        (px0, py): (usize, usize),
        count: usize,
    ) -> [([f32; 4], f32); LANES] {
        let mut pixels = [([0.0; 4], f32::INFINITY); LANES];
        let mut clipped: [Option<Clipped>; LANES] = Default::default();
        for (l, lane) in clipped.iter_mut().enumerate().take(count) {
            let (origin, direction) = camera.ray(px0 + l, py);
            match caster.clip_ray(&origin, &direction) {
                Setup::Missed(bg, behind) => pixels[l] = (bg, behind),
                Setup::Inside(c) => *lane = Some(c),
            }
        }
        let step = caster.params.step as f32;
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
        // SAFETY: `Packets` exist only where the CPU has AVX2.
        let terminated = unsafe { self.composite(caster, &mut rays, &clipped) };
        for l in 0..count {
            let (Some(ray), Some(c)) = (&mut rays[l], &clipped[l]) else { continue };
            let (full, remainder) = segments(c.t_near, c.t_far, step);
            if !terminated[l] && remainder > 1e-6 * step {
                ray.last_segment(caster, full, remainder, &|_: &Vector3<f32>| 1.0);
            }
            pixels[l] = ray.over(c.bg, c.behind);
        }
        pixels
    }

    /// The full segments of the packet's rays, front to back, into each ray's `acc`,
    /// `depth` and `front`; which rays terminated.
    #[target_feature(enable = "avx2")]
    fn composite(
        &self,
        caster: &Caster,
        rays: &mut [Option<Ray>; LANES],
        clipped: &[Option<Clipped>; LANES],
    ) -> [bool; LANES] {
        let params = caster.params;
        let preintegrated = params.preintegrated;
        let step = params.step as f32;
        let full = clipped.each_ref().map(|c| c.as_ref().map_or(0, |c| segments(c.t_near, c.t_far, step).0));
        let (mut k, mut end) = ([0usize; LANES], [0usize; LANES]);
        let mut live = rays.each_ref().map(Option::is_some);
        let mut terminated = [false; LANES];
        let mut lanes = Lanes::new(rays, if preintegrated { 1.0 } else { 0.5 }, params.early_termination as f32);
        loop {
            // Lanes at the end of a run start their next one, or are done.
            let mut fronts = [0.0f32; LANES];
            for l in 0..LANES {
                let Some(ray) = rays[l].as_mut().filter(|_| live[l]) else { continue };
                if k[l] >= end[l] {
                    if k[l] < full[l] {
                        end[l] = caster.run_end(ray, &mut k[l], full[l]);
                    }
                    if k[l] >= end[l] {
                        live[l] = false;
                        continue;
                    }
                }
                if preintegrated {
                    let front = ray.front.unwrap_or_else(|| caster.front(ray, k[l]));
                    (ray.front, fronts[l]) = (Some(front), front);
                }
            }
            if !live.contains(&true) {
                break;
            }
            let (ks, stopped, backs) = lanes.runs(self, caster.tables, preintegrated, (k, end, live), fronts);
            for l in 0..LANES {
                let Some(ray) = rays[l].as_mut().filter(|_| live[l]) else { continue };
                if stopped[l] {
                    (terminated[l], live[l]) = (true, false);
                } else {
                    k[l] = ks[l];
                    if preintegrated {
                        ray.front = Some(backs[l]);
                    }
                }
            }
        }
        lanes.store(rays);
        terminated
    }
}

/// The packet's rays in the vector lanes: where their samples are, and what they gathered.
struct Lanes {
    /// Each ray's first sample (at `offset` steps from its t_near) and the step between
    /// samples, as `Ray::run` hands them to the sampler.
    base: [__m256; 3],
    delta: [__m256; 3],
    t_near: __m256,
    step: __m256,
    termination: __m256,
    acc: [__m256; 4],
    depth: __m256,
}

impl Lanes {
    #[target_feature(enable = "avx2")]
    fn new(rays: &[Option<Ray>; LANES], offset: f32, termination: f32) -> Self {
        let (mut base, mut delta) = ([[0.0f32; LANES]; 3], [[0.0f32; LANES]; 3]);
        let (mut t_near, mut step) = ([0.0f32; LANES], 1.0);
        for (l, ray) in rays.iter().enumerate() {
            let Some(ray) = ray else { continue };
            let (b, s) = (ray.o + ray.d * (ray.t_near + offset * ray.step), ray.d * ray.step);
            for a in 0..3 {
                (base[a][l], delta[a][l]) = (b[a], s[a]);
            }
            (t_near[l], step) = (ray.t_near, ray.step);
        }
        Self {
            base: base.map(|v| load(v)),
            delta: delta.map(|v| load(v)),
            t_near: load(t_near),
            step: _mm256_set1_ps(step),
            termination: _mm256_set1_ps(termination),
            acc: [_mm256_setzero_ps(); 4],
            depth: _mm256_set1_ps(f32::INFINITY),
        }
    }

    /// Segments k, k + 1, ... of the live lanes, all a step at a time, until some lane's
    /// run (up to its `end`) is over or every lane has terminated. Returns each lane's next
    /// segment, whether it terminated, and the scalar at its last segment's back.
    #[target_feature(enable = "avx2")]
    fn runs(
        &mut self,
        packets: &Packets,
        tables: &Tables,
        preintegrated: bool,
        (k, end, live): ([usize; LANES], [usize; LANES], [bool; LANES]),
        fronts: [f32; LANES],
    ) -> ([usize; LANES], [bool; LANES], [f32; LANES]) {
        let mut kv = load_i32(k.map(|k| k as i32));
        let end = load_i32(end.map(|e| e as i32));
        let mut running = _mm256_castsi256_ps(load_i32(live.map(|l| -i32::from(l))));
        let mut stopped = _mm256_setzero_ps();
        let mut front = load(fronts);
        let (tiny, one, half, infinity) =
            (_mm256_set1_ps(1e-5), _mm256_set1_ps(1.0), _mm256_set1_ps(0.5), _mm256_set1_ps(f32::INFINITY));
        loop {
            let kf = _mm256_cvtepi32_ps(kv);
            let at = [0, 1, 2].map(|a| _mm256_add_ps(self.base[a], _mm256_mul_ps(self.delta[a], kf)));
            let value = packets.trilinear.sample(at);
            let color = if preintegrated {
                let color = segment8(tables, front, value);
                front = value;
                color
            } else {
                interpolate8(tables, &tables.stepped, value)
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
            if running_bits == 0 || _mm256_movemask_ps(within) != running_bits {
                break;
            }
        }
        let mut ks = [0i32; LANES];
        // SAFETY: ks holds eight i32.
        unsafe { _mm256_storeu_si256(ks.as_mut_ptr().cast(), kv) };
        let stopped = _mm256_movemask_ps(stopped);
        (ks.map(|k| k as usize), std::array::from_fn(|l| stopped >> l & 1 == 1), store(front))
    }

    /// Each ray's colour, α and depth from the lanes.
    #[target_feature(enable = "avx2")]
    fn store(&self, rays: &mut [Option<Ray>; LANES]) {
        let (acc, depth) = (self.acc.map(|v| store(v)), store(self.depth));
        for (l, ray) in rays.iter_mut().enumerate() {
            if let Some(ray) = ray {
                (ray.acc, ray.depth) = ([acc[0][l], acc[1][l], acc[2][l], acc[3][l]], depth[l]);
            }
        }
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

/// `a + (b - a)·f`, unfused, as `lerp4` takes it.
#[inline]
#[target_feature(enable = "avx2")]
fn lerp8(a: __m256, b: __m256, f: __m256) -> __m256 {
    _mm256_add_ps(a, _mm256_mul_ps(_mm256_sub_ps(b, a), f))
}

/// `x.clamp(0, top)` for finite x.
#[inline]
#[target_feature(enable = "avx2")]
fn clamp8(x: __m256, top: f32) -> __m256 {
    _mm256_min_ps(_mm256_max_ps(x, _mm256_setzero_ps()), _mm256_set1_ps(top))
}

/// The floats at `ptr` + `at` (in floats), eight lanes.
///
/// # Safety
/// Every `ptr + at` must lie in one allocation.
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn gather(ptr: *const f32, at: __m256i) -> __m256 {
    // SAFETY: the caller's.
    unsafe { _mm256_i32gather_ps::<4>(ptr, at) }
}

/// `Tables::interpolate` in the lanes: `table` (`LUT_SIZE` entries over [lo, hi]) at `s`.
#[inline]
#[target_feature(enable = "avx2")]
fn interpolate8(tables: &Tables, table: &[[f32; 4]], s: __m256) -> [__m256; 4] {
    assert_eq!(table.len(), LUT_SIZE);
    let x = _mm256_mul_ps(_mm256_sub_ps(s, _mm256_set1_ps(tables.lo)), _mm256_set1_ps(tables.lut_scale));
    let x = clamp8(x, (LUT_SIZE - 1) as f32);
    let i = _mm256_min_epi32(_mm256_cvttps_epi32(x), _mm256_set1_epi32(LUT_SIZE as i32 - 2));
    let f = _mm256_sub_ps(x, _mm256_cvtepi32_ps(i));
    let at = _mm256_slli_epi32::<2>(i);
    let ptr = table.as_ptr().cast::<f32>();
    // SAFETY: 0 ≤ i ≤ LUT_SIZE - 2, so entries i and i + 1 lie in the table.
    [0, 1, 2, 3].map(|c| unsafe { lerp8(gather(ptr.add(c), at), gather(ptr.add(4 + c), at), f) })
}

/// `Tables::segment` in the lanes: the pre-integrated segments from `front` to `back`.
#[inline]
#[target_feature(enable = "avx2")]
fn segment8(tables: &Tables, front: __m256, back: __m256) -> [__m256; 4] {
    let n = PREINTEGRATED_SIZE;
    assert_eq!(tables.preintegrated.len(), n * n);
    let (lo, scale) = (_mm256_set1_ps(tables.pre_lo), _mm256_set1_ps(tables.pre_scale));
    let level = |s| clamp8(_mm256_mul_ps(_mm256_sub_ps(s, lo), scale), (n - 1) as f32);
    let (x, y) = (level(front), level(back));
    let highest = _mm256_set1_epi32(n as i32 - 2);
    let (i, j) = (_mm256_min_epi32(_mm256_cvttps_epi32(x), highest), _mm256_min_epi32(_mm256_cvttps_epi32(y), highest));
    let (fx, fy) = (_mm256_sub_ps(x, _mm256_cvtepi32_ps(i)), _mm256_sub_ps(y, _mm256_cvtepi32_ps(j)));
    let at = _mm256_slli_epi32::<2>(_mm256_add_epi32(_mm256_mullo_epi32(i, _mm256_set1_epi32(n as i32)), j));
    let ptr = tables.preintegrated.as_ptr().cast::<f32>();
    let row = 4 * n;
    [0, 1, 2, 3].map(|c| {
        // SAFETY: 0 ≤ i, j ≤ n - 2, so entries (i, j) to (i + 1, j + 1) lie in the table.
        let g = |o: usize| unsafe { gather(ptr.add(o + c), at) };
        lerp8(lerp8(g(0), g(4), fy), lerp8(g(row), g(row + 4), fy), fx)
    })
}

#[cfg(test)]
mod tests {
    use nalgebra::{Matrix3, Point3, Vector3};

    use crate::camera::{Camera, Projection};
    use crate::transfer::TransferFunction;
    use crate::volume::{nearest_tool, RaycastParams, Shading, ToolPicture, VolumeRaycaster};
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

    /// Every pixel of eight-ray packets is the one-ray caster's, colour and depth to the
    /// bit: point-sampled and pre-integrated, with and without empty-space skipping, early
    /// termination often and rarely reached, a tool in view, a row not a multiple of eight,
    /// over the phantom (tissue everywhere) and a ball in air (rays jumping invisible cells).
    #[test]
    fn packets_give_the_one_ray_casters_bits() {
        let tf = TransferFunction::preset("ct_soft_tissue").unwrap();
        let (mut compared, mut tissue, mut tool_hits, mut jumped) = (0usize, 0usize, 0usize, false);
        for volume in [phantom::phantom([64, 40, 31], 4.0).unwrap(), ball_in_air()] {
            let camera = oblique(&volume, (45, 37));
            let (lo, hi) = volume.bounds();
            let tip = ((lo + hi) / 2.0 - (hi - lo).component_mul(&Vector3::new(0.1, 0.45, -0.1))).into();
            let tool = ToolPicture { tip, tail: [tip[0], tip[1], hi.z + 10.0], radius: 3.0, color: [0.9, 0.8, 0.1] };
            for (preintegrated, empty_space_skipping, early_termination, tools) in [
                (false, true, 0.999, vec![]),
                (true, true, 0.999, vec![]),
                (false, false, 0.9, vec![tool]),
                (true, true, 0.9, vec![tool]),
                (true, false, 0.999, vec![]),
            ] {
                let params = RaycastParams {
                    step: 0.7,
                    preintegrated,
                    shading: Shading::None,
                    empty_space_skipping,
                    early_termination,
                    background: [0.2, 0.3, 0.4, 1.0],
                    tools,
                    ..Default::default()
                };
                let raycaster = VolumeRaycaster::new(&volume, &tf, &params).unwrap();
                let caster = raycaster.caster();
                let Some(packets) = caster.packets.as_ref() else {
                    eprintln!("skipped: no AVX2 on this CPU");
                    return;
                };
                jumped |= caster
                    .cells
                    .is_some_and(|cells| 2 * cells.visible.iter().filter(|v| !**v).count() > cells.visible.len());
                for py in 0..camera.height {
                    for px0 in (0..camera.width).step_by(super::LANES) {
                        let count = (camera.width - px0).min(super::LANES);
                        let pixels = packets.cast(&caster, &camera, (px0, py), count);
                        for (l, (color, depth)) in pixels.iter().take(count).enumerate() {
                            let (origin, direction) = camera.ray(px0 + l, py);
                            let (want, want_depth) = caster.cast(&origin, &direction);
                            assert_eq!(
                                (color.map(f32::to_bits), depth.to_bits()),
                                (want.map(f32::to_bits), want_depth.to_bits()),
                                "pixel ({}, {py}), {params:?}: {color:?} at {depth} against {want:?} at {want_depth}",
                                px0 + l
                            );
                            tissue += usize::from(depth.is_finite());
                            let light = -direction;
                            tool_hits += usize::from(
                                nearest_tool(&params.tools, params.ambient, &origin, &direction, &light).is_some(),
                            );
                            compared += 1;
                        }
                    }
                }
            }
        }
        assert_eq!(compared, 2 * 5 * 45 * 37);
        // Both scenes show tissue and the tool; the ball's box is mostly invisible cells.
        assert!(jumped && tissue > 2000 && tool_hits > 100, "{jumped} {tissue} {tool_hits}");
    }
}
