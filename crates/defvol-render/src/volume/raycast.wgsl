// The volume raycaster, one invocation per pixel: line by line the twin of
// volume/cpu.rs (Caster::cast, composite, iso, shade, sample; Tables::sample and
// segment; MacroCells::visible_at and exit; clip); Camera::ray and the tools are
// camera_tools.wgsl's, compiled in front of this file. `macro_cells` is MacroCells::new,
// run on the device when the volume is a device buffer another stage rewrites (the warp).

struct Params {
    // world_from_camera: rotation columns and the eye.
    cam_x: vec4<f32>,
    cam_y: vec4<f32>,
    cam_z: vec4<f32>,
    cam_pos: vec4<f32>,
    // index_from_world columns, and the volume's world origin.
    ifw_x: vec4<f32>,
    ifw_y: vec4<f32>,
    ifw_z: vec4<f32>,
    vol_origin: vec4<f32>,
    dims: vec4<u32>,
    cells: vec4<u32>,
    // width, height, mode (0 composite, 1 mip, 2 iso), flags (1 pre-integrated, 2 skipping)
    image: vec4<u32>,
    // perspective (1) or orthographic (0), tan(fov/2) or ortho height, aspect, step
    proj: vec4<f32>,
    // lut lo, lut hi, pre-integrated lo, hi
    tf: vec4<f32>,
    // direction toward the light (world), w = 1 when given (else the headlight)
    light: vec4<f32>,
    // ambient, early termination, iso value, gradient scale
    misc: vec4<f32>,
    background: vec4<f32>,
    // shading (0 none, 1 gradient, 2 forward difference), tool count
    shading: vec4<u32>,
    // per tool: tip and radius, tail, colour
    tools: array<vec4<f32>, 12>,
}

const LUT_SIZE: u32 = 1024u;
const PRE_SIZE: u32 = 512u;
const CELL: f32 = 8.0;

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> volume: array<f32>;
@group(0) @binding(2) var<storage, read> lut: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> pre: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> cells: array<u32>;
@group(0) @binding(5) var<storage, read_write> out_rgba: array<u32>;
@group(0) @binding(6) var<storage, read_write> out_depth: array<f32>;

fn voxel(i: u32, j: u32, k: u32) -> f32 {
    return volume[i + p.dims.x * (j + p.dims.y * k)];
}

fn sample(q: vec3<f32>) -> f32 {
    let n = vec3<f32>(p.dims.xyz);
    let c = clamp(q, vec3<f32>(0.0), n - 1.0);
    let i = min(vec3<u32>(c), max(p.dims.xyz, vec3<u32>(2u)) - 2u);
    let f = c - vec3<f32>(i);
    let i1 = min(i + 1u, p.dims.xyz - 1u);
    let c00 = voxel(i.x, i.y, i.z) + (voxel(i1.x, i.y, i.z) - voxel(i.x, i.y, i.z)) * f.x;
    let c10 = voxel(i.x, i1.y, i.z) + (voxel(i1.x, i1.y, i.z) - voxel(i.x, i1.y, i.z)) * f.x;
    let c01 = voxel(i.x, i.y, i1.z) + (voxel(i1.x, i.y, i1.z) - voxel(i.x, i.y, i1.z)) * f.x;
    let c11 = voxel(i.x, i1.y, i1.z) + (voxel(i1.x, i1.y, i1.z) - voxel(i.x, i1.y, i1.z)) * f.x;
    let c0 = c00 + (c10 - c00) * f.y;
    let c1 = c01 + (c11 - c01) * f.y;
    return c0 + (c1 - c0) * f.z;
}

// The grid grid_gradient.wgsl reads: the volume.
fn grid_dims() -> vec3<u32> {
    return p.dims.xyz;
}

fn grid_voxel(i: u32, j: u32, k: u32) -> f32 {
    return voxel(i, j, k);
}

fn lut_sample(s: f32) -> vec4<f32> {
    let x = clamp((s - p.tf.x) / (p.tf.y - p.tf.x), 0.0, 1.0) * f32(LUT_SIZE - 1u);
    let i = min(u32(x), LUT_SIZE - 2u);
    let f = x - f32(i);
    return lut[i] + (lut[i + 1u] - lut[i]) * f;
}

// Tables::sample_step: a full step's premultiplied colour and α (stored after the lut).
fn lut_sample_step(s: f32) -> vec4<f32> {
    let x = clamp((s - p.tf.x) / (p.tf.y - p.tf.x), 0.0, 1.0) * f32(LUT_SIZE - 1u);
    let i = min(u32(x), LUT_SIZE - 2u);
    let f = x - f32(i);
    return lut[LUT_SIZE + i] + (lut[LUT_SIZE + i + 1u] - lut[LUT_SIZE + i]) * f;
}

fn segment(front: f32, back: f32) -> vec4<f32> {
    let n = f32(PRE_SIZE - 1u);
    let x = clamp((front - p.tf.z) / (p.tf.w - p.tf.z), 0.0, 1.0) * n;
    let y = clamp((back - p.tf.z) / (p.tf.w - p.tf.z), 0.0, 1.0) * n;
    let i = min(u32(x), PRE_SIZE - 2u);
    let j = min(u32(y), PRE_SIZE - 2u);
    let fx = x - f32(i);
    let fy = y - f32(j);
    let a = pre[i * PRE_SIZE + j];
    let b = pre[i * PRE_SIZE + j + 1u];
    let c = pre[(i + 1u) * PRE_SIZE + j];
    let d = pre[(i + 1u) * PRE_SIZE + j + 1u];
    let top = a + (b - a) * fy;
    let bottom = c + (d - c) * fy;
    return top + (bottom - top) * fx;
}

fn visible_at(q: vec3<f32>) -> bool {
    let c = min(vec3<u32>(max(q, vec3<f32>(0.0))) / 8u, p.cells.xyz - 1u);
    return cells[c.x + p.cells.x * (c.y + p.cells.y * c.z)] != 0u;
}

fn cell_exit(q: vec3<f32>, d: vec3<f32>, t: f32) -> f32 {
    var exit = 1e30;
    for (var a = 0; a < 3; a++) {
        let cell = f32(u32(max(q[a], 0.0)) / 8u);
        var bound = cell * CELL;
        if d[a] > 0.0 {
            bound = (cell + 1.0) * CELL;
        }
        if d[a] != 0.0 {
            exit = min(exit, t + (bound - q[a]) / d[a]);
        }
    }
    return exit;
}

fn index_from_world(v: vec3<f32>) -> vec3<f32> {
    return p.ifw_x.xyz * v.x + p.ifw_y.xyz * v.y + p.ifw_z.xyz * v.z;
}

// Transposed: a gradient in index space as a world gradient.
fn world_gradient(g: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(dot(p.ifw_x.xyz, g), dot(p.ifw_y.xyz, g), dot(p.ifw_z.xyz, g));
}

fn shade(q: vec3<f32>, light: vec3<f32>, light_index: vec3<f32>) -> f32 {
    let ambient = p.misc.x;
    if p.shading.x == 1u {
        let w = world_gradient(grid_gradient(q));
        let len = length(w);
        if len <= 1e-12 {
            return 1.0;
        }
        return ambient + (1.0 - ambient) * abs(dot(w / len, light));
    }
    if p.shading.x == 2u {
        let drop = sample(q) - sample(q + light_index);
        return ambient + (1.0 - ambient) * clamp(drop / p.misc.w, 0.0, 1.0);
    }
    return 1.0;
}

// [near, far] of the ray inside the voxel-centre box; near > far when it misses.
fn clip(o: vec3<f32>, d: vec3<f32>) -> vec2<f32> {
    var near = 0.0;
    var far = 1e30;
    for (var a = 0; a < 3; a++) {
        let top = f32(p.dims[a] - 1u);
        if abs(d[a]) < 1e-30 {
            if o[a] < 0.0 || o[a] > top {
                return vec2<f32>(1.0, 0.0);
            }
            continue;
        }
        let t0 = (0.0 - o[a]) / d[a];
        let t1 = (top - o[a]) / d[a];
        near = max(near, min(t0, t1));
        far = min(far, max(t0, t1));
    }
    return vec2<f32>(near, far);
}

@compute @workgroup_size(8, 8)
fn render(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = p.image.x;
    let h = p.image.y;
    if gid.x >= w || gid.y >= h {
        return;
    }
    let pixel = gid.y * w + gid.x;
    let ray = camera_ray(gid.xy, vec2<u32>(w, h), p.cam_x.xyz, p.cam_y.xyz, p.cam_z.xyz, p.cam_pos.xyz, p.proj);
    let world_origin = ray.origin;
    let world_dir = ray.dir;
    let o = index_from_world(world_origin - p.vol_origin.xyz);
    let d = index_from_world(world_dir);
    var light = -world_dir;
    if p.light.w > 0.5 {
        light = normalize(p.light.xyz);
    }
    let tool = tool_hit(p.tools, p.shading.y, p.misc.x, world_origin, world_dir, light);
    var bg = p.background;
    var behind = 1e30;
    if tool.x >= 0.0 {
        bg = vec4<f32>(tool.yzw, 1.0);
        behind = tool.x;
    }
    let span = clip(o, d);
    if span.x > span.y || min(span.y, behind) < span.x {
        out_rgba[pixel] = pack(bg);
        out_depth[pixel] = behind;
        return;
    }
    let light_index = index_from_world(light);
    let step = p.proj.w;
    let t_near = span.x;
    let t_far = min(span.y, behind);
    let steps = u32(floor((t_far - t_near) / step));

    if p.image.z == 1u {
        if tool.x >= 0.0 {
            out_rgba[pixel] = pack(bg);
            out_depth[pixel] = behind;
            return;
        }
        var peak = -1e30;
        for (var k = 0u; k <= steps; k++) {
            peak = max(peak, sample(o + d * (t_near + f32(k) * step)));
        }
        let g = clamp((peak - p.tf.x) / (p.tf.y - p.tf.x), 0.0, 1.0);
        out_rgba[pixel] = pack(vec4<f32>(g, g, g, 1.0));
        out_depth[pixel] = 1e30;
        return;
    }
    if p.image.z == 2u {
        let iso = p.misc.z;
        var prev = sample(o + d * t_near);
        for (var k = 1u; k <= steps; k++) {
            let t = t_near + f32(k) * step;
            let s = sample(o + d * t);
            if (prev - iso) * (s - iso) <= 0.0 && prev != s {
                var a = t - step;
                var b = t;
                var sa = prev;
                for (var n = 0; n < 12; n++) {
                    let m = 0.5 * (a + b);
                    let sm = sample(o + d * m);
                    if (sa - iso) * (sm - iso) <= 0.0 {
                        b = m;
                    } else {
                        a = m;
                        sa = sm;
                    }
                }
                let hit = 0.5 * (a + b);
                let e = lut_sample(iso);
                var base = vec3<f32>(1.0);
                if e.x + e.y + e.z > 0.0 {
                    base = e.xyz;
                }
                let f = shade(o + d * hit, light, light_index);
                out_rgba[pixel] = pack(vec4<f32>(base * f, 1.0));
                out_depth[pixel] = hit;
                return;
            }
            prev = s;
        }
        out_rgba[pixel] = pack(bg);
        out_depth[pixel] = behind;
        return;
    }

    // Composite (Caster::composite).
    let preintegrated = (p.image.w & 1u) != 0u;
    let skipping = (p.image.w & 2u) != 0u;
    let remainder = (t_far - t_near) - f32(steps) * step;
    var acc = vec4<f32>(0.0);
    var depth = 1e30;
    var front = 0.0;
    var has_front = false;
    var may_skip = true;
    var visible_until = -1e30;
    var k = 0u;
    loop {
        if k > steps {
            break;
        }
        var len = step;
        if k >= steps {
            len = remainder;
        }
        if len <= 1e-6 * step {
            break;
        }
        let t0 = t_near + f32(k) * step;
        if skipping && may_skip && t0 >= visible_until {
            let p0 = o + d * t0;
            if visible_at(p0) {
                visible_until = cell_exit(p0, d, t0);
            } else {
                let inside = u32(floor((cell_exit(p0, d, t0) - t_near) / step));
                if inside > k {
                    k = inside;
                    has_front = false;
                    may_skip = false;
                    continue;
                }
            }
        }
        may_skip = true;
        let middle = o + d * (t0 + 0.5 * len);
        var color = vec3<f32>(0.0);
        var alpha = 0.0;
        if preintegrated {
            var f = front;
            if !has_front {
                f = sample(o + d * t0);
            }
            let b = sample(o + d * (t0 + len));
            front = b;
            has_front = true;
            let seg = segment(f, b);
            if k < steps {
                color = seg.xyz;
                alpha = seg.w;
            } else {
                alpha = 1.0 - pow(max(1.0 - seg.w, 0.0), len / step);
                var scale = len / step;
                if seg.w > 0.0 {
                    scale = alpha / seg.w;
                }
                color = seg.xyz * scale;
            }
        } else if k < steps {
            let e = lut_sample_step(sample(middle));
            color = e.xyz;
            alpha = e.w;
        } else {
            let e = lut_sample(sample(middle));
            alpha = 1.0 - exp(-e.w * len);
            color = e.xyz * alpha;
        }
        if alpha > 1e-5 {
            let f = shade(middle, light, light_index);
            let weight = 1.0 - acc.w;
            acc = vec4<f32>(acc.xyz + weight * color * f, acc.w + weight * alpha);
            if depth >= 1e30 && acc.w >= 0.5 {
                depth = t0 + 0.5 * len;
            }
            if acc.w >= p.misc.y {
                break;
            }
        }
        k += 1u;
    }
    let rest = 1.0 - acc.w;
    out_rgba[pixel] = pack(vec4<f32>(acc.xyz + rest * bg.xyz * bg.w, acc.w + rest * bg.w));
    if depth >= 1e30 {
        depth = behind;
    }
    out_depth[pixel] = depth;
}

// MacroCells::new for one cell: can any sample in it be visible? The scalar range of the
// voxels a sample in the cell reads (one past its far side), then the largest extinction
// over that range of the table (Tables::max_tau), widened by one entry each way: the
// device's division may round a level differently, and a visible cell must never be
// skipped.
@compute @workgroup_size(64)
fn macro_cells(@builtin(global_invocation_id) gid: vec3<u32>) {
    let c = gid.x + gid.y * p.shading.z * 64u;
    let count = p.cells.x * p.cells.y * p.cells.z;
    if c >= count {
        return;
    }
    let cc = vec3<u32>(c % p.cells.x, (c / p.cells.x) % p.cells.y, c / (p.cells.x * p.cells.y));
    let start = cc * 8u;
    let stop = min(start + vec3<u32>(9u), p.dims.xyz);
    var lo = 1e38;
    var hi = -1e38;
    for (var k = start.z; k < stop.z; k++) {
        for (var j = start.y; j < stop.y; j++) {
            for (var i = start.x; i < stop.x; i++) {
                let v = voxel(i, j, k);
                lo = min(lo, v);
                hi = max(hi, v);
            }
        }
    }
    let level = (LUT_SIZE - 1u);
    let a = u32(clamp((lo - p.tf.x) / (p.tf.y - p.tf.x), 0.0, 1.0) * f32(level));
    let b = u32(clamp((hi - p.tf.x) / (p.tf.y - p.tf.x), 0.0, 1.0) * f32(level));
    var tau = 0.0;
    for (var e = max(a, 1u) - 1u; e <= min(b + 2u, level); e++) {
        tau = max(tau, lut[e].w);
    }
    cells[c] = select(0u, 1u, tau > 0.0);
}
