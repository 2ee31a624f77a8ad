// Grid warp by exact row spans: the GPU twin of the `Spans` scheme in kernels.rs (rasterize_slice).
// - `tet_maps`: per tet, its maps from the deformed nodes (output index space) and the rest
//   nodes (source index space), as `tet_map` computes them in f64; rebased on the tet's box
//   corner so f32 keeps precision in voxel-local coordinates; and its box's row count;
// - `scan_rows`, `scan_blocks`: a prefix sum of the row counts over all tets, and from its
//   total the dispatch of `warp_rows`;
// - `warp_rows`: one invocation a row of any tet's box, so big and small tets spread evenly
//   over the GPU; its exact span (TetMap::span, rasterize_slice) sampled trilinear or
//   tricubic (Catmull-Rom) as the CPU's Sampler does (Sampler::trilinear_run); the voxels
//   written marked covered;
// - `fill`: every voxel no tet covered gets the background, or with keep_uncovered the
//   source's value at the same place (Sampler::at through the identity map, as
//   `initial_value`).
struct Params {
    out_dims: vec4<u32>,   // nx, ny, nz, tet count
    src_dims: vec4<u32>,   // nx, ny, nz, displacement volumes
    background: vec4<f32>, // background, inside tolerance, sample tolerance, keep_uncovered (1/0)
    identity: array<vec4<f32>, 3>, // source index from output index, rows (offset, di, dj, dk)
    groups: vec4<u32>,     // row widths of the fill and tet-map dispatch grids, 0, sampling (0 trilinear, 1 tricubic)
    scan: vec4<u32>,       // row width of the scan_rows grid, its blocks (256 tets each)
}

@group(0) @binding(0) var<uniform> params: Params;
// Per tet, 9 vec4: bary rows 0-3 (b = x + y·i + z·j + w·k, local), source rows 0-2
// (likewise), box low corner (xyz), box size (xyz; 0 marks a skipped tet).
@group(0) @binding(1) var<storage, read_write> maps: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> source: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<f32>;
// Deformed nodes in output index space (xyz), rest nodes in source index space (xyz).
@group(0) @binding(4) var<storage, read> nodes: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> rest: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read> tets: array<vec4<u32>>;
// Voxels written from inside a tet; tets skipped (inverted, flat, or off the grid); 1 where
// the tets' rows overflow u32; unused; from COVERAGE on, a bit per output voxel written.
@group(0) @binding(7) var<storage, read_write> stats: array<atomic<u32>>;
// Displacement volumes in source index space (CompiledDisplacement::in_space), 4 vec4 each:
// the rows of l = A·p + a (xyz: A's row, w: a), then the displacement in index units (xyz).
@group(0) @binding(8) var<storage, read> pushes: array<vec4<f32>>;

// Per tet its box's row count, then (scan_rows) its first row within its block of 256
// tets; after the tets, per block its first row (scan_blocks). Before ROWS: warp_rows'
// dispatch (x, y, 1) and the total rows.
@group(0) @binding(9) var<storage, read_write> rows: array<u32>;

const WG: u32 = 64u;
const ROWS: u32 = 4u;
const COVERAGE: u32 = 4u;

fn inside(a: vec4<f32>, c: vec4<f32>, i: f32) -> bool {
    let b = a + c * i;
    return all(b >= vec4<f32>(0.0));
}

// p clamped into the source's voxel-centre box; w = 0 where p lies beyond the sample
// tolerance outside it (clamp_to_box: the sample is then the background).
fn in_source(p: vec3<f32>) -> vec4<f32> {
    let top = vec3<f32>(params.src_dims.xyz) - vec3<f32>(1.0);
    let tol = params.background.z;
    let outside = any(p < vec3<f32>(-tol)) || any(p > top + vec3<f32>(tol));
    return vec4<f32>(clamp(p, vec3<f32>(0.0), top), select(1.0, 0.0, outside));
}

fn trilinear(p: vec3<f32>) -> f32 {
    let at = in_source(p);
    if (at.w == 0.0) {
        return params.background.x;
    }
    let q = at.xyz;
    let cell = min(vec3<u32>(q), max(params.src_dims.xyz, vec3<u32>(2u)) - vec3<u32>(2u));
    let f = q - vec3<f32>(cell);
    let nx = params.src_dims.x;
    let nxy = params.src_dims.x * params.src_dims.y;
    let sx = select(0u, 1u, params.src_dims.x > 1u);
    let sy = select(0u, nx, params.src_dims.y > 1u);
    let sz = select(0u, nxy, params.src_dims.z > 1u);
    let b = cell.x + nx * cell.y + nxy * cell.z;
    let c00 = mix(source[b], source[b + sx], f.x);
    let c10 = mix(source[b + sy], source[b + sy + sx], f.x);
    let c01 = mix(source[b + sz], source[b + sz + sx], f.x);
    let c11 = mix(source[b + sz + sy], source[b + sz + sy + sx], f.x);
    return mix(mix(c00, c10, f.y), mix(c01, c11, f.y), f.z);
}

// Catmull-Rom weights of the four taps around t in [0, 1) (volume::catmull_rom).
fn catmull_rom(t: f32) -> vec4<f32> {
    let t2 = t * t;
    let t3 = t2 * t;
    return 0.5 * vec4<f32>(-t3 + 2.0 * t2 - t, 3.0 * t3 - 5.0 * t2 + 2.0, -3.0 * t3 + 4.0 * t2 + t, t3 - t2);
}

// Tricubic (Catmull-Rom) sample, the twin of volume::tricubic: taps beyond the edges repeat
// the edge voxel; beyond the sample tolerance outside the voxel-centre box, the background.
fn tricubic(p: vec3<f32>) -> f32 {
    let at = in_source(p);
    if (at.w == 0.0) {
        return params.background.x;
    }
    let q = at.xyz;
    let b = vec3<i32>(floor(q));
    let f = q - vec3<f32>(b);
    let wx = catmull_rom(f.x);
    let wy = catmull_rom(f.y);
    let wz = catmull_rom(f.z);
    let n = vec3<i32>(params.src_dims.xyz);
    var acc = 0.0;
    for (var c = 0; c < 4; c = c + 1) {
        let kk = clamp(b.z + c - 1, 0, n.z - 1);
        for (var r = 0; r < 4; r = r + 1) {
            let jj = clamp(b.y + r - 1, 0, n.y - 1);
            let row = n.x * (jj + n.y * kk);
            var line = 0.0;
            for (var a = 0; a < 4; a = a + 1) {
                line = line + wx[a] * source[u32(row + clamp(b.x + a - 1, 0, n.x - 1))];
            }
            acc = acc + wz[c] * wy[r] * line;
        }
    }
    return acc;
}

// Quadratic B-spline of support [-1, 1], 1 at 0 (bspline::quadratic_bspline).
fn quadratic_bspline(x: f32) -> f32 {
    let t = (x + 1.0) * 1.5;
    var b = 0.0;
    if (t >= 0.0 && t < 1.0) {
        b = 0.5 * t * t;
    } else if (t >= 1.0 && t < 2.0) {
        b = 0.5 * (-2.0 * t * t + 6.0 * t - 3.0);
    } else if (t >= 2.0 && t < 3.0) {
        b = 0.5 * (3.0 - t) * (3.0 - t);
    }
    return b / 0.75;
}

// The backward map of the displacement volumes, the last applied first (bspline::backward_all).
fn displaced(p: vec3<f32>) -> vec3<f32> {
    var q = p;
    for (var v = i32(params.src_dims.w) - 1; v >= 0; v = v - 1) {
        let base = u32(v) * 4u;
        let l = vec3<f32>(dot(pushes[base].xyz, q), dot(pushes[base + 1u].xyz, q), dot(pushes[base + 2u].xyz, q))
            + vec3<f32>(pushes[base].w, pushes[base + 1u].w, pushes[base + 2u].w);
        let along = select(quadratic_bspline(l.z / 2.0), quadratic_bspline(l.z), l.z < 0.0);
        q = q - quadratic_bspline(l.x) * quadratic_bspline(l.y) * along * pushes[base + 3u].xyz;
    }
    return q;
}

// The source at p after the displacement volumes, as Sampler::at.
fn sample(p: vec3<f32>) -> f32 {
    let q = displaced(p);
    if (params.groups.w == 1u) {
        return tricubic(q);
    }
    return trilinear(q);
}

@compute @workgroup_size(64)
fn fill(@builtin(global_invocation_id) gid: vec3<u32>) {
    let v = gid.x + gid.y * params.groups.x * WG;
    if (v >= arrayLength(&out) || ((atomicLoad(&stats[COVERAGE + v / 32u]) >> (v & 31u)) & 1u) == 1u) {
        return;
    }
    if (params.background.w == 0.0) {
        out[v] = params.background.x;
        return;
    }
    let nx = params.out_dims.x;
    let ny = params.out_dims.y;
    let ijk = vec3<f32>(f32(v % nx), f32((v / nx) % ny), f32(v / (nx * ny)));
    let r = params.identity;
    out[v] = sample(vec3<f32>(dot(r[0], vec4<f32>(1.0, ijk)), dot(r[1], vec4<f32>(1.0, ijk)), dot(r[2], vec4<f32>(1.0, ijk))));
}

fn skip_tet(t: u32, base: u32) {
    maps[base + 8u] = vec4<f32>(0.0);
    rows[ROWS + t] = 0u;
    atomicAdd(&stats[1], 1u);
}

@compute @workgroup_size(64)
fn tet_maps(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = gid.x + gid.y * params.groups.y * WG;
    if (t >= params.out_dims.w) {
        return;
    }
    let ids = tets[t];
    let base = t * 9u;
    let p0 = nodes[ids.x].xyz;
    let p1 = nodes[ids.y].xyz;
    let p2 = nodes[ids.z].xyz;
    let p3 = nodes[ids.w].xyz;
    let stol = params.background.z;
    let top = vec3<f32>(params.out_dims.xyz) - vec3<f32>(1.0);
    // The box, widened by the sample tolerance (a vertex at 38.9999999 still covers 39).
    let lo = max(ceil(min(min(p0, p1), min(p2, p3)) - vec3<f32>(stol)), vec3<f32>(0.0));
    let hi = min(floor(max(max(p0, p1), max(p2, p3)) + vec3<f32>(stol)), top);
    if (any(lo > hi)) {
        skip_tet(t, base);
        return;
    }
    let e1 = p1 - p0;
    let e2 = p2 - p0;
    let e3 = p3 - p0;
    let q0 = rest[ids.x].xyz;
    let f1 = rest[ids.y].xyz - q0;
    let f2 = rest[ids.z].xyz - q0;
    let f3 = rest[ids.w].xyz - q0;
    let det = dot(e1, cross(e2, e3));
    let rest_det = dot(f1, cross(f2, f3));
    // Same orientation as at rest, and not flat: |det| against the cube of the longest edge.
    let longest = max(max(max(length(e1), length(e2)), max(length(e3), length(p2 - p1))), max(length(p3 - p1), length(p3 - p2)));
    if (det * rest_det <= 0.0 || abs(det) < 1e-9 * longest * longest * longest) {
        skip_tet(t, base);
        return;
    }
    // Rows of the inverse of the edge matrix (columns e1, e2, e3).
    let r0 = cross(e2, e3) / det;
    let r1 = cross(e3, e1) / det;
    let r2 = cross(e1, e2) / det;
    let l0 = p0 - lo;
    let b1 = vec4<f32>(-dot(r0, l0), r0);
    let b2 = vec4<f32>(-dot(r1, l0), r1);
    let b3 = vec4<f32>(-dot(r2, l0), r2);
    maps[base] = vec4<f32>(1.0, 0.0, 0.0, 0.0) - b1 - b2 - b3;
    maps[base + 1u] = b1;
    maps[base + 2u] = b2;
    maps[base + 3u] = b3;
    // Source index: q0 + Q · inverse · (x - l0), Q with columns f1, f2, f3.
    let mx = f1.x * r0 + f2.x * r1 + f3.x * r2;
    let my = f1.y * r0 + f2.y * r1 + f3.y * r2;
    let mz = f1.z * r0 + f2.z * r1 + f3.z * r2;
    maps[base + 4u] = vec4<f32>(q0.x - dot(mx, l0), mx);
    maps[base + 5u] = vec4<f32>(q0.y - dot(my, l0), my);
    maps[base + 6u] = vec4<f32>(q0.z - dot(mz, l0), mz);
    maps[base + 7u] = vec4<f32>(lo, 0.0);
    let size = hi - lo + vec3<f32>(1.0);
    maps[base + 8u] = vec4<f32>(size, 0.0);
    rows[ROWS + t] = u32(size.y) * u32(size.z);
}

// A tet's maps as warp_row reads them.
struct TetMaps {
    b: array<vec4<f32>, 4>,
    s: array<vec4<f32>, 3>,
    lo: vec3<u32>,
    size: vec3<u32>,
}

fn tet_maps_of(t: u32) -> TetMaps {
    let base = t * 9u;
    var m: TetMaps;
    m.b = array<vec4<f32>, 4>(maps[base], maps[base + 1u], maps[base + 2u], maps[base + 3u]);
    m.s = array<vec4<f32>, 3>(maps[base + 4u], maps[base + 5u], maps[base + 6u]);
    m.lo = vec3<u32>(maps[base + 7u].xyz);
    m.size = vec3<u32>(maps[base + 8u].xyz);
    return m;
}

// Marks output voxels first..=last covered, for `fill` to pass over.
fn cover(first: u32, last: u32) {
    var v = first;
    loop {
        if (v > last) {
            break;
        }
        let end = min(last, v | 31u);
        let n = end - v + 1u;
        let bits = select(((1u << n) - 1u) << (v & 31u), 0xffffffffu, n == 32u);
        atomicOr(&stats[COVERAGE + v / 32u], bits);
        v = end + 1u;
    }
}

// Row r (j fastest) of a tet's box: its exact span (TetMap::span, rasterize_slice) sampled
// trilinear or tricubic (Sampler::trilinear_run); returns the voxels written.
fn warp_row(m: TetMaps, r: u32) -> u32 {
    let jl = f32(r % m.size.y);
    let kl = f32(r / m.size.y);
    let b = m.b;
    let a = vec4<f32>(b[0].x + b[0].z * jl + b[0].w * kl, b[1].x + b[1].z * jl + b[1].w * kl, b[2].x + b[2].z * jl + b[2].w * kl, b[3].x + b[3].z * jl + b[3].w * kl) + vec4<f32>(params.background.y);
    let c = vec4<f32>(b[0].y, b[1].y, b[2].y, b[3].y);
    var first = 0.0;
    var last = f32(m.size.x - 1u);
    for (var q = 0u; q < 4u; q = q + 1u) {
        if (c[q] > 0.0) {
            first = max(first, ceil(-a[q] / c[q]));
        } else if (c[q] < 0.0) {
            last = min(last, floor(-a[q] / c[q]));
        } else if (a[q] < 0.0) {
            return 0u;
        }
    }
    // Widen by one, then settle on the evaluated predicate (as TetMap::span does).
    var i0 = i32(clamp(first - 1.0, 0.0, f32(m.size.x - 1u)));
    var i1 = i32(clamp(last + 1.0, 0.0, f32(m.size.x - 1u)));
    while (i0 <= i1 && !inside(a, c, f32(i0))) {
        i0 = i0 + 1;
    }
    while (i1 >= i0 && !inside(a, c, f32(i1))) {
        i1 = i1 - 1;
    }
    if (i1 < i0) {
        return 0u;
    }
    let row = (m.lo.y + r % m.size.y) * params.out_dims.x + (m.lo.z + r / m.size.y) * params.out_dims.x * params.out_dims.y + m.lo.x;
    let s = m.s;
    for (var i = i0; i <= i1; i = i + 1) {
        let fi = f32(i);
        let p = vec3<f32>(s[0].x + s[0].y * fi + s[0].z * jl + s[0].w * kl, s[1].x + s[1].y * fi + s[1].z * jl + s[1].w * kl, s[2].x + s[2].y * fi + s[2].z * jl + s[2].w * kl);
        out[row + u32(i)] = sample(p);
    }
    cover(row + u32(i0), row + u32(i1));
    return u32(i1 - i0 + 1);
}

var<workgroup> partial: array<u32, 256>;

// Exclusive prefix sum of the row counts within each block of 256 tets, in place; the
// block's total after the tets' entries.
@compute @workgroup_size(256)
fn scan_rows(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let block = wid.x + wid.y * params.scan.x;
    let n = params.out_dims.w;
    let t = block * 256u + lid.x;
    var count = 0u;
    if (t < n) {
        count = rows[ROWS + t];
    }
    partial[lid.x] = count;
    workgroupBarrier();
    for (var d = 1u; d < 256u; d = d * 2u) {
        var add = 0u;
        if (lid.x >= d) {
            add = partial[lid.x - d];
        }
        workgroupBarrier();
        partial[lid.x] = partial[lid.x] + add;
        workgroupBarrier();
    }
    if (t < n) {
        rows[ROWS + t] = partial[lid.x] - count;
    }
    if (lid.x == 255u && block < params.scan.y) {
        rows[ROWS + n + block] = partial[255u];
    }
}

var<workgroup> wrapped: atomic<u32>;

// Exclusive prefix sum of the blocks' totals, the total rows, and the dispatch of
// warp_rows: a 2D grid of 64-wide workgroups; none where the rows overflow u32 (stats[2]).
@compute @workgroup_size(256)
fn scan_blocks(@builtin(local_invocation_id) lid: vec3<u32>) {
    let blocks = params.scan.y;
    let at = ROWS + params.out_dims.w;
    let chunk = (blocks + 255u) / 256u;
    let first = min(lid.x * chunk, blocks);
    let last = min(first + chunk, blocks);
    var sum = 0u;
    for (var b = first; b < last; b = b + 1u) {
        if (sum + rows[at + b] < sum) {
            atomicStore(&wrapped, 1u);
        }
        sum = sum + rows[at + b];
    }
    partial[lid.x] = sum;
    workgroupBarrier();
    if (lid.x == 0u) {
        var running = 0u;
        for (var i = 0u; i < 256u; i = i + 1u) {
            let v = partial[i];
            partial[i] = running;
            if (running + v < running) {
                atomicStore(&wrapped, 1u);
            }
            running = running + v;
        }
        let over = atomicLoad(&wrapped) != 0u;
        if (over) {
            atomicStore(&stats[2], 1u);
        }
        let groups = select(running / WG + select(0u, 1u, running % WG != 0u), 0u, over);
        let x = min(groups, 65535u);
        rows[0] = x;
        rows[1] = select((groups + x - 1u) / max(x, 1u), 0u, groups == 0u);
        rows[2] = 1u;
        rows[3] = running;
    }
    workgroupBarrier();
    var start = partial[lid.x];
    for (var b = first; b < last; b = b + 1u) {
        let total = rows[at + b];
        rows[at + b] = start;
        start = start + total;
    }
}

// The first row of tet t in the flat order of every tet's rows.
fn row_start(t: u32) -> u32 {
    return rows[ROWS + params.out_dims.w + t / 256u] + rows[ROWS + t];
}

var<workgroup> written_here: atomic<u32>;

// One invocation a row of any tet's box: the tet found by bisection over the row starts.
@compute @workgroup_size(64)
fn warp_rows(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let g = gid.x + gid.y * groups.x * WG;
    var written = 0u;
    if (g < rows[3]) {
        var lo = 0u;
        var hi = params.out_dims.w - 1u;
        while (lo < hi) {
            let mid = (lo + hi + 1u) / 2u;
            if (row_start(mid) <= g) {
                lo = mid;
            } else {
                hi = mid - 1u;
            }
        }
        written = warp_row(tet_maps_of(lo), g - row_start(lo));
    }
    if (written > 0u) {
        atomicAdd(&written_here, written);
    }
    workgroupBarrier();
    if (lid.x == 0u) {
        let total = atomicLoad(&written_here);
        if (total > 0u) {
            atomicAdd(&stats[0], total);
        }
    }
}
