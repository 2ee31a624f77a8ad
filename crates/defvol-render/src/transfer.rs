//! Transfer functions: piecewise-linear colour and opacity over the scalar, their lookup
//! tables, and the pre-integrated table of seed 000, section 5.1 (colour and opacity of a
//! whole ray segment from its front and back scalars).
//!
//! Opacity is given per unit length (the opacity of a 1 mm slab for a millimetre volume):
//! a segment of length d has α = 1 - (1 - opacity)^d, i.e. extinction τ = -ln(1 - opacity).

use serde::{Deserialize, Serialize};

use super::RenderError;

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TfPoint {
    pub value: f64,
    /// RGB in 0..1.
    pub color: [f64; 3],
    /// Opacity of a unit length, 0..1 (exclusive).
    pub opacity: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransferFunction {
    pub points: Vec<TfPoint>,
    /// Point values are fractions of the volume's range (for MRI, which has no units).
    #[serde(default)]
    pub relative: bool,
}

const fn p(value: f64, color: [f64; 3], opacity: f64) -> TfPoint {
    TfPoint { value, color, opacity }
}

impl TransferFunction {
    pub const PRESETS: [&'static str; 3] = ["ct_soft_tissue", "ct_bone", "mri"];

    /// CT in Hounsfield units: soft tissue and organs translucent, vessels and bone bright.
    pub fn preset(name: &str) -> Result<Self, RenderError> {
        let points = match name {
            "ct_soft_tissue" => vec![
                p(-1000.0, [0.0, 0.0, 0.0], 0.0),
                p(-200.0, [0.0, 0.0, 0.0], 0.0),
                p(-100.0, [0.85, 0.65, 0.45], 0.01),
                p(20.0, [0.75, 0.35, 0.3], 0.03),
                p(80.0, [0.9, 0.45, 0.35], 0.08),
                p(250.0, [1.0, 0.85, 0.7], 0.3),
                p(700.0, [1.0, 1.0, 0.95], 0.8),
                p(3000.0, [1.0, 1.0, 1.0], 0.9),
            ],
            "ct_bone" => vec![
                p(-1000.0, [0.0; 3], 0.0),
                p(150.0, [0.0; 3], 0.0),
                p(300.0, [0.9, 0.8, 0.65], 0.4),
                p(1000.0, [1.0, 1.0, 0.95], 0.9),
                p(3000.0, [1.0; 3], 0.95),
            ],
            "mri" => {
                return Ok(Self {
                    points: vec![
                        p(0.0, [0.0; 3], 0.0),
                        p(0.1, [0.0; 3], 0.0),
                        p(0.4, [0.7, 0.6, 0.55], 0.05),
                        p(0.8, [1.0, 0.95, 0.9], 0.3),
                        p(1.0, [1.0; 3], 0.5),
                    ],
                    relative: true,
                })
            }
            other => return Err(RenderError::UnknownPreset(other.to_owned())),
        };
        Ok(Self { points, relative: false })
    }

    /// Checks the points; the function in the volume's own values.
    pub fn resolve(&self, data_range: (f32, f32)) -> Result<Self, RenderError> {
        let bad = |why: String| Err(RenderError::TransferFunction(why));
        if self.points.is_empty() {
            return bad("it has no points".into());
        }
        for (i, q) in self.points.iter().enumerate() {
            if !(q.value.is_finite()
                && q.color.iter().all(|c| (0.0..=1.0).contains(c))
                && (0.0..1.0).contains(&q.opacity))
            {
                return bad(format!("point {i} ({q:?}): value must be finite, colour in 0..1, opacity in [0, 1)"));
            }
            if i > 0 && q.value < self.points[i - 1].value {
                return bad(format!("point {i} goes back to value {}", q.value));
            }
        }
        let (lo, hi) = (f64::from(data_range.0), f64::from(data_range.1));
        let map = |v: f64| if self.relative { lo + v * (hi - lo) } else { v };
        Ok(Self {
            points: self.points.iter().map(|q| TfPoint { value: map(q.value), ..*q }).collect(),
            relative: false,
        })
    }

    /// (colour, extinction per unit length) at `s`, exactly (the f64 reference's form).
    pub fn eval(&self, s: f64) -> ([f64; 3], f64) {
        let pts = &self.points;
        let after = pts.partition_point(|q| q.value <= s);
        let (color, opacity) = match (after.checked_sub(1).map(|i| pts[i]), pts.get(after)) {
            (Some(a), Some(b)) if b.value > a.value => {
                let f = (s - a.value) / (b.value - a.value);
                ([0, 1, 2].map(|c| a.color[c] + (b.color[c] - a.color[c]) * f), a.opacity + (b.opacity - a.opacity) * f)
            }
            (Some(a), _) => (a.color, a.opacity),
            (None, Some(b)) => (b.color, b.opacity),
            (None, None) => ([0.0; 3], 0.0),
        };
        (color, -(1.0 - opacity).ln())
    }

    /// An open interval holding every scalar of non-zero opacity: a segment whose scalars
    /// all lie outside it adds nothing (empty-space skipping for tets). Empty (lo > hi)
    /// when nothing is visible.
    pub fn visible_span(&self) -> (f64, f64) {
        let pts = &self.points;
        let (Some(first), Some(last)) =
            (pts.iter().position(|q| q.opacity > 0.0), pts.iter().rposition(|q| q.opacity > 0.0))
        else {
            return (f64::INFINITY, f64::NEG_INFINITY);
        };
        let lo = first.checked_sub(1).map_or(f64::NEG_INFINITY, |i| pts[i].value);
        let hi = pts.get(last + 1).map_or(f64::INFINITY, |q| q.value);
        (lo, hi)
    }

    /// The scalar range in which the function changes (outside it, it is constant).
    pub fn span(&self) -> (f64, f64) {
        match (self.points.first(), self.points.last()) {
            (Some(a), Some(b)) => (a.value, b.value),
            _ => (0.0, 1.0),
        }
    }
}

/// Entries of the 1D table and levels of the pre-integrated one.
pub const LUT_SIZE: usize = 1024;
pub const PREINTEGRATED_SIZE: usize = 512;

/// The transfer function sampled for rendering: (r, g, b, τ) on `LUT_SIZE` values over its
/// span, and the pre-integrated segments for one step length.
#[derive(Debug, Clone)]
pub struct Tables {
    pub lo: f32,
    pub hi: f32,
    /// r, g, b, τ per unit length.
    pub lut: Vec<[f32; 4]>,
    /// The same entries as a full step's premultiplied r, g, b and α (α = 1 - e^(-τ·step)):
    /// point sampling without an exponential per sample.
    pub stepped: Vec<[f32; 4]>,
    /// Premultiplied r, g, b and α of a segment of `step` from front level i to back level j
    /// (row i, column j) over [pre_lo, pre_hi]; empty unless asked for.
    pub preintegrated: Vec<[f32; 4]>,
    /// The pre-integrated levels span the data's range, not the function's: a segment
    /// running from below the function's span to above it crosses the span over only part
    /// of its length, which clamping its ends would lose, and levels beyond the data would be
    /// resolution wasted.
    pub pre_lo: f32,
    pub pre_hi: f32,
    pub step: f32,
    /// Table entries per scalar unit: (LUT_SIZE - 1) / (hi - lo).
    pub(crate) lut_scale: f32,
    /// Pre-integrated levels per scalar unit: (PREINTEGRATED_SIZE - 1) / (pre_hi - pre_lo).
    pub(crate) pre_scale: f32,
}

impl Tables {
    /// Tables for `tf`: the 1D one over its span, the pre-integrated one (when asked for)
    /// over `data_range`.
    pub fn new(tf: &TransferFunction, data_range: (f32, f32), step: f64, preintegrate: bool) -> Self {
        let (lo, hi) = tf.span();
        let hi = if hi > lo { hi } else { lo + 1.0 };
        let (pre_lo, pre_hi) =
            if data_range.1 > data_range.0 { (f64::from(data_range.0), f64::from(data_range.1)) } else { (lo, hi) };
        let at = |i: usize, n: usize| lo + (hi - lo) * i as f64 / (n - 1) as f64;
        let lut = (0..LUT_SIZE)
            .map(|i| {
                let (c, tau) = tf.eval(at(i, LUT_SIZE));
                [c[0] as f32, c[1] as f32, c[2] as f32, tau as f32]
            })
            .collect();
        let stepped = (0..LUT_SIZE)
            .map(|i| {
                let (c, tau) = tf.eval(at(i, LUT_SIZE));
                let alpha = 1.0 - (-tau * step).exp();
                [(c[0] * alpha) as f32, (c[1] * alpha) as f32, (c[2] * alpha) as f32, alpha as f32]
            })
            .collect();
        let preintegrated = if preintegrate { preintegrate_table(tf, pre_lo, pre_hi, step) } else { Vec::new() };
        Self {
            lo: lo as f32,
            hi: hi as f32,
            lut,
            stepped,
            preintegrated,
            pre_lo: pre_lo as f32,
            pre_hi: pre_hi as f32,
            step: step as f32,
            lut_scale: ((LUT_SIZE - 1) as f64 / (hi - lo)) as f32,
            pre_scale: ((PREINTEGRATED_SIZE - 1) as f64 / (pre_hi - pre_lo)) as f32,
        }
    }

    /// (r, g, b, τ) at `s`, linear between table entries.
    #[inline]
    pub fn sample(&self, s: f32) -> [f32; 4] {
        self.interpolate(&self.lut, s)
    }

    /// A full step's premultiplied colour and α at `s`, linear between table entries.
    #[inline(always)]
    pub fn sample_step(&self, s: f32) -> [f32; 4] {
        self.interpolate(&self.stepped, s)
    }

    /// `table` (one of the `LUT_SIZE` tables over [lo, hi]) at `s`, linear between entries.
    #[inline(always)]
    fn interpolate(&self, table: &[[f32; 4]], s: f32) -> [f32; 4] {
        let x = ((s - self.lo) * self.lut_scale).clamp(0.0, (LUT_SIZE - 1) as f32);
        let i = (x as i32).min(LUT_SIZE as i32 - 2) as usize;
        let f = x - i as f32;
        lerp4(table[i], table[i + 1], f)
    }

    /// The segment from `front` to `back` scalars: premultiplied colour and α, bilinear in
    /// the pre-integrated table.
    #[inline(always)]
    pub fn segment(&self, front: f32, back: f32) -> [f32; 4] {
        let n = PREINTEGRATED_SIZE;
        let level = |s: f32| ((s - self.pre_lo) * self.pre_scale).clamp(0.0, (n - 1) as f32);
        let (x, y) = (level(front), level(back));
        let (i, j) = ((x as i32).min(n as i32 - 2) as usize, (y as i32).min(n as i32 - 2) as usize);
        let (fx, fy) = (x - i as f32, y - j as f32);
        let t = &self.preintegrated;
        let top = lerp4(t[i * n + j], t[i * n + j + 1], fy);
        let bottom = lerp4(t[(i + 1) * n + j], t[(i + 1) * n + j + 1], fy);
        lerp4(top, bottom, fx)
    }

    /// The largest extinction over the scalar interval [a, b] (for empty-space skipping).
    pub fn max_tau(&self, a: f32, b: f32) -> f32 {
        let index = |s: f32| (((s - self.lo) / (self.hi - self.lo)).clamp(0.0, 1.0) * (LUT_SIZE - 1) as f32) as usize;
        let (i, j) = (index(a), (index(b) + 1).min(LUT_SIZE - 1));
        self.lut[i..=j].iter().map(|e| e[3]).fold(0.0, f32::max)
    }
}

/// `a + (b - a)·f` per channel, written out: `[_; 4].map` is not always inlined (profiled:
/// the pre-integrated lookup's was a call per sample), and this runs per sample.
#[inline(always)]
fn lerp4(a: [f32; 4], b: [f32; 4], f: f32) -> [f32; 4] {
    [a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f, a[2] + (b[2] - a[2]) * f, a[3] + (b[3] - a[3]) * f]
}

/// Each segment integrated front to back in 64 sub-steps, the scalar linear along it.
fn preintegrate_table(tf: &TransferFunction, lo: f64, hi: f64, step: f64) -> Vec<[f32; 4]> {
    use rayon::prelude::*;
    const SUBSTEPS: usize = 64;
    let n = PREINTEGRATED_SIZE;
    let level = |i: usize| lo + (hi - lo) * i as f64 / (n - 1) as f64;
    (0..n * n)
        .into_par_iter()
        .map(|k| {
            let (front, back) = (level(k / n), level(k % n));
            let ds = step / SUBSTEPS as f64;
            let mut acc = [0.0f64; 4];
            for m in 0..SUBSTEPS {
                let s = front + (back - front) * (m as f64 + 0.5) / SUBSTEPS as f64;
                let (c, tau) = tf.eval(s);
                let alpha = 1.0 - (-tau * ds).exp();
                let w = (1.0 - acc[3]) * alpha;
                for ch in 0..3 {
                    acc[ch] += w * c[ch];
                }
                acc[3] += w;
            }
            acc.map(|v| v as f32)
        })
        .collect()
}

/// Scalar levels (front and back) and length levels of the [`SegmentTable`].
pub const SEGMENT_LEVELS: usize = 128;
pub const SEGMENT_LENGTHS: usize = 32;

/// The 3D pre-integrated table of seed 000, section 5.1, for rays through tetrahedra:
/// premultiplied colour and α of a segment of length `len` ≤ `max_len` whose scalar runs
/// linearly from `front` to `back`. Segments are as long as a tet is thick, so the length is
/// a coordinate of the table, not a constant as in the volume raycaster's 2D one.
#[derive(Debug, Clone)]
pub struct SegmentTable {
    pub lo: f32,
    pub hi: f32,
    pub max_len: f32,
    /// Levels per scalar unit and per unit length.
    pub level_scale: f32,
    pub length_scale: f32,
    /// Index ((front · SEGMENT_LEVELS) + back) · SEGMENT_LENGTHS + length level.
    pub entries: Vec<[f32; 4]>,
}

impl SegmentTable {
    /// Each (front, back) pair integrated once in 128 sub-steps; every length follows from
    /// the same sub-samples (sub-step transparency is (1 - α₁)^l at length level l), so the
    /// whole table costs about as much as its 2D counterpart.
    pub fn new(tf: &TransferFunction, data_range: (f32, f32), max_len: f64) -> Self {
        use rayon::prelude::*;
        const SUBSTEPS: usize = 128;
        let (n, lengths) = (SEGMENT_LEVELS, SEGMENT_LENGTHS);
        let (lo, hi) =
            if data_range.1 > data_range.0 { (f64::from(data_range.0), f64::from(data_range.1)) } else { tf.span() };
        let hi = if hi > lo { hi } else { lo + 1.0 };
        let level = |i: usize| lo + (hi - lo) * i as f64 / (n - 1) as f64;
        // Sub-step length at length level 1.
        let unit = max_len / (lengths - 1) as f64 / SUBSTEPS as f64;
        let entries = (0..n * n)
            .into_par_iter()
            .flat_map_iter(|k| {
                let (front, back) = (level(k / n), level(k % n));
                let samples: Vec<([f64; 3], f64)> = (0..SUBSTEPS)
                    .map(|m| {
                        let (color, tau) = tf.eval(front + (back - front) * (m as f64 + 0.5) / SUBSTEPS as f64);
                        (color, (-tau * unit).exp())
                    })
                    .collect();
                (0..lengths).map(move |l| {
                    let mut acc = [0.0f64; 4];
                    for (color, clear) in &samples {
                        let alpha = 1.0 - clear.powi(l as i32);
                        let w = (1.0 - acc[3]) * alpha;
                        for c in 0..3 {
                            acc[c] += w * color[c];
                        }
                        acc[3] += w;
                    }
                    acc.map(|v| v as f32)
                })
            })
            .collect();
        Self {
            lo: lo as f32,
            hi: hi as f32,
            max_len: max_len as f32,
            level_scale: ((n - 1) as f64 / (hi - lo)) as f32,
            length_scale: ((lengths - 1) as f64 / max_len) as f32,
            entries,
        }
    }

    /// A segment no longer than `max_len`: trilinear in (front, back, length).
    #[inline(always)]
    pub fn lookup(&self, front: f32, back: f32, len: f32) -> [f32; 4] {
        let (n, lengths) = (SEGMENT_LEVELS, SEGMENT_LENGTHS);
        // Plain comparisons rather than `clamp`: the callers' values are finite, and this
        // is the innermost lookup of the tet raycaster.
        let limit = |v: f32, top: f32| {
            if v > 0.0 {
                if v < top {
                    v
                } else {
                    top
                }
            } else {
                0.0
            }
        };
        let level = |s: f32| limit((s - self.lo) * self.level_scale, (n - 1) as f32);
        let (x, y) = (level(front), level(back));
        let z = limit(len * self.length_scale, (lengths - 1) as f32);
        let (i, j, l) = ((x as usize).min(n - 2), (y as usize).min(n - 2), (z as usize).min(lengths - 2));
        let (fx, fy, fz) = (x - i as f32, y - j as f32, z - l as f32);
        let at = |i: usize, j: usize| {
            let at = (i * n + j) * lengths + l;
            lerp4(self.entries[at], self.entries[at + 1], fz)
        };
        let (a, b, c, d) = (at(i, j), at(i, j + 1), at(i + 1, j), at(i + 1, j + 1));
        lerp4(lerp4(a, b, fy), lerp4(c, d, fy), fx)
    }
}
