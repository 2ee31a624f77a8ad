//! A tet's geometry as the walk reads it: its outward face planes and the scalar's linear
//! field, refreshed after every deformation step; in f64 for the references, in f32 for
//! the walk and the GPU, one tet at a time or eight side by side (the same bits).

use bytemuck::{Pod, Zeroable};
use nalgebra::{Matrix3, SimdRealField, Vector3};

use super::field::{linear_field_of, F8, V3};
use defvol_core::mesh::TET_FACES;

/// Per tet, as the GPU reads it: outward face planes (n, n·x on the face; face k opposite
/// vertex k) and the scalar's gradient and offset (s(x) = g·x + w), anchored coordinates.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub(crate) struct TetGeometry {
    pub(crate) planes: [[f32; 4]; 4],
    pub(crate) gradient: [f32; 4],
}

/// Planes and gradient of one tet in f64, for the reference (degenerate tets get zero
/// normals and a constant scalar, so rays pass them without a contribution).
pub(crate) fn tet_geometry(x: &[Vector3<f64>; 4], s: &[f64; 4]) -> ([[f64; 4]; 4], [f64; 4]) {
    let mut planes = [[0.0; 4]; 4];
    for (k, face) in TET_FACES.iter().enumerate() {
        let (a, b, c) = (x[face[0]], x[face[1]], x[face[2]]);
        let mut n = (b - a).cross(&(c - a));
        // Outward: away from the opposite vertex (inverted tets stay consistent).
        if n.dot(&(x[k] - a)) > 0.0 {
            n = -n;
        }
        let n = n.try_normalize(1e-300).unwrap_or_else(Vector3::zeros);
        planes[k] = [n.x, n.y, n.z, n.dot(&a)];
    }
    let m = Matrix3::from_rows(&[(x[1] - x[0]).transpose(), (x[2] - x[0]).transpose(), (x[3] - x[0]).transpose()]);
    let grad =
        m.try_inverse().map_or_else(Vector3::zeros, |inv| inv * Vector3::new(s[1] - s[0], s[2] - s[0], s[3] - s[0]));
    let offset = if grad == Vector3::zeros() { (s[0] + s[1] + s[2] + s[3]) / 4.0 } else { s[0] - grad.dot(&x[0]) };
    (planes, [grad.x, grad.y, grad.z, offset])
}

/// The `geometry` kernel's arithmetic, in f32 on anchored positions: planes and gradient of
/// one tet.
pub(crate) fn tet_geometry_f32(x: &[V3; 4], s: &[f32; 4]) -> TetGeometry {
    let (planes, gradient) = tet_geometry_of(x, s);
    TetGeometry { planes, gradient }
}

/// [`tet_geometry_f32`] of eight tets at once, lane l the l-th: the same bits.
pub(crate) fn tet_geometry_8(x: &[[V3; 4]; 8], s: &[[f32; 4]; 8]) -> [TetGeometry; 8] {
    use std::array::from_fn;
    let lanes = |f: &dyn Fn(usize) -> f32| F8::from(from_fn::<f32, 8, _>(f));
    let x = from_fn(|v| Vector3::new(lanes(&|l| x[l][v].x), lanes(&|l| x[l][v].y), lanes(&|l| x[l][v].z)));
    let (planes, gradient) = tet_geometry_of(&x, &from_fn(|v| lanes(&|l| s[l][v])));
    let (planes, gradient) = (planes.map(|p| p.map(<[f32; 8]>::from)), gradient.map(<[f32; 8]>::from));
    from_fn(|l| TetGeometry {
        planes: from_fn(|k| from_fn(|c| planes[k][c][l])),
        gradient: from_fn(|c| gradient[c][l]),
    })
}

/// Planes (outward unit normals, zero on a degenerate face) and gradient of one tet (f32)
/// or of eight side by side ([`F8`]): the same operations, the branches as selects.
fn tet_geometry_of<T: SimdRealField<Element = f32> + Copy>(x: &[Vector3<T>; 4], s: &[T; 4]) -> ([[T; 4]; 4], [T; 4]) {
    let zero = T::zero();
    let planes = std::array::from_fn(|k| {
        let face = TET_FACES[k];
        let a = x[face[0]];
        let n = (x[face[1]] - a).cross(&(x[face[2]] - a));
        // Outward: away from the opposite vertex. A product by -1, which `wide` computes
        // as f32 does (its negation is 0 - x, +0 where f32's is -0).
        let sign = T::splat(-1.0).select(n.dot(&(x[k] - a)).simd_gt(zero), T::one());
        let n = n * sign;
        let len = n.norm();
        let n = (n / len).map(|c| c.select(len.simd_gt(zero), zero));
        [n.x, n.y, n.z, n.dot(&a)]
    });
    (planes, linear_field_of(x, s))
}

#[cfg(test)]
mod tests {
    use super::*;
    use defvol_core::mesh::generate::{lattice, CellSplit};

    /// Eight tets refreshed side by side give each tet's own refresh to the bit, and that
    /// one the f64 planes and gradient within f32 round-off: a lattice's tets (faces on
    /// the axes, zero normal components), turned and inverted; and (bits only) nearly flat,
    /// flat and collapsed ones.
    #[test]
    fn eight_tets_side_by_side_give_each_tets_own_geometry() {
        let mesh = lattice(Vector3::zeros(), Vector3::new(6.0, 4.0, 4.0), [3, 2, 2], CellSplit::Five).unwrap();
        let turn = nalgebra::Rotation3::from_euler_angles(0.4, -0.3, 0.2);
        let mut tets: Vec<[V3; 4]> = Vec::new();
        for (t, tet) in mesh.tets().iter().enumerate() {
            let x = tet.map(|i| mesh.nodes()[i as usize].cast::<f32>());
            tets.push(x);
            tets.push(x.map(|p| turn.cast::<f32>() * p));
            tets.push([x[1], x[0], x[2], x[3]]);
            tets.push([x[0], x[1], x[2], (x[0] + x[1] + x[2]) / 3.0]);
            tets.push([x[0], x[1], x[2], x[1]]);
            tets.push([x[t % 4]; 4]);
        }
        let scalars = |t: usize| [0, 1, 2, 3].map(|v| ((t * 7 + v * 3) % 11) as f32 * 10.0 - 20.0);
        let (mut compared, mut flat) = (0, 0);
        for (chunk, x8) in tets.chunks_exact(8).enumerate() {
            let x8: [[V3; 4]; 8] = std::array::from_fn(|l| x8[l]);
            let s8 = std::array::from_fn(|l| scalars(chunk * 8 + l));
            for (l, got) in tet_geometry_8(&x8, &s8).iter().enumerate() {
                let want = tet_geometry_f32(&x8[l], &s8[l]);
                assert_eq!(bytemuck::bytes_of(got), bytemuck::bytes_of(&want), "tet {}", chunk * 8 + l);
                flat += usize::from(want.gradient[..3] == [0.0; 3]);
                compared += 1;
                // Against f64 where the tet is one (the nearly flat one is ill-conditioned).
                if (chunk * 8 + l) % 6 >= 3 {
                    continue;
                }
                let (planes, gradient) = tet_geometry(&x8[l].map(|p| p.cast::<f64>()), &s8[l].map(f64::from));
                let close = |a: f32, b: f64| (f64::from(a) - b).abs() <= 1e-4 * (1.0 + b.abs());
                let all_close = want.planes.iter().flatten().zip(planes.iter().flatten()).all(|(a, b)| close(*a, *b))
                    && want.gradient.iter().zip(&gradient).all(|(a, b)| close(*a, *b));
                assert!(all_close, "tet {}: {want:?} against {planes:?} {gradient:?}", chunk * 8 + l);
            }
        }
        assert!(compared >= 350 && flat >= 120, "{compared} tets, {flat} degenerate");
    }
}
