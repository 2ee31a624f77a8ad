//! Linear fields over a tet, in the f32 the GPU holds: the scalar the tet raycaster
//! integrates and the map the source is read through are both affine inside a tet.

use nalgebra::Vector3;

pub(crate) type V3 = Vector3<f32>;

/// The linear field taking the values `s` at the tet's vertices `x`: gradient and offset
/// (s(p) = g·p + w); a constant, their mean, on a degenerate tet.
pub(crate) fn linear_field(x: &[V3; 4], s: &[f32; 4]) -> [f32; 4] {
    // The rows of M are the edges from vertex 0; M⁻¹'s columns are the rows' cross products
    // over det.
    let (r0, r1, r2) = (x[1] - x[0], x[2] - x[0], x[3] - x[0]);
    let det = r0.dot(&r1.cross(&r2));
    let grad = if det != 0.0 {
        (r1.cross(&r2) * (s[1] - s[0]) + r2.cross(&r0) * (s[2] - s[0]) + r0.cross(&r1) * (s[3] - s[0])) / det
    } else {
        V3::zeros()
    };
    let offset = if grad != V3::zeros() { s[0] - grad.dot(&x[0]) } else { (s[0] + s[1] + s[2] + s[3]) / 4.0 };
    [grad.x, grad.y, grad.z, offset]
}
