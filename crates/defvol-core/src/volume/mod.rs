//! Voxel volumes: a regular grid with ITK's geometry (values at voxel centres,
//! voxel (i,j,k) at `origin + direction · (i·sx, j·sy, k·sz)`), samples stored x-fastest as f32.

pub mod bspline;
pub mod lanes;
pub mod phantom;

use std::sync::OnceLock;

use nalgebra::{Matrix3, Vector3};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum VolumeError {
    #[error("{file}: dimension {axis} is {dim}; every dimension must be at least 1")]
    ZeroDim { file: String, axis: usize, dim: usize },
    #[error("{file}: spacing {spacing:?} must be finite and positive on every axis")]
    BadSpacing { file: String, spacing: [f64; 3] },
    #[error("{file}: origin {origin:?} is not finite")]
    BadOrigin { file: String, origin: [f64; 3] },
    #[error("{file}: direction matrix is not a finite rotation (|det| = {det})")]
    BadDirection { file: String, det: f64 },
    #[error("{file}: the direction matrix is sheared or scaled (|DᵀD - I| = {deviation:.2e}); a voxel grid's axes must be orthonormal")]
    ShearedDirection { file: String, deviation: f64 },
    #[error("{file}: {got} samples for dims {dims:?} ({expected} expected)")]
    SampleCount { file: String, got: usize, expected: usize, dims: [usize; 3] },
    #[error("{file}: sample {index} (voxel {voxel:?}) is not finite")]
    NonFiniteSample { file: String, index: usize, voxel: [usize; 3] },
    #[error("{file}: dims {dims:?} hold more than {max} voxels, the most the samplers address (32-bit offsets)")]
    TooManyVoxels { file: String, dims: [usize; 3], max: usize },
}

/// The most voxels a volume holds: the samplers (the scalar loops, the vector lanes and
/// the GPU's indices) address a voxel by a 32-bit offset from the first.
pub const MAX_VOXELS: usize = i32::MAX as usize;

/// A voxel lattice: dims, spacing, origin and direction, ITK's convention.
#[derive(Debug, Clone, PartialEq)]
pub struct Grid {
    pub dims: [usize; 3],
    pub spacing: [f64; 3],
    pub origin: [f64; 3],
    pub direction: Matrix3<f64>,
}

impl Grid {
    /// Its voxels, saturating at `usize::MAX` (a runaway deformation's box can count more;
    /// size checks then refuse it).
    pub fn len(&self) -> usize {
        self.dims.iter().fold(1usize, |n, &d| n.saturating_mul(d))
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    pub fn world_from_index(&self, ijk: Vector3<f64>) -> Vector3<f64> {
        Vector3::from(self.origin) + self.direction * ijk.component_mul(&Vector3::from(self.spacing))
    }
    pub fn index_from_world(&self, p: Vector3<f64>) -> Vector3<f64> {
        (self.direction.transpose() * (p - Vector3::from(self.origin))).component_div(&Vector3::from(self.spacing))
    }
    /// Continuous indices of `points` in f32, padded to four as the GPU reads them.
    pub fn indices_f32(&self, points: &[Vector3<f64>]) -> Vec<[f32; 4]> {
        points
            .iter()
            .map(|p| {
                let q = self.index_from_world(*p);
                [q.x as f32, q.y as f32, q.z as f32, 0.0]
            })
            .collect()
    }
    /// The affine map from this grid's continuous index to `other`'s: (matrix, offset).
    pub fn index_map_to(&self, other: &Grid) -> (Matrix3<f64>, Vector3<f64>) {
        let world_from_index = self.direction * Matrix3::from_diagonal(&Vector3::from(self.spacing));
        let other_from_world =
            Matrix3::from_diagonal(&Vector3::from(other.spacing).map(|s| 1.0 / s)) * other.direction.transpose();
        (
            other_from_world * world_from_index,
            other_from_world * (Vector3::from(self.origin) - Vector3::from(other.origin)),
        )
    }
}

/// A scalar voxel volume in file units (millimetres for medical formats).
#[derive(Debug, Clone)]
pub struct Volume {
    dims: [usize; 3],
    spacing: [f64; 3],
    origin: [f64; 3],
    direction: Matrix3<f64>,
    data: Vec<f32>,
    /// The samples in bricks for the eight-lane samplers, made on first use.
    bricks: OnceLock<Option<lanes::Bricks>>,
}

/// Geometry and samples: the bricked copy is derived from them.
impl PartialEq for Volume {
    fn eq(&self, other: &Self) -> bool {
        (self.dims, self.spacing, self.origin, self.direction)
            == (other.dims, other.spacing, other.origin, other.direction)
            && self.data == other.data
    }
}

impl Volume {
    /// Validates the geometry and the samples; `source` names the file for errors.
    pub fn new(
        dims: [usize; 3],
        spacing: [f64; 3],
        origin: [f64; 3],
        direction: Matrix3<f64>,
        data: Vec<f32>,
        source: &str,
    ) -> Result<Self, VolumeError> {
        let src = || source.to_owned();
        if let Some(axis) = dims.iter().position(|d| *d == 0) {
            return Err(VolumeError::ZeroDim { file: src(), axis, dim: 0 });
        }
        if !spacing.iter().all(|s| s.is_finite() && *s > 0.0) {
            return Err(VolumeError::BadSpacing { file: src(), spacing });
        }
        if !origin.iter().all(|o| o.is_finite()) {
            return Err(VolumeError::BadOrigin { file: src(), origin });
        }
        let det = direction.determinant();
        if !det.is_finite() || (det.abs() - 1.0).abs() > 1e-3 {
            return Err(VolumeError::BadDirection { file: src(), det });
        }
        // Its transpose is used as its inverse: it must be a rotation (or a reflection),
        // to the precision files print it with.
        let deviation = (direction.transpose() * direction - Matrix3::identity()).norm();
        if deviation > 1e-4 {
            return Err(VolumeError::ShearedDirection { file: src(), deviation });
        }
        let expected = match dims.iter().try_fold(1usize, |n, &d| n.checked_mul(d)) {
            Some(n) if n <= MAX_VOXELS => n,
            _ => return Err(VolumeError::TooManyVoxels { file: src(), dims, max: MAX_VOXELS }),
        };
        if data.len() != expected {
            return Err(VolumeError::SampleCount { file: src(), got: data.len(), expected, dims });
        }
        if let Some(index) = data.iter().position(|v| !v.is_finite()) {
            let voxel = [index % dims[0], (index / dims[0]) % dims[1], index / (dims[0] * dims[1])];
            return Err(VolumeError::NonFiniteSample { file: src(), index, voxel });
        }
        Ok(Self { dims, spacing, origin, direction, data, bricks: OnceLock::new() })
    }

    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }
    pub fn spacing(&self) -> [f64; 3] {
        self.spacing
    }
    pub fn origin(&self) -> [f64; 3] {
        self.origin
    }
    pub fn direction(&self) -> &Matrix3<f64> {
        &self.direction
    }
    pub fn data(&self) -> &[f32] {
        &self.data
    }
    /// The samples in place, for a stage that rewrites them (the warp's host copy); what it
    /// writes must stay finite, as `new` checks.
    pub fn data_mut(&mut self) -> &mut [f32] {
        self.bricks = OnceLock::new();
        &mut self.data
    }
    /// The samples in bricks ([`lanes::Bricks`]), made on the first call (about 1.15x the
    /// samples' memory, half that in 16-bit fixed point, kept while the volume lives);
    /// none where the CPU has no lanes.
    pub fn bricks(&self) -> Option<&lanes::Bricks> {
        self.bricks.get_or_init(|| lanes::Bricks::new(&self.data, self.dims)).as_ref()
    }
    pub fn len(&self) -> usize {
        self.data.len()
    }
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// The volume's lattice (geometry without samples).
    pub fn grid(&self) -> Grid {
        Grid { dims: self.dims, spacing: self.spacing, origin: self.origin, direction: self.direction }
    }

    /// Samples on a grid's lattice.
    pub fn from_grid(grid: &Grid, data: Vec<f32>, source: &str) -> Result<Self, VolumeError> {
        Self::new(grid.dims, grid.spacing, grid.origin, grid.direction, data, source)
    }

    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }

    /// Physical position of voxel (i, j, k) (continuous indices allowed).
    pub fn world_from_index(&self, ijk: Vector3<f64>) -> Vector3<f64> {
        Vector3::from(self.origin) + self.direction * ijk.component_mul(&Vector3::from(self.spacing))
    }

    /// Continuous voxel index of a physical position.
    pub fn index_from_world(&self, p: Vector3<f64>) -> Vector3<f64> {
        // direction is a rotation (checked on construction): its inverse is its transpose.
        (self.direction.transpose() * (p - Vector3::from(self.origin))).component_div(&Vector3::from(self.spacing))
    }

    /// Physical bounds of the voxel centres (min, max) over the 8 corners.
    pub fn bounds(&self) -> (Vector3<f64>, Vector3<f64>) {
        let d = self.dims.map(|d| (d - 1) as f64);
        let corners: Vec<Vector3<f64>> = (0..8)
            .map(|c| {
                self.world_from_index(Vector3::new(
                    d[0] * (c & 1) as f64,
                    d[1] * ((c >> 1) & 1) as f64,
                    d[2] * ((c >> 2) & 1) as f64,
                ))
            })
            .collect();
        crate::mesh::bounds(&corners)
    }

    /// Trilinear sample at a continuous voxel index; `None` outside the voxel-centre box.
    pub fn sample_index(&self, ijk: Vector3<f64>) -> Option<f32> {
        trilinear(&self.data, self.dims, ijk.x, ijk.y, ijk.z, 0.0).map(|v| v as f32)
    }

    /// Trilinear sample at a physical position.
    pub fn sample_world(&self, p: Vector3<f64>) -> Option<f32> {
        self.sample_index(self.index_from_world(p))
    }

    /// (min, max) of the samples.
    pub fn range(&self) -> (f32, f32) {
        self.data.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), v| (lo.min(*v), hi.max(*v)))
    }
}

/// The trilinear blend of a voxel cube: `v(offset)` reads a corner, `strides` are the x,
/// y, z offsets (0 along a flat axis), `f` the fractions. Shared by every trilinear sampler.
#[inline(always)]
pub fn lerp_cube<T: crate::math::Real>(v: impl Fn(usize) -> T, strides: [usize; 3], f: [T; 3]) -> T {
    let [sx, sy, sz] = strides;
    let c00 = v(0) + (v(sx) - v(0)) * f[0];
    let c10 = v(sy) + (v(sy + sx) - v(sy)) * f[0];
    let c01 = v(sz) + (v(sz + sx) - v(sz)) * f[0];
    let c11 = v(sz + sy) + (v(sz + sy + sx) - v(sz + sy)) * f[0];
    let c0 = c00 + (c10 - c00) * f[1];
    let c1 = c01 + (c11 - c01) * f[1];
    c0 + (c1 - c0) * f[2]
}

/// The point moved onto the voxel-centre box when within `tolerance` (voxels) of it;
/// `None` when further out.
#[inline]
pub fn clamp_to_box<T: crate::math::Real>(dims: [usize; 3], x: T, y: T, z: T, tolerance: T) -> Option<(T, T, T)> {
    let c = |v: T, n: usize| {
        let max = T::of((n - 1) as f64);
        (v >= -tolerance && v <= max + tolerance).then(|| v.clamp(T::zero(), max))
    };
    Some((c(x, dims[0])?, c(y, dims[1])?, c(z, dims[2])?))
}

/// Trilinear interpolation of x-fastest samples at a continuous index, in precision T;
/// `None` beyond `tolerance` outside the voxel-centre box.
#[inline]
pub fn trilinear<T: crate::math::Real>(data: &[f32], dims: [usize; 3], x: T, y: T, z: T, tolerance: T) -> Option<T> {
    let (x, y, z) = clamp_to_box(dims, x, y, z, tolerance)?;
    let cell = |c: T, n: usize| (c.trunc_i32().max(0) as usize).min(n.saturating_sub(2));
    let (i, j, k) = (cell(x, dims[0]), cell(y, dims[1]), cell(z, dims[2]));
    let strides = [
        usize::from(dims[0] > 1),
        if dims[1] > 1 { dims[0] } else { 0 },
        if dims[2] > 1 { dims[0] * dims[1] } else { 0 },
    ];
    let base = i + dims[0] * (j + dims[1] * k);
    Some(lerp_cube(
        |o| T::of_f32(data[base + o]),
        strides,
        [x - T::of(i as f64), y - T::of(j as f64), z - T::of(k as f64)],
    ))
}

/// How a volume is read between voxel centres.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sampling {
    Trilinear,
    /// Catmull-Rom cubic convolution, 4x4x4 taps: sharper, about 4-8x the cost.
    Tricubic,
}

/// Sample points this far (in source voxels) outside the voxel-centre box are read on its
/// edge rather than as background: round-off on a mesh built on the box must not punch
/// holes in its boundary.
pub const SAMPLE_TOLERANCE: f64 = 1e-6;

/// Catmull-Rom weights for the 4 taps around t in [0, 1).
#[inline]
fn catmull_rom<T: crate::math::Real>(t: T) -> [T; 4] {
    let (h, one, two, three) = (T::of(0.5), T::one(), T::of(2.0), T::of(3.0));
    let t2 = t * t;
    let t3 = t2 * t;
    [
        h * (-t3 + two * t2 - t),
        h * (three * t3 - T::of(5.0) * t2 + two),
        h * (-three * t3 + T::of(4.0) * t2 + t),
        h * (t3 - t2),
    ]
    .map(|w| w * one)
}

/// Tricubic (Catmull-Rom) interpolation; taps beyond the edges repeat the edge voxel.
pub fn tricubic<T: crate::math::Real>(data: &[f32], dims: [usize; 3], x: T, y: T, z: T) -> Option<T> {
    let (x, y, z) = clamp_to_box(dims, x, y, z, T::of(SAMPLE_TOLERANCE))?;
    let base = |c: T| c.to_f64().floor() as i64;
    let (bi, bj, bk) = (base(x), base(y), base(z));
    let (wx, wy, wz) =
        (catmull_rom(x - T::of(bi as f64)), catmull_rom(y - T::of(bj as f64)), catmull_rom(z - T::of(bk as f64)));
    let clamp = |v: i64, n: usize| v.clamp(0, n as i64 - 1) as usize;
    let mut acc = T::zero();
    for (c, wzc) in wz.iter().enumerate() {
        let kk = clamp(bk + c as i64 - 1, dims[2]);
        for (b, wyb) in wy.iter().enumerate() {
            let jj = clamp(bj + b as i64 - 1, dims[1]);
            let row = dims[0] * (jj + dims[1] * kk);
            let mut line = T::zero();
            for (a, wxa) in wx.iter().enumerate() {
                line += *wxa * T::of(data[row + clamp(bi + a as i64 - 1, dims[0])] as f64);
            }
            acc += *wzc * *wyb * line;
        }
    }
    Some(acc)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp() -> Volume {
        let dims = [4, 3, 2];
        let data = (0..24).map(|n| (n % 4) as f32 + 10.0 * ((n / 4) % 3) as f32 + 100.0 * (n / 12) as f32).collect();
        Volume::new(dims, [0.5, 1.0, 2.0], [1.0, 2.0, 3.0], Matrix3::identity(), data, "ramp").unwrap()
    }

    #[test]
    fn trilinear_reproduces_linear_fields() {
        let v = ramp();
        let s = v.sample_index(Vector3::new(1.25, 0.5, 0.75)).unwrap();
        assert!((s - (1.25 + 5.0 + 75.0)).abs() < 1e-5);
        let p = v.world_from_index(Vector3::new(3.0, 2.0, 1.0));
        assert_eq!(p, Vector3::new(2.5, 4.0, 5.0));
        assert!((v.sample_world(p).unwrap() - 123.0).abs() < 1e-5);
        assert!(v.sample_index(Vector3::new(3.01, 0.0, 0.0)).is_none());
    }

    #[test]
    fn rotated_direction_round_trips() {
        let rot = nalgebra::Rotation3::from_euler_angles(0.3, -0.2, 1.1).into_inner();
        let v = Volume::new([2, 2, 2], [1.0, 2.0, 3.0], [5.0, 0.0, -1.0], rot, vec![0.0; 8], "r").unwrap();
        let ijk = Vector3::new(0.3, 1.7, 0.9);
        assert!((v.index_from_world(v.world_from_index(ijk)) - ijk).norm() < 1e-12);
    }

    #[test]
    fn bad_geometry_is_named() {
        let e =
            Volume::new([2, 2, 1], [1.0, 0.0, 1.0], [0.0; 3], Matrix3::identity(), vec![0.0; 4], "a.mha").unwrap_err();
        assert!(e.to_string().contains("a.mha") && e.to_string().contains("spacing"), "{e}");
        let e = Volume::new([2, 2, 1], [1.0; 3], [0.0; 3], Matrix3::identity(), vec![0.0; 3], "a").unwrap_err();
        assert!(matches!(e, VolumeError::SampleCount { got: 3, expected: 4, .. }));
        let e = Volume::new([2, 2, 1], [1.0; 3], [0.0; 3], Matrix3::identity(), vec![0.0, 0.0, f32::NAN, 0.0], "a")
            .unwrap_err();
        assert!(matches!(e, VolumeError::NonFiniteSample { index: 2, voxel: [0, 1, 0], .. }));
    }

    /// Dims past 2³¹ - 1 voxels (or past usize) are refused by name before the samples are
    /// counted; dims just within are held to their samples as any others.
    #[test]
    fn volumes_past_the_samplers_offsets_are_refused_by_name() {
        let new = |dims| Volume::new(dims, [1.0; 3], [0.0; 3], Matrix3::identity(), Vec::new(), "huge.nii");
        for dims in [[46_341, 46_341, 1], [2, 1 << 30, 1], [usize::MAX, 2, 3], [1 << 40, 1 << 40, 1]] {
            let e = new(dims).unwrap_err();
            assert!(matches!(e, VolumeError::TooManyVoxels { max: MAX_VOXELS, .. }), "{dims:?}: {e}");
            assert!(e.to_string().contains("huge.nii") && e.to_string().contains("2147483647"), "{e}");
        }
        assert_eq!(46_340 * 46_340, 2_147_395_600);
        let e = new([46_340, 46_340, 1]).unwrap_err();
        assert!(matches!(e, VolumeError::SampleCount { got: 0, expected: 2_147_395_600, .. }), "{e}");
        assert!(matches!(new([1 << 30, 2, 1]).unwrap_err(), VolumeError::TooManyVoxels { .. }));
        assert!(matches!(new([(1 << 31) - 1, 1, 1]).unwrap_err(), VolumeError::SampleCount { .. }));
    }
}
