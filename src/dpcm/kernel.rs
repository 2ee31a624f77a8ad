//! The phyxel update, shared by every CPU path and mirrored line by line in
//! `shaders/dpcm.wgsl`.
//!
//! Z(n+1) = 2·Z(n) - Z(n-1) + F·h²/m (the seed's Verlet form), with every force already
//! scaled by h²/m (stiffness) or h/m (damping; velocities are per step, Z(n) - Z(n-1)).
//! Link forces are sums of differences (z_j - z_i), never Σz_j - 4·z_i: the differences are
//! exactly zero at rest, so a grid at a non-zero rest height stays there bit for bit (the
//! seed fought quantisation noise at rest).

use bytemuck::{Pod, Zeroable};

/// Side of the square tiles markers are binned into (and of the GPU workgroups).
pub const TILE: usize = 16;

/// Link directions as (dx, dy): four axial, then four diagonal.
pub const AXIAL: [(isize, isize); 4] = [(-1, 0), (1, 0), (0, -1), (0, 1)];
pub const DIAGONAL: [(isize, isize); 4] = [(-1, -1), (1, -1), (-1, 1), (1, 1)];

/// Per-step coefficients, as the shader's uniform reads them.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct Coeffs {
    /// Ground link: k·h²/m and c·h/m.
    pub ground_a: f32,
    pub ground_b: f32,
    /// Axial links (left, right, up, down).
    pub axial_a: f32,
    pub axial_b: f32,
    /// Diagonal links.
    pub diag_a: f32,
    pub diag_b: f32,
    /// Half-width of the plastic ground link's elastic band (metres); negative: elastic.
    pub plastic_threshold: f32,
    /// Probability that a link exists, scaled to 2^24 (2^24: every link).
    pub link_keep: u32,
    /// Seed of the stochastic topology (already hashed).
    pub link_seed: u32,
    pub has_axial: u32,
    pub has_diagonal: u32,
    pub _pad: u32,
}

/// A marker as the kernels read it: grid units for (col, row) and threshold, metres for
/// heights, forces pre-scaled by h²/m.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct KernelMarker {
    pub col: f32,
    pub row: f32,
    /// Height of the marker's centre above the fixed plane (metres).
    pub height: f32,
    /// Height change since the previous step (metres per step).
    pub step_dz: f32,
    /// k·h²/m·spacing: the push for a penetration of one phyxel.
    pub stiffness_a: f32,
    /// c·h/m.
    pub damping_b: f32,
    /// Radius of influence in phyxels.
    pub threshold: f32,
    /// 1 / ((1 - flattening)·spacing): heights into flattened grid units.
    pub z_scale: f32,
}

/// The "lowbias32" integer hash (Chris Wellons); u32 arithmetic that WGSL reproduces.
#[inline(always)]
pub fn hash32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

/// Whether the stochastic topology keeps the link owned by phyxel `owner` in canonical
/// direction `dir` (0: +x, 1: +y, 2: +x+y, 3: -x+y).
#[inline(always)]
pub fn link_kept(c: &Coeffs, owner: u32, dir: u32) -> bool {
    (hash32(owner.wrapping_mul(4).wrapping_add(dir) ^ c.link_seed) >> 8) < c.link_keep
}

/// The undirected link from (x, y) to (x + dx, y + dy) as (owner index, canonical direction).
#[inline(always)]
fn canonical(width: usize, x: usize, y: usize, dx: isize, dy: isize) -> (u32, u32) {
    let (ox, oy, dir) = match (dx, dy) {
        (1, 0) => (x as isize, y as isize, 0),
        (-1, 0) => (x as isize - 1, y as isize, 0),
        (0, 1) => (x as isize, y as isize, 1),
        (0, -1) => (x as isize, y as isize - 1, 1),
        (1, 1) => (x as isize, y as isize, 2),
        (-1, -1) => (x as isize - 1, y as isize - 1, 2),
        (-1, 1) => (x as isize, y as isize, 3),
        _ => (x as isize + 1, y as isize - 1, 3), // (1, -1)
    };
    ((oy as usize * width + ox as usize) as u32, dir)
}

/// Sum over existing links of a (z_j - z) + b (v_j - v), for one family of directions.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn family_term(c: &Coeffs, dirs: &[(isize, isize); 4], a: f32, b: f32, z: &[f32], zp: &[f32], width: usize, height: usize, x: usize, y: usize) -> f32 {
    let i = y * width + x;
    let (zi, vi) = (z[i], z[i] - zp[i]);
    let mut dzs = 0.0f32;
    let mut dvs = 0.0f32;
    for &(dx, dy) in dirs {
        let (nx, ny) = (x as isize + dx, y as isize + dy);
        let inside = nx >= 0 && ny >= 0 && (nx as usize) < width && (ny as usize) < height;
        let kept = inside && {
            let (owner, dir) = canonical(width, x, y, dx, dy);
            link_kept(c, owner, dir)
        };
        if kept {
            let j = ny as usize * width + nx as usize;
            dzs += z[j] - zi;
            dvs += (z[j] - zp[j]) - vi;
        } else {
            dzs += 0.0;
            dvs += 0.0;
        }
    }
    a * dzs + b * dvs
}

/// The plastic ground link's rest point after Z(n): dragged so that |Z - rest| <= threshold
/// (the hysteresis of [CLH96]). Elastic when the threshold is negative.
#[inline(always)]
pub fn plastic_rest(c: &Coeffs, rest: f32, z: f32) -> f32 {
    if c.plastic_threshold < 0.0 {
        rest
    } else {
        rest.max(z - c.plastic_threshold).min(z + c.plastic_threshold)
    }
}

/// Z(n+1) of phyxel (x, y) without markers: the general form, any topology, any position
/// (borders lose their outward links). `ground_a`/`ground_b` are the phyxel's own.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub fn phyxel_update(c: &Coeffs, ground_a: f32, ground_b: f32, rest: f32, z: &[f32], zp: &[f32], width: usize, height: usize, x: usize, y: usize) -> f32 {
    let i = y * width + x;
    let (zi, vi) = (z[i], z[i] - zp[i]);
    let mut links = 0.0f32;
    if c.has_axial != 0 {
        links += family_term(c, &AXIAL, c.axial_a, c.axial_b, z, zp, width, height, x, y);
    }
    if c.has_diagonal != 0 {
        links += family_term(c, &DIAGONAL, c.diag_a, c.diag_b, z, zp, width, height, x, y);
    }
    let ground = ground_a * (zi - rest) + ground_b * vi;
    2.0 * zi - zp[i] + (links - ground)
}

/// The push of one marker on a phyxel at (x, y) with height z and step velocity v, already
/// scaled by h²/m: a radial repulsion inside the (flattened) sphere of influence, projected
/// on the phyxel's axis, plus viscous coupling to the marker's own motion.
#[inline(always)]
pub fn marker_term(m: &KernelMarker, x: f32, y: f32, z: f32, v: f32) -> f32 {
    let dx = x - m.col;
    let dy = y - m.row;
    let dz = (z - m.height) * m.z_scale;
    let d2 = dx * dx + dy * dy + dz * dz;
    if d2 >= m.threshold * m.threshold {
        return 0.0;
    }
    let d = d2.sqrt();
    let dir = if d > 0.0 { dz / d } else { -1.0 };
    m.stiffness_a * (m.threshold - d) * dir + m.damping_b * (m.step_dz - v)
}

/// Per-phyxel ground coefficients: one value for the grid, or a texture row.
pub trait Field: Copy {
    fn at(self, x: usize) -> f32;
}
impl Field for f32 {
    #[inline(always)]
    fn at(self, _: usize) -> f32 {
        self
    }
}
impl Field for &[f32] {
    #[inline(always)]
    fn at(self, x: usize) -> f32 {
        self[x]
    }
}

/// Rows y-1, y, y+1 of Z(n) and Z(n-1).
pub struct Rows<'a> {
    pub up: &'a [f32],
    pub mid: &'a [f32],
    pub down: &'a [f32],
    pub up_p: &'a [f32],
    pub mid_p: &'a [f32],
    pub down_p: &'a [f32],
}

/// The interior of one row (columns 1..width-1) for the regular topologies, written so the
/// compiler vectorises it. Same expression tree as [`phyxel_update`]: the two agree bit for
/// bit (tested), the general form being the reference and the border path.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub fn interior_row<const AX: bool, const DG: bool, GA: Field, GB: Field>(c: &Coeffs, ga: GA, gb: GB, rest: &mut [f32], plastic: bool, rest_height: f32, r: &Rows, out: &mut [f32]) {
    let w = out.len();
    let (up, mid, down) = (&r.up[..w], &r.mid[..w], &r.down[..w]);
    let (up_p, mid_p, down_p) = (&r.up_p[..w], &r.mid_p[..w], &r.down_p[..w]);
    let per_phyxel_rest = !rest.is_empty();
    for x in 1..w - 1 {
        let zi = mid[x];
        let vi = zi - mid_p[x];
        let mut links = 0.0f32;
        if AX {
            let dzs = 0.0 + (mid[x - 1] - zi) + (mid[x + 1] - zi) + (up[x] - zi) + (down[x] - zi);
            let dvs = 0.0
                + ((mid[x - 1] - mid_p[x - 1]) - vi)
                + ((mid[x + 1] - mid_p[x + 1]) - vi)
                + ((up[x] - up_p[x]) - vi)
                + ((down[x] - down_p[x]) - vi);
            links += c.axial_a * dzs + c.axial_b * dvs;
        }
        if DG {
            let dzs = 0.0 + (up[x - 1] - zi) + (up[x + 1] - zi) + (down[x - 1] - zi) + (down[x + 1] - zi);
            let dvs = 0.0
                + ((up[x - 1] - up_p[x - 1]) - vi)
                + ((up[x + 1] - up_p[x + 1]) - vi)
                + ((down[x - 1] - down_p[x - 1]) - vi)
                + ((down[x + 1] - down_p[x + 1]) - vi);
            links += c.diag_a * dzs + c.diag_b * dvs;
        }
        let rest_x = if per_phyxel_rest {
            let r = if plastic { plastic_rest(c, rest[x], zi) } else { rest[x] };
            rest[x] = r;
            r
        } else {
            rest_height
        };
        let ground = ga.at(x) * (zi - rest_x) + gb.at(x) * vi;
        out[x] = 2.0 * zi - mid_p[x] + (links - ground);
    }
}
