//! Linear fields over a tet, in the f32 the GPU holds: the scalar the tet raycaster
//! integrates and the map the source is read through are both affine inside a tet.

use nalgebra::{SimdRealField, Vector3};

pub(crate) type V3 = Vector3<f32>;

/// Eight tets' floats side by side, for the geometry refresh: nalgebra's arithmetic lane by
/// lane, each lane the f32 one's bits (IEEE adds, multiplies, divisions and square roots).
pub(crate) type F8 = simba::simd::WideF32x8;

/// The linear field taking the values `s` at the tet's vertices `x`: gradient and offset
/// (s(p) = g·p + w); a constant, their mean, on a degenerate tet.
pub(crate) fn linear_field(x: &[V3; 4], s: &[f32; 4]) -> [f32; 4] {
    linear_field_of(x, s)
}

/// [`linear_field`] of one tet (f32) or of eight side by side ([`F8`]): the same
/// operations, the branches as selects.
pub(crate) fn linear_field_of<T: SimdRealField<Element = f32> + Copy>(x: &[Vector3<T>; 4], s: &[T; 4]) -> [T; 4] {
    // The rows of M are the edges from vertex 0; M⁻¹'s columns are the rows' cross products
    // over det.
    let zero = T::zero();
    let (r0, r1, r2) = (x[1] - x[0], x[2] - x[0], x[3] - x[0]);
    let det = r0.dot(&r1.cross(&r2));
    let grad = (r1.cross(&r2) * (s[1] - s[0]) + r2.cross(&r0) * (s[2] - s[0]) + r0.cross(&r1) * (s[3] - s[0])) / det;
    let grad = grad.map(|g| zero.select(det.simd_eq(zero), g));
    let flat = grad.x.simd_eq(zero) & grad.y.simd_eq(zero) & grad.z.simd_eq(zero);
    let mean = (s[0] + s[1] + s[2] + s[3]) / T::splat(4.0);
    let offset = mean.select(flat, s[0] - grad.dot(&x[0]));
    [grad.x, grad.y, grad.z, offset]
}
