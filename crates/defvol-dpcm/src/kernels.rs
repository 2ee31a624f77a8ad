//! The phyxel update, shared by every CPU path and mirrored line by line in
//! `dpcm.wgsl`.
//!
//! Z(n+1) = 2·Z(n) - Z(n-1) + F·h²/m (the seed's Verlet form), with every force already
//! scaled by h²/m (stiffness) or h/m (damping; velocities are per step, Z(n) - Z(n-1)).
//! The kernels hold u = Z - rest height, so the balance state is exactly 0 and stays so bit
//! for bit (the seed fought quantisation noise at rest).
//!
//! Links of one family (axial or diagonal) sum as a·Σ(u_j - u) + b·Σ(v_j - v)
//! = (a+b)·Σu_j - b·Σup_j - n·(a·u + b·v), with n the family's existing links: a third of the
//! work of summing differences. Neighbour sums associate as (l + r) + (t + b) for axial and
//! (tl + bl) + (tr + br) for diagonal links, in every path.

use bytemuck::{Pod, Zeroable};

/// Side of the square tiles markers are binned into (and of the GPU workgroups).
pub const TILE: usize = 16;

/// |u| below this (metres) is set to 0 after each step: far below any engraving, and above
/// f32's subnormal range, whose arithmetic is ~100x slower on x86 CPUs. Waves that die out
/// in the far field would otherwise fill the grid with subnormals.
pub const FLUSH_BELOW: f32 = 1e-20;

#[inline(always)]
pub fn flush_tiny(x: f32) -> f32 {
    if x.abs() < FLUSH_BELOW {
        0.0
    } else {
        x
    }
}

/// Per-step coefficients, as the shader's uniform reads them.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct Coeffs {
    /// Ground link: k·h²/m and c·h/m.
    pub ground_a: f32,
    pub ground_b: f32,
    /// Axial links (left, right, up, down): a, b and a + b.
    pub axial_a: f32,
    pub axial_b: f32,
    pub axial_ab: f32,
    /// Diagonal links.
    pub diag_a: f32,
    pub diag_b: f32,
    pub diag_ab: f32,
    /// Half-width of the plastic ground link's elastic band (metres); negative: elastic.
    pub plastic_threshold: f32,
    /// Probability that a link exists, scaled to 2^24 (2^24: every link).
    pub link_keep: u32,
    /// Seed of the stochastic topology (already hashed).
    pub link_seed: u32,
    pub has_axial: u32,
    pub has_diagonal: u32,
    pub _pad: [u32; 3],
}

/// A marker as the kernels read it: grid units for (col, row) and threshold, metres for
/// heights, forces pre-scaled by h²/m.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct KernelMarker {
    pub col: f32,
    pub row: f32,
    /// Height of the marker's centre above the rest height (metres).
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

/// Whether the link from (x, y) towards (dx, dy) exists (inside the grid, and drawn).
#[inline(always)]
pub fn link_exists(c: &Coeffs, width: usize, height: usize, x: usize, y: usize, dx: isize, dy: isize) -> Option<usize> {
    let (nx, ny) = (x as isize + dx, y as isize + dy);
    if nx < 0 || ny < 0 || nx as usize >= width || ny as usize >= height {
        return None;
    }
    let (owner, dir) = canonical(width, x, y, dx, dy);
    link_kept(c, owner, dir).then_some(ny as usize * width + nx as usize)
}

/// A family's (Σu_j, Σup_j, n) over existing links, summed as ((d0 + d1) + (d2 + d3)) in
/// `order` (absent links add 0, which changes no sum).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn family_sums(
    c: &Coeffs,
    order: &[(isize, isize); 4],
    u: &[f32],
    up: &[f32],
    width: usize,
    height: usize,
    x: usize,
    y: usize,
) -> (f32, f32, f32) {
    let mut su = [0.0f32; 4];
    let mut sp = [0.0f32; 4];
    let mut n = 0.0f32;
    for (k, &(dx, dy)) in order.iter().enumerate() {
        if let Some(j) = link_exists(c, width, height, x, y, dx, dy) {
            su[k] = u[j];
            sp[k] = up[j];
            n += 1.0;
        }
    }
    ((su[0] + su[1]) + (su[2] + su[3]), (sp[0] + sp[1]) + (sp[2] + sp[3]), n)
}

/// Link directions (dx, dy) in summation order: axial (l, r, t, b); diagonal (tl, bl, tr, br).
pub const AXIAL: [(isize, isize); 4] = [(-1, 0), (1, 0), (0, -1), (0, 1)];
pub const DIAGONAL: [(isize, isize); 4] = [(-1, -1), (-1, 1), (1, -1), (1, 1)];

/// The plastic ground link's rest point after Z(n): dragged so that |Z - rest| <= threshold
/// (the hysteresis of \[CLH96\]). Elastic when the threshold is negative.
#[inline(always)]
pub fn plastic_rest(c: &Coeffs, rest: f32, z: f32) -> f32 {
    if c.plastic_threshold < 0.0 {
        rest
    } else {
        rest.max(z - c.plastic_threshold).min(z + c.plastic_threshold)
    }
}

/// The update from the link sums: shared by the general form and the fast rows.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn combine(c: &Coeffs, sums: [f32; 4], self_a: f32, self_b: f32, ga: f32, gb: f32, rest: f32, u: f32, up: f32) -> f32 {
    let [su_ax, sp_ax, su_dg, sp_dg] = sums;
    let v = u - up;
    let links =
        ((c.axial_ab * su_ax - c.axial_b * sp_ax) + (c.diag_ab * su_dg - c.diag_b * sp_dg)) - (self_a * u + self_b * v);
    let ground = ga * (u - rest) + gb * v;
    flush_tiny(2.0 * u - up + (links - ground))
}

/// u(n+1) of phyxel (x, y) without markers: the general form, any topology, any position
/// (borders lose their outward links). `ground_a`/`ground_b` are the phyxel's own.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub fn phyxel_update(
    c: &Coeffs,
    ground_a: f32,
    ground_b: f32,
    rest: f32,
    u: &[f32],
    up: &[f32],
    width: usize,
    height: usize,
    x: usize,
    y: usize,
) -> f32 {
    let i = y * width + x;
    let (mut ax, mut dg) = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0));
    if c.has_axial != 0 {
        ax = family_sums(c, &AXIAL, u, up, width, height, x, y);
    }
    if c.has_diagonal != 0 {
        dg = family_sums(c, &DIAGONAL, u, up, width, height, x, y);
    }
    let self_a = ax.2 * c.axial_a + dg.2 * c.diag_a;
    let self_b = ax.2 * c.axial_b + dg.2 * c.diag_b;
    combine(c, [ax.0, ax.1, dg.0, dg.1], self_a, self_b, ground_a, ground_b, rest, u[i], up[i])
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
    // Branch-free (selects), so a row of phyxels runs in SIMD lanes.
    let d = d2.sqrt();
    let dir = if d > 0.0 { dz / d } else { -1.0 };
    let push = m.stiffness_a * (m.threshold - d) * dir + m.damping_b * (m.step_dz - v);
    if d2 < m.threshold * m.threshold {
        push
    } else {
        0.0
    }
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

/// The ground links' rest points along a row.
pub trait RestRow {
    /// The rest point of phyxel x for this step, given Z(n) there (plasticity moves it).
    fn rest(&mut self, c: &Coeffs, x: usize, z: f32) -> f32;
}
/// Every phyxel at one rest height.
pub struct UniformRest(pub f32);
/// Per-phyxel rest points that stay (a rest-height texture, elastic ground).
pub struct FixedRest<'a>(pub &'a [f32]);
/// Per-phyxel rest points dragged by the plastic ground link.
pub struct PlasticRest<'a>(pub &'a mut [f32]);

impl RestRow for UniformRest {
    #[inline(always)]
    fn rest(&mut self, _: &Coeffs, _: usize, _: f32) -> f32 {
        self.0
    }
}
impl RestRow for FixedRest<'_> {
    #[inline(always)]
    fn rest(&mut self, _: &Coeffs, x: usize, _: f32) -> f32 {
        self.0[x]
    }
}
impl RestRow for PlasticRest<'_> {
    #[inline(always)]
    fn rest(&mut self, c: &Coeffs, x: usize, z: f32) -> f32 {
        let r = plastic_rest(c, self.0[x], z);
        self.0[x] = r;
        r
    }
}

/// Which links of a phyxel exist: bit k for [`AXIAL`]`[k]`, bit 4 + k for [`DIAGONAL`]`[k]`.
pub trait LinkMask: Copy {
    fn at(self, x: usize) -> u8;
}
/// Every link (the regular topologies' interior).
#[derive(Clone, Copy)]
pub struct AllLinks;
impl LinkMask for AllLinks {
    #[inline(always)]
    fn at(self, _: usize) -> u8 {
        0xFF
    }
}
impl LinkMask for &[u8] {
    #[inline(always)]
    fn at(self, x: usize) -> u8 {
        self[x]
    }
}

/// The link masks of a stochastic topology, drawn once (the same draw as [`link_kept`]).
pub fn link_masks(c: &Coeffs, width: usize, height: usize) -> Vec<u8> {
    (0..width * height)
        .map(|i| {
            let (x, y) = (i % width, i / width);
            AXIAL.iter().chain(&DIAGONAL).enumerate().fold(0u8, |mask, (bit, &(dx, dy))| {
                if link_exists(c, width, height, x, y, dx, dy).is_some() {
                    mask | 1 << bit
                } else {
                    mask
                }
            })
        })
        .collect()
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
pub fn interior_row<const AX: bool, const DG: bool, M: LinkMask, GA: Field, GB: Field, R: RestRow>(
    c: &Coeffs,
    links: M,
    ga: GA,
    gb: GB,
    mut rest: R,
    r: &Rows,
    out: &mut [f32],
) {
    let w = out.len();
    let (up, mid, down) = (&r.up[..w], &r.mid[..w], &r.down[..w]);
    let (up_p, mid_p, down_p) = (&r.up_p[..w], &r.mid_p[..w], &r.down_p[..w]);
    for x in 1..w - 1 {
        let m = links.at(x);
        let on = |bit: u8, v: f32| if m & (1 << bit) != 0 { v } else { 0.0 };
        let mut sums = [0.0f32; 4];
        let (mut n_ax, mut n_dg) = (0.0f32, 0.0f32);
        if AX {
            sums[0] = (on(0, mid[x - 1]) + on(1, mid[x + 1])) + (on(2, up[x]) + on(3, down[x]));
            sums[1] = (on(0, mid_p[x - 1]) + on(1, mid_p[x + 1])) + (on(2, up_p[x]) + on(3, down_p[x]));
            n_ax = (m & 0x0F).count_ones() as f32;
        }
        if DG {
            sums[2] = (on(4, up[x - 1]) + on(5, down[x - 1])) + (on(6, up[x + 1]) + on(7, down[x + 1]));
            sums[3] = (on(4, up_p[x - 1]) + on(5, down_p[x - 1])) + (on(6, up_p[x + 1]) + on(7, down_p[x + 1]));
            n_dg = (m & 0xF0).count_ones() as f32;
        }
        let self_a = n_ax * c.axial_a + n_dg * c.diag_a;
        let self_b = n_ax * c.axial_b + n_dg * c.diag_b;
        let rest_x = rest.rest(c, x, mid[x]);
        out[x] = combine(c, sums, self_a, self_b, ga.at(x), gb.at(x), rest_x, mid[x], mid_p[x]);
    }
}
