// The mesh raycaster's boundary faces binned into 8x8-pixel tiles on the device: the twin
// of `bin_boundary` in cpu.rs, from the node positions as they are on the device.
// `count_tiles` counts the faces each tile's box list gets, `scan_tiles` turns the counts
// into starts (one workgroup), `fill_tiles` writes the faces. Within a tile the faces come
// in whatever order the atomics give (the CPU lists them in boundary order); the walk
// takes the nearest hit, so only exact ties can tell.

struct Params {
    // world_from_camera: rotation columns and the anchored eye.
    cam_x: vec4<f32>,
    cam_y: vec4<f32>,
    cam_z: vec4<f32>,
    cam_pos: vec4<f32>,
    // perspective (1) or orthographic (0), tan(fov/2) or ortho height, aspect, -
    proj: vec4<f32>,
    // width, height, tiles across, tiles down
    image: vec4<u32>,
    // boundary faces, tiles in all, face capacity, row width of the face dispatch grid
    counts: vec4<u32>,
}

const TILE: u32 = 8u;

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> nodes: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> tets: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> boundary: array<u32>;
@group(0) @binding(4) var<storage, read_write> cursor: array<atomic<u32>>;
// starts of the tiles (tiles + 1 entries, the last one the total), then the faces
@group(0) @binding(5) var<storage, read_write> tiles: array<u32>;

fn tile_of(v: f32, n: u32) -> u32 {
    return min(u32(max(v, 0.0)) / TILE, n - 1u);
}

// (x0, x1, y0, y1) of the tiles face `id` (tet · 4 + face) covers; x0 > x1 when none.
fn tile_box(id: u32) -> vec4<u32> {
    let none = vec4<u32>(1u, 0u, 0u, 0u);
    let all = vec4<u32>(0u, p.image.z - 1u, 0u, p.image.w - 1u);
    var faces = array<vec3<u32>, 4>(vec3<u32>(1u, 2u, 3u), vec3<u32>(0u, 3u, 2u), vec3<u32>(0u, 1u, 3u), vec3<u32>(0u, 2u, 1u));
    let ids = tets[id >> 2u];
    let f = faces[id & 3u];
    var corner = array<u32, 3>(ids[f.x], ids[f.y], ids[f.z]);
    var c: array<vec3<f32>, 3>;
    var ahead = false;
    for (var i = 0u; i < 3u; i++) {
        let q = nodes[corner[i]].xyz - p.cam_pos.xyz;
        c[i] = vec3<f32>(dot(p.cam_x.xyz, q), dot(p.cam_y.xyz, q), dot(p.cam_z.xyz, q));
        ahead = ahead || c[i].z > 0.0;
    }
    if !ahead {
        return none;
    }
    let w = f32(p.image.x);
    let h = f32(p.image.y);
    var lo = vec2<f32>(1e30);
    var hi = vec2<f32>(-1e30);
    for (var i = 0u; i < 3u; i++) {
        var uv: vec2<f32>;
        if p.proj.x > 0.5 {
            if c[i].z <= 1e-9 {
                return all;
            }
            uv = vec2<f32>(c[i].x / c[i].z / (p.proj.y * p.proj.z), c[i].y / c[i].z / p.proj.y);
        } else {
            uv = vec2<f32>(c[i].x / (p.proj.y / 2.0 * p.proj.z), c[i].y / (p.proj.y / 2.0));
        }
        let px = vec2<f32>((uv.x + 1.0) / 2.0 * w - 0.5, (uv.y + 1.0) / 2.0 * h - 0.5);
        lo = min(lo, px);
        hi = max(hi, px);
    }
    // One pixel of margin: the hit test has a tolerance, the box must not be tighter.
    if hi.x < -1.0 || hi.y < -1.0 || lo.x > w || lo.y > h {
        return none;
    }
    return vec4<u32>(tile_of(lo.x - 1.0, p.image.z), tile_of(hi.x + 1.0, p.image.z), tile_of(lo.y - 1.0, p.image.w), tile_of(hi.y + 1.0, p.image.w));
}

@compute @workgroup_size(64)
fn count_tiles(@builtin(global_invocation_id) gid: vec3<u32>) {
    let f = gid.x + gid.y * p.counts.w * 64u;
    if f >= p.counts.x {
        return;
    }
    let b = tile_box(boundary[f]);
    for (var ty = b.z; ty <= b.w && b.x <= b.y; ty++) {
        for (var tx = b.x; tx <= b.y; tx++) {
            atomicAdd(&cursor[ty * p.image.z + tx], 1u);
        }
    }
}

const SCAN: u32 = 256u;
var<workgroup> partial: array<u32, 256>;

// Exclusive prefix sum of the counts into the starts; each tile's cursor restarts there.
@compute @workgroup_size(256)
fn scan_tiles(@builtin(local_invocation_id) lid: vec3<u32>) {
    let n = p.counts.y;
    let chunk = (n + SCAN - 1u) / SCAN;
    let first = min(lid.x * chunk, n);
    let last = min(first + chunk, n);
    var sum = 0u;
    for (var t = first; t < last; t++) {
        sum += atomicLoad(&cursor[t]);
    }
    partial[lid.x] = sum;
    workgroupBarrier();
    if lid.x == 0u {
        var running = 0u;
        for (var i = 0u; i < SCAN; i++) {
            let v = partial[i];
            partial[i] = running;
            running += v;
        }
        tiles[n] = running;
    }
    workgroupBarrier();
    var start = partial[lid.x];
    for (var t = first; t < last; t++) {
        let count = atomicLoad(&cursor[t]);
        tiles[t] = start;
        atomicStore(&cursor[t], start);
        start += count;
    }
}

@compute @workgroup_size(64)
fn fill_tiles(@builtin(global_invocation_id) gid: vec3<u32>) {
    let f = gid.x + gid.y * p.counts.w * 64u;
    if f >= p.counts.x {
        return;
    }
    let id = boundary[f];
    let b = tile_box(id);
    let base = p.counts.y + 1u;
    for (var ty = b.z; ty <= b.w && b.x <= b.y; ty++) {
        for (var tx = b.x; tx <= b.y; tx++) {
            let slot = atomicAdd(&cursor[ty * p.image.z + tx], 1u);
            if slot < p.counts.z {
                tiles[base + slot] = id;
            }
        }
    }
}
