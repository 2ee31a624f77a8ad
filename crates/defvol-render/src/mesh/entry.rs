//! Where a ray enters the mesh: the nearest boundary face of its tile that it crosses.
//! A tile's faces are laid out once in lanes (each face's plane and its tet's three other
//! planes, a float per face per channel) for the tile's 64 rays, which test them eight at
//! a time where the CPU has AVX2: the same arithmetic in the same order as one face at a
//! time (unfused, the same comparisons), so the same hit.

use super::field::V3;
use super::geometry::TetGeometry;

/// A boundary face a ray crosses, `t` along it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Hit {
    pub(crate) t: f32,
    pub(crate) tet: u32,
    pub(crate) face: u32,
    /// The face looks toward the ray (an entry), not away (an exit).
    pub(crate) front: bool,
}

/// What an entry search asks: the ray (anchored origin, unit direction), the distance
/// along it beyond which hits count, whether only front faces do, and how far off a
/// face's other planes a hit may lie.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Search<'a> {
    pub(crate) o: &'a V3,
    pub(crate) d: &'a V3,
    pub(crate) after: f32,
    pub(crate) fronts_only: bool,
    pub(crate) tolerance: f32,
}

/// Faces a vector holds.
const LANES: usize = 8;

/// One tile's boundary faces in lanes.
pub(crate) struct TileFaces {
    /// Face ids (tet · 4 + face), in the bins' order.
    ids: Vec<u32>,
    /// Faces rounded up to whole groups of eight; spare faces have zero planes (no hit).
    padded: usize,
    /// Channel c of plane slot s of face f at `(4 s + c) · padded + f`: slot 0 the face's
    /// own plane, slots 1-3 its tet's other planes in order.
    planes: Vec<f32>,
}

impl TileFaces {
    pub(crate) fn new(faces: &[u32], geometry: &[TetGeometry]) -> Self {
        let padded = faces.len().div_ceil(LANES) * LANES;
        let mut planes = vec![0.0f32; 16 * padded];
        for (f, &id) in faces.iter().enumerate() {
            let tet_planes = &geometry[(id >> 2) as usize].planes;
            let own = (id & 3) as usize;
            let slots = std::iter::once(own).chain((0..4).filter(|&j| j != own));
            for (slot, j) in slots.enumerate() {
                for (c, value) in tet_planes[j].iter().enumerate() {
                    planes[(4 * slot + c) * padded + f] = *value;
                }
            }
        }
        Self { ids: faces.to_vec(), padded, planes }
    }

    /// Channel `c` of plane slot `slot` of face `f`.
    #[inline]
    fn at(&self, slot: usize, c: usize, f: usize) -> f32 {
        self.planes[(4 * slot + c) * self.padded + f]
    }

    fn hit(&self, f: usize, t: f32, front: bool) -> Hit {
        let id = self.ids[f];
        Hit { t, tet: id >> 2, face: id & 3, front }
    }

    /// The nearest face crossed beyond `after` (only front-facing ones when `fronts_only`):
    /// the hit on the face's plane counts when it lies within `tolerance` of the tet's
    /// three other planes; on equal distances the first face in the bin's order.
    /// Also: the farthest crossing of a front-facing face's plane beyond `after`, a bound
    /// on where the ray could enter again (beyond it, no rescan is needed).
    pub(crate) fn nearest_hit(&self, search: Search) -> (Option<Hit>, f32) {
        #[cfg(target_arch = "x86_64")]
        if defvol_core::volume::lanes::lanes_available() {
            // SAFETY: AVX2 is present.
            return unsafe { self.nearest_hit_avx2(search) };
        }
        self.nearest_hit_one_by_one(search)
    }

    /// [`Self::nearest_hit`] one face at a time.
    pub(crate) fn nearest_hit_one_by_one(&self, search: Search) -> (Option<Hit>, f32) {
        let Search { o, d, after, fronts_only, tolerance } = search;
        let mut best: Option<Hit> = None;
        let mut fronts_until = f32::NEG_INFINITY;
        for f in 0..self.ids.len() {
            let q = |slot: usize| [0, 1, 2, 3].map(|c| self.at(slot, c, f));
            let plane = q(0);
            let denom = plane[0] * d.x + plane[1] * d.y + plane[2] * d.z;
            let t = (plane[3] - (plane[0] * o.x + plane[1] * o.y + plane[2] * o.z)) / denom;
            if denom == 0.0 || t <= after || t.is_nan() {
                continue;
            }
            if denom < 0.0 {
                fronts_until = fronts_until.max(t);
            } else if fronts_only {
                continue;
            }
            if best.is_some_and(|b| t >= b.t) {
                continue;
            }
            let p = o + d * t;
            let on_face = (1..4).all(|slot| {
                let q = q(slot);
                q[0] * p.x + q[1] * p.y + q[2] * p.z - q[3] <= tolerance
            });
            if on_face {
                best = Some(self.hit(f, t, denom < 0.0));
            }
        }
        (best, fronts_until)
    }

    /// [`Self::nearest_hit`] eight faces at a time.
    ///
    /// # Safety
    /// AVX2 must be present.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn nearest_hit_avx2(&self, search: Search) -> (Option<Hit>, f32) {
        use std::arch::x86_64::*;
        let Search { o, d, after, fronts_only, tolerance } = search;
        let [ox, oy, oz, dx, dy, dz] = [o.x, o.y, o.z, d.x, d.y, d.z].map(|v| _mm256_set1_ps(v));
        let (zero, after_v, tolerance_v) = (_mm256_setzero_ps(), _mm256_set1_ps(after), _mm256_set1_ps(tolerance));
        let backs_count = if fronts_only { _mm256_setzero_ps() } else { _mm256_castsi256_ps(_mm256_set1_epi32(-1)) };
        let dot = |a: [__m256; 3], b: [__m256; 3]| {
            _mm256_add_ps(
                _mm256_add_ps(_mm256_mul_ps(a[0], b[0]), _mm256_mul_ps(a[1], b[1])),
                _mm256_mul_ps(a[2], b[2]),
            )
        };
        let mut fronts_until = _mm256_set1_ps(f32::NEG_INFINITY);
        let mut best: Option<Hit> = None;
        for group in 0..self.padded / LANES {
            // SAFETY: each channel holds `padded` floats, whole groups of eight.
            let q = |slot: usize| {
                [0, 1, 2, 3].map(|c| unsafe {
                    _mm256_loadu_ps(self.planes.as_ptr().add((4 * slot + c) * self.padded + group * LANES))
                })
            };
            let plane = q(0);
            let normal = [plane[0], plane[1], plane[2]];
            let denom = dot(normal, [dx, dy, dz]);
            let t = _mm256_div_ps(_mm256_sub_ps(plane[3], dot(normal, [ox, oy, oz])), denom);
            // Ordered comparisons: false where t is NaN, as the one-face test skips it.
            let valid =
                _mm256_and_ps(_mm256_cmp_ps::<_CMP_NEQ_OQ>(denom, zero), _mm256_cmp_ps::<_CMP_GT_OQ>(t, after_v));
            let front = _mm256_and_ps(valid, _mm256_cmp_ps::<_CMP_LT_OQ>(denom, zero));
            fronts_until = _mm256_blendv_ps(fronts_until, _mm256_max_ps(fronts_until, t), front);
            let mut hits = _mm256_and_ps(valid, _mm256_or_ps(front, backs_count));
            let p = [
                _mm256_add_ps(ox, _mm256_mul_ps(dx, t)),
                _mm256_add_ps(oy, _mm256_mul_ps(dy, t)),
                _mm256_add_ps(oz, _mm256_mul_ps(dz, t)),
            ];
            for slot in 1..4 {
                let q = q(slot);
                let distance = _mm256_sub_ps(dot([q[0], q[1], q[2]], p), q[3]);
                hits = _mm256_and_ps(hits, _mm256_cmp_ps::<_CMP_LE_OQ>(distance, tolerance_v));
            }
            let mut mask = _mm256_movemask_ps(hits) as u32;
            if mask == 0 {
                continue;
            }
            let mut ts = [0.0f32; LANES];
            // SAFETY: ts holds eight floats.
            unsafe { _mm256_storeu_ps(ts.as_mut_ptr(), t) };
            let fronts = _mm256_movemask_ps(front) as u32;
            while mask != 0 {
                let lane = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                if best.is_none_or(|b| ts[lane] < b.t) {
                    best = Some(self.hit(group * LANES + lane, ts[lane], fronts >> lane & 1 == 1));
                }
            }
        }
        let mut lanes = [0.0f32; LANES];
        // SAFETY: lanes holds eight floats.
        unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), fronts_until) };
        (best, lanes.into_iter().fold(f32::NEG_INFINITY, f32::max))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::geometry::tet_geometry_f32;
    use defvol_core::mesh::generate::{lattice, CellSplit};
    use defvol_core::mesh::TetMesh;
    use nalgebra::{Rotation3, Vector3};

    /// A turned lattice's boundary faces (both orientations, so rays meet entries and
    /// exits) with their tets' geometry.
    fn boundary(mesh: &TetMesh) -> (Vec<u32>, Vec<TetGeometry>) {
        let turn = Rotation3::from_euler_angles(0.3, -0.2, 0.5);
        let geometry: Vec<TetGeometry> = mesh
            .tets()
            .iter()
            .map(|tet| {
                let x = tet.map(|i| (turn * mesh.nodes()[i as usize]).cast::<f32>());
                tet_geometry_f32(&x, &[0.0; 4])
            })
            .collect();
        let faces = mesh
            .neighbours()
            .iter()
            .enumerate()
            .flat_map(|(t, n)| (0..4).filter(move |&k| n[k] < 0).map(move |k| (t * 4 + k) as u32))
            .collect();
        (faces, geometry)
    }

    /// Eight faces at a time find the one-face loop's hit (tet, face, distance to the bit,
    /// side) and bound on re-entry, over rays from outside and inside a turned lattice
    /// crossing bins of 1 to 200 faces, with and without back faces, from several starts.
    #[test]
    fn eight_faces_at_a_time_find_the_one_face_loops_hit() {
        if !defvol_core::volume::lanes::lanes_available() {
            eprintln!("skipped: no AVX2 on this CPU");
            return;
        }
        let mesh = lattice(Vector3::zeros(), Vector3::new(10.0, 8.0, 6.0), [5, 4, 3], CellSplit::Five).unwrap();
        let (faces, geometry) = boundary(&mesh);
        let (mut compared, mut hits, mut fronts, mut backs) = (0, 0, 0, 0);
        for count in [1, 7, 8, 9, 40, 200] {
            let bin = TileFaces::new(&faces[..count.min(faces.len())], &geometry);
            for r in 0..200 {
                let u = r as f32;
                let o = V3::new(5.0, 4.0, 3.0)
                    + if r % 3 == 0 {
                        V3::zeros()
                    } else {
                        V3::new(20.0 * (u * 0.7).sin(), 20.0 * (u * 1.3).cos(), 9.0)
                    };
                let aim = V3::new(10.0 * (u * 0.37).fract(), 8.0 * (u * 0.61).fract(), 6.0 * (u * 0.83).fract());
                let d = (aim - o).try_normalize(1e-6).unwrap_or(V3::x());
                for (after, fronts_only) in [(0.0, false), (0.0, true), (3.0, false), (-1.0, true)] {
                    // SAFETY: AVX2 is present (checked above).
                    let search = Search { o: &o, d: &d, after, fronts_only, tolerance: 1e-4 };
                    let lanes = unsafe { bin.nearest_hit_avx2(search) };
                    let one = bin.nearest_hit_one_by_one(search);
                    let key = |(hit, until): (Option<Hit>, f32)| {
                        (hit.map(|h| (h.tet, h.face, h.t.to_bits(), h.front)), until)
                    };
                    assert_eq!(
                        key(lanes),
                        key(one),
                        "{count} faces, ray {r}, after {after}, fronts only {fronts_only}"
                    );
                    compared += 1;
                    if let Some(h) = one.0 {
                        hits += 1;
                        fronts += usize::from(h.front);
                        backs += usize::from(!h.front);
                    }
                }
            }
        }
        assert!(
            compared == 6 * 800 && hits > 600 && fronts > 300 && backs > 200,
            "{hits} hits: {fronts} in, {backs} out"
        );
    }
}
