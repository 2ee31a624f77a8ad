//! Displacement volumes (seed 002, section 3.2): local deformation without a mesh.
//!
//! A displacement volume has a centre c, a displacement d and an extent e. In its frame
//! (w along d, u and v across), the displacement weight is V = Bu(u)·Bv(v)·Bw(w): quadratic
//! B-splines of support [-e, e] across, and along w the support [-e, 0] behind the centre
//! and twice that, [0, 2e], ahead of it (material squeezed ahead of the push), each scaled
//! to 1 at the centre. V and its derivative vanish on the volume's faces, so the
//! deformation is C¹ and leaves everything outside untouched.
//!
//! It acts as a backward distortion of sampling positions: out(p) = src(p - V(p)·d), which
//! moves the content at c by +d. Several volumes compose as the deformations they are,
//! applied in order (the last one's backward map is applied first). Sampling positions
//! live in the source's physical space (the rest space of a mesh warp).

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

/// A displacement volume in the source's physical units.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DisplacementVolume {
    pub centre: [f64; 3],
    pub displacement: [f64; 3],
    pub extent: f64,
}

/// Quadratic B-spline of support [-1, 1], 1 at 0 (the uniform quadratic basis, scaled).
pub fn quadratic_bspline(x: f64) -> f64 {
    let t = (x + 1.0) * 1.5; // knots at 0, 1, 2, 3 over [-1, 1]
    let b = if !(0.0..3.0).contains(&t) {
        0.0
    } else if t < 1.0 {
        0.5 * t * t
    } else if t < 2.0 {
        0.5 * (-2.0 * t * t + 6.0 * t - 3.0)
    } else {
        0.5 * (3.0 - t) * (3.0 - t)
    };
    b / 0.75
}

/// The compiled form: a frame and the checks done once.
#[derive(Debug, Clone, Copy)]
pub struct CompiledDisplacement {
    centre: Vector3<f64>,
    displacement: Vector3<f64>,
    /// Rows: u, v, w axes.
    frame: Matrix3<f64>,
    extent: f64,
}

impl DisplacementVolume {
    /// A push driven by a tool pose, with no physics: centred on the tool tip, pushing
    /// `depth` along the tool's -z (into the tissue; the shaft runs along +z).
    pub fn from_tool(source_from_tool: &nalgebra::Isometry3<f64>, depth: f64, extent: f64) -> Self {
        let tip = source_from_tool.translation.vector;
        let push = source_from_tool.rotation * Vector3::new(0.0, 0.0, -depth);
        Self { centre: tip.into(), displacement: push.into(), extent }
    }

    /// Validates and prepares the volume. A push larger than half the extent would fold
    /// space (the backward map stops being one-to-one), so it is refused.
    pub fn compile(&self) -> Result<CompiledDisplacement, String> {
        let c = Vector3::from(self.centre);
        let d = Vector3::from(self.displacement);
        if !(c.iter().chain(d.iter()).all(|v| v.is_finite()) && self.extent.is_finite()) {
            return Err("centre, displacement and extent must be finite".into());
        }
        if self.extent <= 0.0 {
            return Err(format!("extent {} must be positive", self.extent));
        }
        if d.norm() >= 0.5 * self.extent {
            return Err(format!(
                "displacement {:.4} is not below half the extent ({:.4}); the deformation would fold",
                d.norm(),
                0.5 * self.extent
            ));
        }
        let w = if d.norm() > 0.0 { d.normalize() } else { Vector3::z() };
        let helper = if w.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let u = helper.cross(&w).normalize();
        let v = w.cross(&u);
        Ok(CompiledDisplacement {
            centre: c,
            displacement: d,
            frame: Matrix3::from_rows(&[u.transpose(), v.transpose(), w.transpose()]),
            extent: self.extent,
        })
    }
}

impl CompiledDisplacement {
    /// V(p) in [0, 1].
    pub fn weight(&self, p: &Vector3<f64>) -> f64 {
        let l = self.frame * (p - self.centre) / self.extent;
        let bw = if l.z < 0.0 { quadratic_bspline(l.z) } else { quadratic_bspline(l.z / 2.0) };
        if bw == 0.0 {
            return 0.0;
        }
        quadratic_bspline(l.x) * quadratic_bspline(l.y) * bw
    }

    /// The volume in another space whose points map to this one's as x ↦ M·x + o (a grid's
    /// index space): the rows of l = A·x + a (the frame coordinates over the extent that
    /// [`Self::weight`] takes; xyz: A's row, w: a) and the displacement there, M⁻¹·d; `None`
    /// for a singular M. The GPU warp samples through this form.
    pub fn in_space(&self, m: &Matrix3<f64>, o: &Vector3<f64>) -> Option<([[f64; 4]; 3], Vector3<f64>)> {
        let a = self.frame * m / self.extent;
        let a0 = self.frame * (o - self.centre) / self.extent;
        let d = m.try_inverse()? * self.displacement;
        Some(([0, 1, 2].map(|r| [a[(r, 0)], a[(r, 1)], a[(r, 2)], a0[r]]), d))
    }

    /// The backward map of this volume: p - V(p)·d.
    pub fn backward(&self, p: &Vector3<f64>) -> Vector3<f64> {
        p - self.displacement * self.weight(p)
    }
}

/// Compiles `volumes` in order; the first refusal with its index.
pub fn compile_all(volumes: &[DisplacementVolume]) -> Result<Vec<CompiledDisplacement>, (usize, String)> {
    volumes.iter().enumerate().map(|(index, d)| d.compile().map_err(|why| (index, why))).collect()
}

/// Backward map of a sequence of deformations applied in order.
pub fn backward_all(volumes: &[CompiledDisplacement], p: &Vector3<f64>) -> Vector3<f64> {
    volumes.iter().rev().fold(*p, |q, v| v.backward(&q))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn push() -> CompiledDisplacement {
        DisplacementVolume { centre: [1.0, 2.0, 3.0], displacement: [0.0, 0.0, 1.5], extent: 4.0 }.compile().unwrap()
    }

    #[test]
    fn bspline_is_normalised_c1_and_compact() {
        assert!((quadratic_bspline(0.0) - 1.0).abs() < 1e-15);
        assert_eq!(quadratic_bspline(1.0), 0.0);
        assert_eq!(quadratic_bspline(-1.0), 0.0);
        // Continuous value and slope at the knots ±1/3.
        for knot in [-1.0 / 3.0, 1.0 / 3.0] {
            let h = 1e-7;
            assert!((quadratic_bspline(knot - h) - quadratic_bspline(knot + h)).abs() < 1e-6);
            let slope = |x: f64| (quadratic_bspline(x + h) - quadratic_bspline(x - h)) / (2.0 * h);
            assert!((slope(knot - 1e-4) - slope(knot + 1e-4)).abs() < 1e-3);
        }
    }

    #[test]
    fn zero_on_the_boundary_faces_full_at_the_centre() {
        let d = push();
        let c = Vector3::new(1.0, 2.0, 3.0);
        assert!((d.weight(&c) - 1.0).abs() < 1e-12);
        // Faces: u, v = ±e; w = -e behind, +2e ahead.
        for p in [c + Vector3::x() * 4.0, c - Vector3::y() * 4.0, c - Vector3::z() * 4.0, c + Vector3::z() * 8.0] {
            assert!(d.weight(&p).abs() < 1e-12, "{p}");
        }
        // Still pushing ahead of the centre (twice the support).
        assert!(d.weight(&(c + Vector3::z() * 4.0)) > 0.1);
        assert_eq!(d.backward(&(c + Vector3::x() * 10.0)), c + Vector3::x() * 10.0);
    }

    #[test]
    fn continuous_inside() {
        let d = push();
        let mut worst: f64 = 0.0;
        for n in 0..2000 {
            let t = n as f64 / 2000.0;
            let p = Vector3::new(-3.0 + 8.0 * t, 2.0 + 0.3 * t, -1.0 + 12.0 * t);
            let q = p + Vector3::new(1e-6, 1e-6, 1e-6);
            worst = worst.max((d.backward(&p) - d.backward(&q)).norm());
        }
        assert!(worst < 1e-5, "{worst}");
    }

    #[test]
    fn composition_applies_the_last_deformation_first_and_separate_ones_commute() {
        let a = DisplacementVolume { centre: [0.0; 3], displacement: [0.5, 0.0, 0.0], extent: 2.0 }.compile().unwrap();
        let b = DisplacementVolume { centre: [20.0, 0.0, 0.0], displacement: [0.0, 0.5, 0.0], extent: 2.0 }
            .compile()
            .unwrap();
        let p = Vector3::new(0.2, 0.1, 0.0);
        assert_eq!(backward_all(&[a, b], &p), backward_all(&[b, a], &p));
        assert_eq!(backward_all(&[a, b], &p), a.backward(&p));
        let c = DisplacementVolume { centre: [0.3, 0.0, 0.0], displacement: [0.0, 0.6, 0.0], extent: 2.0 }
            .compile()
            .unwrap();
        assert_eq!(backward_all(&[a, c], &p), a.backward(&c.backward(&p)));
    }

    #[test]
    fn a_tool_pose_pushes_along_its_shaft() {
        let pose = nalgebra::Isometry3::new(Vector3::new(1.0, 2.0, 3.0), Vector3::x() * std::f64::consts::FRAC_PI_2);
        let d = DisplacementVolume::from_tool(&pose, 0.5, 4.0);
        assert_eq!(d.centre, [1.0, 2.0, 3.0]);
        // Tool z rotated 90° about x points along -y; the push goes along +y.
        let push = Vector3::from(d.displacement);
        assert!((push - Vector3::new(0.0, 0.5, 0.0)).norm() < 1e-12, "{push}");
        assert!(d.compile().is_ok());
    }

    #[test]
    fn folding_pushes_are_refused() {
        let e =
            DisplacementVolume { centre: [0.0; 3], displacement: [0.0, 0.0, 2.0], extent: 4.0 }.compile().unwrap_err();
        assert!(e.contains("fold"), "{e}");
        assert!(DisplacementVolume { centre: [0.0; 3], displacement: [0.0; 3], extent: -1.0 }.compile().is_err());
    }
}
