// One DPCM step: Z(n+1) = 2 Z(n) - Z(n-1) + F h²/m for every phyxel, on u = Z - rest
// height, markers gathered from the phyxel's tile list. Line by line the twin of
// src/dpcm/kernel.rs (phyxel_update, family_sums, combine, plastic_rest, marker_term) and
// of Surface's tile loop.

struct Coeffs {
    ground_a: f32,
    ground_b: f32,
    axial_a: f32,
    axial_b: f32,
    axial_ab: f32,
    diag_a: f32,
    diag_b: f32,
    diag_ab: f32,
    plastic_threshold: f32,
    link_keep: u32,
    link_seed: u32,
    has_axial: u32,
    has_diagonal: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

struct Params {
    c: Coeffs,
    width: u32,
    height: u32,
    tiles_x: u32,
    // bit 0: per-phyxel ground coefficients; bit 1: per-phyxel rest points.
    flags: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
    _pad3: u32,
}

struct Marker {
    col: f32,
    row: f32,
    height: f32,
    step_dz: f32,
    stiffness_a: f32,
    damping_b: f32,
    threshold: f32,
    z_scale: f32,
}

// Which step of a batch this dispatch is: its markers' tile lists start at tile_offsets[offsets_base].
struct BatchStep {
    offsets_base: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

const TILE: u32 = 16u;
// kernels::FLUSH_BELOW: subnormal-free, as on the CPU.
const FLUSH_BELOW: f32 = 1e-20;

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> u: array<f32>;
@group(0) @binding(2) var<storage, read> up: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<f32>;
@group(0) @binding(4) var<storage, read_write> rest: array<f32>;
@group(0) @binding(5) var<storage, read> ground_a: array<f32>;
@group(0) @binding(6) var<storage, read> ground_b: array<f32>;
@group(0) @binding(7) var<storage, read> markers: array<Marker>;
@group(0) @binding(8) var<storage, read> tile_offsets: array<u32>;
@group(0) @binding(9) var<storage, read> tile_indices: array<u32>;
@group(0) @binding(10) var<uniform> batch: BatchStep;

fn hash32(v: u32) -> u32 {
    var x = v;
    x ^= x >> 16u;
    x *= 0x7feb352du;
    x ^= x >> 15u;
    x *= 0x846ca68bu;
    x ^= x >> 16u;
    return x;
}

fn link_kept(owner: u32, dir: u32) -> bool {
    return (hash32((owner * 4u + dir) ^ p.c.link_seed) >> 8u) < p.c.link_keep;
}

// The undirected link from (x, y) to (x + dx, y + dy): (owner index, canonical direction).
fn canonical(x: i32, y: i32, dx: i32, dy: i32) -> vec2<u32> {
    var o = vec3<i32>(x + 1, y - 1, 3); // (1, -1)
    if dx == 1 && dy == 0 { o = vec3<i32>(x, y, 0); }
    if dx == -1 && dy == 0 { o = vec3<i32>(x - 1, y, 0); }
    if dx == 0 && dy == 1 { o = vec3<i32>(x, y, 1); }
    if dx == 0 && dy == -1 { o = vec3<i32>(x, y - 1, 1); }
    if dx == 1 && dy == 1 { o = vec3<i32>(x, y, 2); }
    if dx == -1 && dy == -1 { o = vec3<i32>(x - 1, y - 1, 2); }
    if dx == -1 && dy == 1 { o = vec3<i32>(x, y, 3); }
    return vec2<u32>(u32(o.y) * p.width + u32(o.x), u32(o.z));
}

// The link from (x, y) towards d, when inside the grid and drawn: its index, or -1.
fn link_exists(x: i32, y: i32, d: vec2<i32>) -> i32 {
    let nx = x + d.x;
    let ny = y + d.y;
    if nx < 0 || ny < 0 || u32(nx) >= p.width || u32(ny) >= p.height {
        return -1;
    }
    let link = canonical(x, y, d.x, d.y);
    if !link_kept(link.x, link.y) {
        return -1;
    }
    return ny * i32(p.width) + nx;
}

// A family's (Σu_j, Σup_j, n), summed as ((d0 + d1) + (d2 + d3)).
fn family_sums(order: array<vec2<i32>, 4>, x: i32, y: i32) -> vec3<f32> {
    var su = array<f32, 4>(0.0, 0.0, 0.0, 0.0);
    var sp = array<f32, 4>(0.0, 0.0, 0.0, 0.0);
    var n = 0.0;
    for (var k = 0u; k < 4u; k++) {
        let j = link_exists(x, y, order[k]);
        if j >= 0 {
            su[k] = u[j];
            sp[k] = up[j];
            n += 1.0;
        }
    }
    return vec3<f32>((su[0] + su[1]) + (su[2] + su[3]), (sp[0] + sp[1]) + (sp[2] + sp[3]), n);
}

fn combine(sums: vec4<f32>, self_a: f32, self_b: f32, ga: f32, gb: f32, r: f32, ui: f32, upi: f32) -> f32 {
    let v = ui - upi;
    let links = ((p.c.axial_ab * sums.x - p.c.axial_b * sums.y) + (p.c.diag_ab * sums.z - p.c.diag_b * sums.w)) - (self_a * ui + self_b * v);
    let ground = ga * (ui - r) + gb * v;
    let next = 2.0 * ui - upi + (links - ground);
    return select(next, 0.0, abs(next) < FLUSH_BELOW);
}

fn plastic_rest(r: f32, ui: f32) -> f32 {
    if p.c.plastic_threshold < 0.0 {
        return r;
    }
    return min(max(r, ui - p.c.plastic_threshold), ui + p.c.plastic_threshold);
}

fn marker_term(m: Marker, x: f32, y: f32, ui: f32, v: f32) -> f32 {
    let dx = x - m.col;
    let dy = y - m.row;
    let dz = (ui - m.height) * m.z_scale;
    let d2 = dx * dx + dy * dy + dz * dz;
    if d2 >= m.threshold * m.threshold {
        return 0.0;
    }
    let d = sqrt(d2);
    var dir = -1.0;
    if d > 0.0 {
        dir = dz / d;
    }
    return m.stiffness_a * (m.threshold - d) * dir + m.damping_b * (m.step_dz - v);
}

@compute @workgroup_size(16, 16)
fn step(@builtin(global_invocation_id) gid: vec3<u32>) {
    if gid.x >= p.width || gid.y >= p.height {
        return;
    }
    let x = i32(gid.x);
    let y = i32(gid.y);
    let i = gid.y * p.width + gid.x;
    let ui = u[i];
    let vi = u[i] - up[i];

    var r = 0.0;
    if (p.flags & 2u) != 0u {
        r = plastic_rest(rest[i], ui);
        rest[i] = r;
    }
    var ga = p.c.ground_a;
    var gb = p.c.ground_b;
    if (p.flags & 1u) != 0u {
        ga = ground_a[i];
        gb = ground_b[i];
    }
    var ax = vec3<f32>(0.0, 0.0, 0.0);
    var dg = vec3<f32>(0.0, 0.0, 0.0);
    if p.c.has_axial != 0u {
        ax = family_sums(array<vec2<i32>, 4>(vec2<i32>(-1, 0), vec2<i32>(1, 0), vec2<i32>(0, -1), vec2<i32>(0, 1)), x, y);
    }
    if p.c.has_diagonal != 0u {
        dg = family_sums(array<vec2<i32>, 4>(vec2<i32>(-1, -1), vec2<i32>(-1, 1), vec2<i32>(1, -1), vec2<i32>(1, 1)), x, y);
    }
    let self_a = ax.z * p.c.axial_a + dg.z * p.c.diag_a;
    let self_b = ax.z * p.c.axial_b + dg.z * p.c.diag_b;
    let base = combine(vec4<f32>(ax.x, ax.y, dg.x, dg.y), self_a, self_b, ga, gb, r, ui, up[i]);

    let tile = batch.offsets_base + (gid.y / TILE) * p.tiles_x + gid.x / TILE;
    var push = 0.0;
    for (var k = tile_offsets[tile]; k < tile_offsets[tile + 1u]; k++) {
        push += marker_term(markers[tile_indices[k]], f32(gid.x), f32(gid.y), ui, vi);
    }
    out[i] = base + push;
}
