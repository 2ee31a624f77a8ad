// Grid warp by exact row spans: the GPU twin of the `Spans` scheme in src/warp/mod.rs
// (TetMap::span, rasterize_slice, Sampler::trilinear_run). One workgroup per tet; its
// threads take the rows (j, k) of the tet's box in turn. Maps are rebased on the box's
// low corner so f32 keeps precision in voxel-local coordinates.

struct Params {
    out_dims: vec4<u32>,   // nx, ny, nz, tet count
    src_dims: vec4<u32>,   // nx, ny, nz, workgroups per row of the dispatch grid
    background: vec4<f32>, // background, inside tolerance, sample tolerance, -
}

@group(0) @binding(0) var<uniform> params: Params;
// Per tet, 9 vec4: bary rows 0-3 (b = x + y·i + z·j + w·k, local), source rows 0-2
// (likewise), box low corner (xyz), box size (xyz; 0 marks a skipped tet).
@group(0) @binding(1) var<storage, read> tets: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> source: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<f32>;

const WG: u32 = 64u;

fn inside(a: vec4<f32>, c: vec4<f32>, i: f32) -> bool {
    let b = a + c * i;
    return all(b >= vec4<f32>(0.0));
}

fn trilinear(p: vec3<f32>) -> f32 {
    let dims = vec3<f32>(params.src_dims.xyz);
    let tol = params.background.z;
    let top = dims - vec3<f32>(1.0);
    if (any(p < vec3<f32>(-tol)) || any(p > top + vec3<f32>(tol))) {
        return params.background.x;
    }
    let q = clamp(p, vec3<f32>(0.0), top);
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

@compute @workgroup_size(64)
fn fill_background(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.x + gid.y * groups.x * WG;
    if (i < arrayLength(&out)) {
        out[i] = params.background.x;
    }
}

@compute @workgroup_size(64)
fn warp_tets(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let t = wid.x + wid.y * params.src_dims.w;
    if (t >= params.out_dims.w) {
        return;
    }
    let base = t * 9u;
    let size = vec3<u32>(tets[base + 8u].xyz);
    if (size.x == 0u) {
        return;
    }
    let lo = vec3<u32>(tets[base + 7u].xyz);
    // Barycentric rows as columns of per-coordinate vectors: a(j, k) and the i slope.
    let b0 = tets[base];
    let b1 = tets[base + 1u];
    let b2 = tets[base + 2u];
    let b3 = tets[base + 3u];
    let c = vec4<f32>(b0.y, b1.y, b2.y, b3.y);
    let s0 = tets[base + 4u];
    let s1 = tets[base + 5u];
    let s2 = tets[base + 6u];
    let rows = size.y * size.z;
    let nx = params.out_dims.x;
    let nxy = params.out_dims.x * params.out_dims.y;
    let tol = params.background.y;
    for (var r = lid.x; r < rows; r = r + WG) {
        let jl = f32(r % size.y);
        let kl = f32(r / size.y);
        let a = vec4<f32>(b0.x + b0.z * jl + b0.w * kl, b1.x + b1.z * jl + b1.w * kl, b2.x + b2.z * jl + b2.w * kl, b3.x + b3.z * jl + b3.w * kl) + vec4<f32>(tol);
        var first = 0.0;
        var last = f32(size.x - 1u);
        var empty = false;
        for (var m = 0u; m < 4u; m = m + 1u) {
            if (c[m] > 0.0) {
                first = max(first, ceil(-a[m] / c[m]));
            } else if (c[m] < 0.0) {
                last = min(last, floor(-a[m] / c[m]));
            } else if (a[m] < 0.0) {
                empty = true;
            }
        }
        if (empty) {
            continue;
        }
        // Widen by one, then settle on the evaluated predicate (as TetMap::span does).
        var i0 = i32(clamp(first - 1.0, 0.0, f32(size.x - 1u)));
        var i1 = i32(clamp(last + 1.0, 0.0, f32(size.x - 1u)));
        while (i0 <= i1 && !inside(a, c, f32(i0))) {
            i0 = i0 + 1;
        }
        while (i1 >= i0 && !inside(a, c, f32(i1))) {
            i1 = i1 - 1;
        }
        let row = (lo.y + r % size.y) * nx + (lo.z + r / size.y) * nxy + lo.x;
        for (var i = i0; i <= i1; i = i + 1) {
            let fi = f32(i);
            let p = vec3<f32>(s0.x + s0.y * fi + s0.z * jl + s0.w * kl, s1.x + s1.y * fi + s1.z * jl + s1.w * kl, s2.x + s2.y * fi + s2.z * jl + s2.w * kl);
            out[row + u32(i)] = trilinear(p);
        }
    }
}
