//! The embedded torso-like phantom: nested ellipsoids (body, lungs, liver, kidneys,
//! spleen, a tumour), a spine of vertebral bodies, ribs, and contrast-filled vessels,
//! in Hounsfield units. Analytic, so any resolution is the same object.

use nalgebra::{Matrix3, Vector3};

use super::{Volume, VolumeError};

/// Default phantom grid: the grid-warp seed's 256x160x122 at 1 mm.
pub const DEFAULT_DIMS: [usize; 3] = [256, 160, 122];

struct Ellipsoid {
    centre: [f64; 3],
    radii: [f64; 3],
    value: f32,
}

impl Ellipsoid {
    fn contains(&self, p: &Vector3<f64>) -> bool {
        (0..3).map(|a| ((p[a] - self.centre[a]) / self.radii[a]).powi(2)).sum::<f64>() <= 1.0
    }
}

/// Tube along z (a vessel) or along any axis through `a`..`b`.
struct Tube {
    a: [f64; 3],
    b: [f64; 3],
    radius: f64,
    value: f32,
}

impl Tube {
    fn contains(&self, p: &Vector3<f64>) -> bool {
        let a = Vector3::from(self.a);
        let ab = Vector3::from(self.b) - a;
        let t = ((p - a).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0);
        (p - (a + ab * t)).norm() <= self.radius
    }
}

/// Value at `p` (millimetres, phantom centred on the origin; x left-right, y front-back, z up).
pub fn phantom_value(p: &Vector3<f64>) -> f32 {
    // Later entries overwrite earlier ones (painter's order), as in Shepp-Logan.
    let organs = [
        Ellipsoid { centre: [0.0, 0.0, 0.0], radii: [125.0, 78.0, 200.0], value: 40.0 }, // body (soft tissue)
        Ellipsoid { centre: [0.0, 0.0, 0.0], radii: [119.0, 72.0, 200.0], value: -90.0 }, // subcutaneous fat
        Ellipsoid { centre: [0.0, 0.0, 0.0], radii: [110.0, 64.0, 200.0], value: 35.0 }, // muscle wall/cavity
        Ellipsoid { centre: [-55.0, 0.0, 70.0], radii: [42.0, 50.0, 80.0], value: -800.0 }, // right lung base
        Ellipsoid { centre: [55.0, 0.0, 70.0], radii: [42.0, 50.0, 80.0], value: -800.0 }, // left lung base
        Ellipsoid { centre: [-40.0, -5.0, -5.0], radii: [55.0, 45.0, 45.0], value: 60.0 }, // liver
        Ellipsoid { centre: [-30.0, -15.0, 5.0], radii: [10.0, 9.0, 8.0], value: 90.0 }, // enhancing tumour
        Ellipsoid { centre: [60.0, 10.0, 10.0], radii: [22.0, 18.0, 30.0], value: 50.0 }, // spleen
        Ellipsoid { centre: [-48.0, 28.0, -35.0], radii: [18.0, 14.0, 32.0], value: 150.0 }, // right kidney
        Ellipsoid { centre: [48.0, 28.0, -30.0], radii: [18.0, 14.0, 32.0], value: 150.0 }, // left kidney
        Ellipsoid { centre: [15.0, -20.0, -30.0], radii: [35.0, 20.0, 22.0], value: 20.0 }, // bowel
    ];
    let mut v = -1000.0; // air outside the body
    for e in &organs {
        if e.contains(p) {
            v = e.value;
        }
    }
    if v == -1000.0 {
        return v;
    }
    // Vertebral bodies every 30 mm along z, discs between them.
    let spine = Tube { a: [0.0, 45.0, -200.0], b: [0.0, 45.0, 200.0], radius: 16.0, value: 250.0 };
    if spine.contains(p) {
        let phase = (p.z + 200.0).rem_euclid(30.0);
        v = if phase < 24.0 { 700.0 } else { 80.0 };
    }
    // Ribs: elliptical rings in slabs above z = 20 mm.
    if p.z > 20.0 && (p.z - 20.0).rem_euclid(25.0) < 8.0 {
        let r = (p.x / 116.0).powi(2) + (p.y / 70.0).powi(2);
        if (0.90..=1.0).contains(&r) && p.y > -50.0 {
            v = 900.0;
        }
    }
    let vessels = [
        Tube { a: [8.0, 28.0, -200.0], b: [8.0, 28.0, 200.0], radius: 11.0, value: 200.0 }, // aorta
        Tube { a: [-14.0, 25.0, -200.0], b: [-14.0, 25.0, 200.0], radius: 10.0, value: 180.0 }, // vena cava
        Tube { a: [8.0, 28.0, -30.0], b: [-40.0, 25.0, -40.0], radius: 3.5, value: 200.0 }, // renal artery
        Tube { a: [8.0, 28.0, -28.0], b: [45.0, 25.0, -32.0], radius: 3.5, value: 200.0 },
        Tube { a: [-14.0, 25.0, 0.0], b: [-55.0, -10.0, 10.0], radius: 4.0, value: 170.0 }, // hepatic vein
    ];
    for t in &vessels {
        if t.contains(p) {
            v = t.value;
        }
    }
    v
}

/// The phantom sampled on `dims` voxels at `spacing_mm`, centred on the origin.
///
/// Each voxel averages 2x2x2 sub-samples so organ edges are partial-volume smooth, as in CT.
pub fn phantom(dims: [usize; 3], spacing_mm: f64) -> Result<Volume, VolumeError> {
    let origin = dims.map(|d| -((d - 1) as f64) * spacing_mm / 2.0);
    let mut data = vec![0.0f32; dims[0] * dims[1] * dims[2]];
    use rayon::prelude::*;
    data.par_chunks_mut(dims[0] * dims[1]).enumerate().for_each(|(k, slab)| {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                let mut sum = 0.0;
                for s in 0..8 {
                    let off = Vector3::new((s & 1) as f64, ((s >> 1) & 1) as f64, ((s >> 2) & 1) as f64) * 0.5
                        - Vector3::repeat(0.25);
                    let p = Vector3::new(
                        origin[0] + (i as f64 + off.x) * spacing_mm,
                        origin[1] + (j as f64 + off.y) * spacing_mm,
                        origin[2] + (k as f64 + off.z) * spacing_mm,
                    );
                    sum += phantom_value(&p);
                }
                slab[i + dims[0] * j] = sum / 8.0;
            }
        }
    });
    Volume::new(dims, [spacing_mm; 3], origin, Matrix3::identity(), data, "embedded phantom")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phantom_has_the_expected_tissues() {
        let v = phantom([64, 40, 31], 4.0).unwrap();
        assert_eq!(v.dims(), [64, 40, 31]);
        let (lo, hi) = v.range();
        assert_eq!(lo, -1000.0);
        assert!(hi >= 700.0, "bone present: {hi}");
        // Centre voxel of the liver is liver.
        assert_eq!(phantom_value(&Vector3::new(-60.0, -5.0, -5.0)), 60.0);
        assert_eq!(phantom_value(&Vector3::new(0.0, -100.0, 0.0)), -1000.0);
        let (blo, bhi) = v.bounds();
        assert!((blo + bhi).norm() < 1e-9, "centred");
    }
}
