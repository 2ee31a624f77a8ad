// The tetrahedral-mesh raycaster, line by line the twin of cpu.rs beside it:
// `geometry` is TetRaycaster::update (tet_geometry_f32), one invocation per tet; `render` is
// TetRaycaster::render and cast, with nearest_hit, locate_back, walk and integrate,
// SegmentTable::lookup and Tables::sample, one invocation per pixel (Camera::ray and the
// tools are camera_tools.wgsl's). Coordinates are anchored (world minus the rest mesh's centre).
// Showing the source volume through the mesh (look.rs and source.rs beside it): `geometry` also
// writes each tet's map to the source's index, and the walk samples the source on one grid
// along the ray (SourceLook::cross and finish, shade, value; Tables::sample_step and segment).

struct Params {
    // world_from_camera: rotation columns and the anchored eye.
    cam_x: vec4<f32>,
    cam_y: vec4<f32>,
    cam_z: vec4<f32>,
    cam_pos: vec4<f32>,
    // width, height, tiles across, flags (1 pre-integrated)
    image: vec4<u32>,
    // perspective (1) or orthographic (0), tan(fov/2) or ortho height, aspect, step
    proj: vec4<f32>,
    // segment table lo, hi, longest length; hit tolerance
    table: vec4<f32>,
    // table levels per scalar unit and per unit length; the visible scalars' open interval
    scales: vec4<f32>,
    // lut lo, lut hi, early termination, ambient
    lut: vec4<f32>,
    background: vec4<f32>,
    // tets, tools, where the 1D lut starts in `tables`, tiles in all
    counts: vec4<u32>,
    // the source's dims; flags: 1 shows the source, 2 pre-integrated, 4 gradient shading,
    // 8 forward-difference shading
    src_dims: vec4<u32>,
    // where the full-step lut and the pre-integrated table start in `tables`
    src_at: vec4<u32>,
    // pre-integrated lo and hi, the forward difference's gradient scale, sample tolerance
    src_tf: vec4<f32>,
    // toward the light (world), w = 1 when given (else the headlight)
    src_light: vec4<f32>,
    // per tool: anchored tip and radius, anchored tail, colour
    tools: array<vec4<f32>, 12>,
}

struct TetGeometry {
    planes: array<vec4<f32>, 4>,
    gradient: vec4<f32>,
}

// Rows of the affine map from anchored deformed positions to the source's index.
struct TetMap {
    rows: array<vec4<f32>, 3>,
}

struct Hit {
    t: f32,
    tet: u32,
    face: u32,
    front: bool,
    found: bool,
    // the farthest crossing of a front-facing face's plane beyond `after`
    fronts_until: f32,
}

const TILE: u32 = 8u;
const NO_FACE: u32 = 4u;
const MAX_ENTRIES: u32 = 64u;
const MAX_WALK: u32 = 65536u;
const MAX_STALL: u32 = 64u;
const MAX_PIECES: u32 = 4096u;
const LEVELS: u32 = 128u;
const LENGTHS: u32 = 32u;
const LUT_SIZE: u32 = 1024u;
const FAR: f32 = 1e30;
const PRE_SIZE: u32 = 512u;

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read_write> geo: array<TetGeometry>;
@group(0) @binding(2) var<storage, read> links: array<vec4<i32>>;
@group(0) @binding(3) var<storage, read> tiles: array<u32>;
@group(0) @binding(4) var<storage, read> tables: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> out: array<u32>;
@group(0) @binding(6) var<storage, read> nodes: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> tets: array<vec4<u32>>;
@group(0) @binding(8) var<storage, read_write> maps: array<TetMap>;
@group(0) @binding(9) var<storage, read> rest_index: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read> source: array<f32>;
@group(0) @binding(11) var<storage, read> tet_visible: array<u32>;

// linear_field: gradient and offset of the field taking the values s at the vertices x.
fn linear_field(x: array<vec3<f32>, 4>, s: vec4<f32>) -> vec4<f32> {
    // The rows of M are the edges from vertex 0; M⁻¹'s columns are the rows' cross products over det.
    let r0 = x[1] - x[0];
    let r1 = x[2] - x[0];
    let r2 = x[3] - x[0];
    let det = dot(r0, cross(r1, r2));
    var grad = vec3<f32>(0.0);
    if det != 0.0 {
        grad = (cross(r1, r2) * (s.y - s.x) + cross(r2, r0) * (s.z - s.x) + cross(r0, r1) * (s.w - s.x)) / det;
    }
    var offset = (s.x + s.y + s.z + s.w) / 4.0;
    if any(grad != vec3<f32>(0.0)) {
        offset = s.x - dot(grad, x[0]);
    }
    return vec4<f32>(grad, offset);
}

// tet_geometry: outward face planes (face k opposite vertex k) and the scalar's gradient.
@compute @workgroup_size(64)
fn geometry(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = gid.x;
    if t >= p.counts.x {
        return;
    }
    let ids = tets[t];
    var x = array<vec3<f32>, 4>(nodes[ids.x].xyz, nodes[ids.y].xyz, nodes[ids.z].xyz, nodes[ids.w].xyz);
    let s = vec4<f32>(nodes[ids.x].w, nodes[ids.y].w, nodes[ids.z].w, nodes[ids.w].w);
    var faces = array<vec3<u32>, 4>(vec3<u32>(1u, 2u, 3u), vec3<u32>(0u, 3u, 2u), vec3<u32>(0u, 1u, 3u), vec3<u32>(0u, 2u, 1u));
    var g: TetGeometry;
    for (var k = 0u; k < 4u; k++) {
        let f = faces[k];
        let a = x[f.x];
        var n = cross(x[f.y] - a, x[f.z] - a);
        if dot(n, x[k] - a) > 0.0 {
            n = -n;
        }
        let len = length(n);
        if len > 0.0 {
            n = n / len;
        } else {
            n = vec3<f32>(0.0);
        }
        g.planes[k] = vec4<f32>(n, dot(n, a));
    }
    g.gradient = linear_field(x, s);
    geo[t] = g;
    // SourceLook::update_maps
    if (p.src_dims.w & 1u) != 0u {
        var m: TetMap;
        for (var c = 0u; c < 3u; c++) {
            let q = vec4<f32>(rest_index[ids.x][c], rest_index[ids.y][c], rest_index[ids.z][c], rest_index[ids.w][c]);
            m.rows[c] = linear_field(x, q);
        }
        maps[t] = m;
    }
}

// plane_t: (n·d, the ray parameter on the plane)
fn plane_t(q: vec4<f32>, o: vec3<f32>, d: vec3<f32>) -> vec2<f32> {
    let denom = q.x * d.x + q.y * d.y + q.z * d.z;
    return vec2<f32>(denom, (q.w - (q.x * o.x + q.y * o.y + q.z * o.z)) / denom);
}

// Tables::sample
fn lut_sample(s: f32) -> vec4<f32> {
    let x = clamp((s - p.lut.x) / (p.lut.y - p.lut.x), 0.0, 1.0) * f32(LUT_SIZE - 1u);
    let i = min(u32(x), LUT_SIZE - 2u);
    let f = x - f32(i);
    let a = tables[p.counts.z + i];
    let b = tables[p.counts.z + i + 1u];
    return a + (b - a) * f;
}

fn table_at(i: u32, j: u32, l: u32, fz: f32) -> vec4<f32> {
    let a = tables[(i * LEVELS + j) * LENGTHS + l];
    let b = tables[(i * LEVELS + j) * LENGTHS + l + 1u];
    return a + (b - a) * fz;
}

// SegmentTable::lookup
fn lookup(front: f32, back: f32, len: f32) -> vec4<f32> {
    let n = f32(LEVELS - 1u);
    let x = clamp((front - p.table.x) * p.scales.x, 0.0, n);
    let y = clamp((back - p.table.x) * p.scales.x, 0.0, n);
    let z = clamp(len * p.scales.y, 0.0, f32(LENGTHS - 1u));
    let i = min(u32(x), LEVELS - 2u);
    let j = min(u32(y), LEVELS - 2u);
    let l = min(u32(z), LENGTHS - 2u);
    let fx = x - f32(i);
    let fy = y - f32(j);
    let fz = z - f32(l);
    let a = table_at(i, j, l, fz);
    let b = table_at(i, j + 1u, l, fz);
    let c = table_at(i + 1u, j, l, fz);
    let d = table_at(i + 1u, j + 1u, l, fz);
    let top = a + (b - a) * fy;
    let bottom = c + (d - c) * fy;
    return top + (bottom - top) * fx;
}

struct Start {
    tet: u32,
    face: u32,
    t: f32,
}

struct Accumulator {
    acc: vec4<f32>,
    depth: f32,
}

// TetRaycaster::integrate
fn integrate(state: ptr<function, Accumulator>, t0: f32, t1: f32, s0: f32, s1: f32) {
    let len = t1 - t0;
    if !(len > 0.0) {
        return;
    }
    // Pre-integrated pieces as long as the table reaches, point samples a step apart.
    var step = p.proj.w;
    if (p.image.w & 1u) != 0u {
        step = p.table.z;
    }
    var n = 1u;
    if len > step {
        n = min(u32(ceil(len / step)), MAX_PIECES);
    }
    let inv_n = 1.0 / f32(n);
    let piece = len * inv_n;
    for (var m = 0u; m < n; m++) {
        var e: vec4<f32>;
        if (p.image.w & 1u) != 0u {
            let f0 = f32(m) * inv_n;
            let f1 = f32(m + 1u) * inv_n;
            e = lookup(s0 + (s1 - s0) * f0, s0 + (s1 - s0) * f1, piece);
        } else {
            let q = lut_sample(s0 + (s1 - s0) * ((f32(m) + 0.5) * inv_n));
            let alpha = 1.0 - exp(-q.w * piece);
            e = vec4<f32>(q.xyz * alpha, alpha);
        }
        let weight = 1.0 - (*state).acc.w;
        (*state).acc += weight * e;
        if (*state).depth >= FAR && (*state).acc.w >= 0.5 {
            (*state).depth = t0 + (f32(m) + 0.5) * piece;
        }
    }
}

// TetRaycaster::nearest_hit
fn nearest_hit(first: u32, last: u32, o: vec3<f32>, d: vec3<f32>, after: f32, fronts_only: bool) -> Hit {
    var best = Hit(0.0, 0u, 0u, false, false, -FAR);
    var fronts_until = -FAR;
    let base = p.counts.w + 1u;
    for (var i = first; i < last; i++) {
        let id = tiles[base + i];
        let tet = id >> 2u;
        let k = id & 3u;
        let pt = plane_t(geo[tet].planes[k], o, d);
        if pt.x == 0.0 || !(pt.y > after) {
            continue;
        }
        if pt.x < 0.0 {
            fronts_until = max(fronts_until, pt.y);
        } else if fronts_only {
            continue;
        }
        if best.found && pt.y >= best.t {
            continue;
        }
        let q = o + d * pt.y;
        var on_face = true;
        for (var j = 0u; j < 4u; j++) {
            let plane = geo[tet].planes[j];
            if j != k && plane.x * q.x + plane.y * q.y + plane.z * q.z - plane.w > p.table.w {
                on_face = false;
            }
        }
        if on_face {
            best = Hit(pt.y, tet, k, pt.x < 0.0, true, 0.0);
        }
    }
    best.fronts_until = fronts_until;
    return best;
}

// TetRaycaster::locate_back: (tet, entry face, t)
fn locate_back(start: u32, o: vec3<f32>, d: vec3<f32>, t_from: f32) -> Start {
    var tet = start;
    for (var n = 0u; n < MAX_WALK; n++) {
        var entry_t = -FAR;
        var entry_k = NO_FACE;
        for (var k = 0u; k < 4u; k++) {
            let pt = plane_t(geo[tet].planes[k], o, d);
            if pt.x < -1e-7 && pt.y > entry_t {
                entry_t = pt.y;
                entry_k = k;
            }
        }
        if entry_k == NO_FACE || entry_t <= t_from {
            return Start(tet, entry_k, t_from);
        }
        let link = links[tet][entry_k];
        if link < 0 {
            return Start(tet, entry_k, entry_t);
        }
        tet = u32(link) >> 2u;
    }
    return Start(tet, NO_FACE, t_from);
}

struct March {
    t0: f32,
    k: u32,
    front: f32,
    has_front: bool,
}

fn apply(m: TetMap, x: vec3<f32>) -> vec3<f32> {
    let r0 = m.rows[0];
    let r1 = m.rows[1];
    let r2 = m.rows[2];
    return vec3<f32>(
        r0.x * x.x + r0.y * x.y + r0.z * x.z + r0.w,
        r1.x * x.x + r1.y * x.y + r1.z * x.z + r1.w,
        r2.x * x.x + r2.y * x.y + r2.z * x.z + r2.w,
    );
}

fn src_voxel(i: u32, j: u32, k: u32) -> f32 {
    return source[i + p.src_dims.x * (j + p.src_dims.y * k)];
}

// sample_clamped
fn src_clamped(q: vec3<f32>) -> f32 {
    let n = vec3<f32>(p.src_dims.xyz);
    let c = clamp(q, vec3<f32>(0.0), n - 1.0);
    let i = min(vec3<u32>(c), max(p.src_dims.xyz, vec3<u32>(2u)) - 2u);
    let f = c - vec3<f32>(i);
    let i1 = min(i + 1u, p.src_dims.xyz - 1u);
    let c00 = src_voxel(i.x, i.y, i.z) + (src_voxel(i1.x, i.y, i.z) - src_voxel(i.x, i.y, i.z)) * f.x;
    let c10 = src_voxel(i.x, i1.y, i.z) + (src_voxel(i1.x, i1.y, i.z) - src_voxel(i.x, i1.y, i.z)) * f.x;
    let c01 = src_voxel(i.x, i.y, i1.z) + (src_voxel(i1.x, i.y, i1.z) - src_voxel(i.x, i.y, i1.z)) * f.x;
    let c11 = src_voxel(i.x, i1.y, i1.z) + (src_voxel(i1.x, i1.y, i1.z) - src_voxel(i.x, i1.y, i1.z)) * f.x;
    let c0 = c00 + (c10 - c00) * f.y;
    let c1 = c01 + (c11 - c01) * f.y;
    return c0 + (c1 - c0) * f.z;
}

// The grid grid_gradient.wgsl reads: the source.
fn grid_dims() -> vec3<u32> {
    return p.src_dims.xyz;
}

fn grid_voxel(i: u32, j: u32, k: u32) -> f32 {
    return src_voxel(i, j, k);
}

// SourceLook::value: (value, 1 inside the voxel-centre box, else 0)
fn src_value(q: vec3<f32>) -> vec2<f32> {
    let tol = p.src_tf.w;
    let top = vec3<f32>(p.src_dims.xyz) - 1.0;
    if any(q < vec3<f32>(-tol)) || any(q > top + tol) {
        return vec2<f32>(0.0, 0.0);
    }
    return vec2<f32>(src_clamped(q), 1.0);
}

// Tables::sample_step
fn src_step_lut(s: f32) -> vec4<f32> {
    let x = clamp((s - p.lut.x) / (p.lut.y - p.lut.x), 0.0, 1.0) * f32(LUT_SIZE - 1u);
    let i = min(u32(x), LUT_SIZE - 2u);
    let f = x - f32(i);
    let a = tables[p.src_at.x + i];
    let b = tables[p.src_at.x + i + 1u];
    return a + (b - a) * f;
}

// Tables::segment
fn src_segment(front: f32, back: f32) -> vec4<f32> {
    let n = f32(PRE_SIZE - 1u);
    let x = clamp((front - p.src_tf.x) / (p.src_tf.y - p.src_tf.x), 0.0, 1.0) * n;
    let y = clamp((back - p.src_tf.x) / (p.src_tf.y - p.src_tf.x), 0.0, 1.0) * n;
    let i = min(u32(x), PRE_SIZE - 2u);
    let j = min(u32(y), PRE_SIZE - 2u);
    let fx = x - f32(i);
    let fy = y - f32(j);
    let base = p.src_at.y;
    let a = tables[base + i * PRE_SIZE + j];
    let b = tables[base + i * PRE_SIZE + j + 1u];
    let c = tables[base + (i + 1u) * PRE_SIZE + j];
    let d = tables[base + (i + 1u) * PRE_SIZE + j + 1u];
    let top = a + (b - a) * fy;
    let bottom = c + (d - c) * fy;
    return top + (bottom - top) * fx;
}

// SourceLook::shade
fn src_shade(q: vec3<f32>, m: TetMap, light: vec3<f32>) -> f32 {
    let ambient = p.lut.w;
    if (p.src_dims.w & 4u) != 0u {
        let gi = grid_gradient(q);
        let g = m.rows[0].xyz * gi.x + m.rows[1].xyz * gi.y + m.rows[2].xyz * gi.z;
        let len = length(g);
        if len > 1e-12 {
            return ambient + (1.0 - ambient) * abs(dot(g, light) / len);
        }
        return 1.0;
    }
    if (p.src_dims.w & 8u) != 0u {
        let l = vec3<f32>(dot(m.rows[0].xyz, light), dot(m.rows[1].xyz, light), dot(m.rows[2].xyz, light));
        let fall = src_clamped(q) - src_clamped(q + l);
        return ambient + (1.0 - ambient) * clamp(fall / p.src_tf.z, 0.0, 1.0);
    }
    return 1.0;
}

// SourceLook::add
fn src_add(state: ptr<function, Accumulator>, e: vec4<f32>, q: vec3<f32>, m: TetMap, light: vec3<f32>, t_mid: f32) {
    if e.w <= 1e-5 {
        return;
    }
    let shade = src_shade(q, m, light);
    let weight = 1.0 - (*state).acc.w;
    (*state).acc = (*state).acc + weight * vec4<f32>(e.xyz * shade, e.w);
    if (*state).depth >= FAR && (*state).acc.w >= 0.5 {
        (*state).depth = t_mid;
    }
}

fn src_offset() -> f32 {
    if (p.src_dims.w & 2u) != 0u {
        return 0.0;
    }
    return 0.5;
}

// SourceLook::cross
fn src_cross(state: ptr<function, Accumulator>, march: ptr<function, March>, tet: u32, t_out: f32, o: vec3<f32>, d: vec3<f32>, light: vec3<f32>) {
    let step = p.proj.w;
    let pre = (p.src_dims.w & 2u) != 0u;
    let offset = src_offset();
    let m = maps[tet];
    let t0 = (*march).t0;
    // In a tet with nothing to see, only the segment coming in from the tet before adds anything.
    var composite = tet_visible[tet] != 0u || (pre && (*march).has_front);
    for (var n = 0u; n < MAX_WALK; n++) {
        let t = t0 + (f32((*march).k) + offset) * step;
        if !(t <= t_out) {
            return;
        }
        if !composite {
            var last = u32(max(floor((t_out - t0) / step - offset), f32((*march).k)));
            if t0 + (f32(last) + offset) * step > t_out {
                last = max(max(last, 1u) - 1u, (*march).k);
            }
            if pre {
                let v = src_value(apply(m, o + d * (t0 + (f32(last) + offset) * step)));
                (*march).front = v.x;
                (*march).has_front = v.y > 0.0;
            }
            (*march).k = last + 1u;
            return;
        }
        composite = tet_visible[tet] != 0u;
        let q = apply(m, o + d * t);
        let v = src_value(q);
        if pre {
            if (*march).has_front && v.y > 0.0 && (*march).k > 0u {
                let middle = apply(m, o + d * (t - 0.5 * step));
                src_add(state, src_segment((*march).front, v.x), middle, m, light, t - 0.5 * step);
            }
            (*march).front = v.x;
            (*march).has_front = v.y > 0.0;
        } else if v.y > 0.0 {
            src_add(state, src_step_lut(v.x), q, m, light, t);
        }
        (*march).k += 1u;
        if (*state).acc.w >= p.lut.z {
            return;
        }
    }
}

// SourceLook::finish
fn src_finish(state: ptr<function, Accumulator>, march: March, tet: u32, t_end: f32, o: vec3<f32>, d: vec3<f32>, light: vec3<f32>) {
    let step = p.proj.w;
    let m = maps[tet];
    let pre = (p.src_dims.w & 2u) != 0u;
    var start = march.t0 + f32(march.k) * step;
    if pre {
        start -= step;
    }
    let len = t_end - start;
    if len <= 1e-6 * step {
        return;
    }
    let middle = apply(m, o + d * (start + 0.5 * len));
    if pre {
        let back = src_value(apply(m, o + d * t_end));
        if !march.has_front || back.y == 0.0 {
            return;
        }
        let seg = src_segment(march.front, back.x);
        let alpha = 1.0 - pow(max(1.0 - seg.w, 0.0), len / step);
        var scale = len / step;
        if seg.w > 0.0 {
            scale = alpha / seg.w;
        }
        src_add(state, vec4<f32>(seg.xyz * scale, alpha), middle, m, light, start + 0.5 * len);
    } else {
        let v = src_value(middle);
        if v.y == 0.0 {
            return;
        }
        let e = lut_sample(v.x);
        let alpha = 1.0 - exp(-e.w * len);
        src_add(state, vec4<f32>(e.xyz * alpha, alpha), middle, m, light, start + 0.5 * len);
    }
}

fn scalar(g: vec4<f32>, o: vec3<f32>, d: vec3<f32>, t: f32) -> f32 {
    return g.x * (o.x + d.x * t) + g.y * (o.y + d.y * t) + g.z * (o.z + d.z * t) + g.w;
}

// TetRaycaster::walk: where the ray stopped.
fn walk(state: ptr<function, Accumulator>, start: Start, o: vec3<f32>, d: vec3<f32>, t_stop: f32) -> f32 {
    var tet = start.tet;
    var face_in = start.face;
    var t_in = start.t;
    var stalled = 0u;
    var s_in = scalar(geo[tet].gradient, o, d, t_in);
    let shows_source = (p.src_dims.w & 1u) != 0u;
    var march = March(t_in, 0u, 0.0, false);
    var light = -d;
    if p.src_light.w > 0.0 {
        light = p.src_light.xyz;
    }
    for (var n = 0u; n < MAX_WALK; n++) {
        var num = 0.0;
        var den = 0.0;
        var exit_k = NO_FACE;
        for (var k = 0u; k < 4u; k++) {
            let plane = geo[tet].planes[k];
            let denom = plane.x * d.x + plane.y * d.y + plane.z * d.z;
            if k == face_in || !(denom > 1e-7) {
                continue;
            }
            let q = plane.w - (plane.x * o.x + plane.y * o.y + plane.z * o.z);
            if exit_k == NO_FACE || q * den < num * denom {
                num = q;
                den = denom;
                exit_k = k;
            }
        }
        if exit_k == NO_FACE {
            return t_in;
        }
        let t_out = min(max(num / den, t_in), t_stop);
        if t_out - t_in <= 1e-6 * (1.0 + abs(t_in)) {
            stalled += 1u;
        } else {
            stalled = 0u;
        }
        if stalled > MAX_STALL {
            return t_out;
        }
        let s_out = scalar(geo[tet].gradient, o, d, t_out);
        if shows_source {
            src_cross(state, &march, tet, t_out, o, d, light);
        } else if max(s_in, s_out) > p.scales.z && min(s_in, s_out) < p.scales.w {
            integrate(state, t_in, t_out, s_in, s_out);
        }
        if (*state).acc.w >= p.lut.z {
            return t_out;
        }
        let link = links[tet][exit_k];
        if t_out >= t_stop || link < 0 {
            // The ray leaves the mesh or meets a tool: the source's last, shorter segment.
            if shows_source {
                src_finish(state, march, tet, t_out, o, d, light);
            }
            return t_out;
        }
        tet = u32(link) >> 2u;
        face_in = u32(link) & 3u;
        t_in = t_out;
        s_in = s_out;
    }
    return t_in;
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
    let o = ray.origin;
    let d = ray.dir;

    // cast
    let tool = tool_hit(p.tools, p.counts.y, p.lut.w, o, d, -d);
    var bg = p.background;
    var t_stop = FAR;
    if tool.x >= 0.0 {
        bg = vec4<f32>(tool.yzw, 1.0);
        t_stop = tool.x;
    }
    let tile = (gid.y / TILE) * p.image.z + gid.x / TILE;
    let first = tiles[tile];
    let last = tiles[tile + 1u];
    var state = Accumulator(vec4<f32>(0.0), FAR);
    var t_from = 0.0;
    var walked = false;
    var last_start = -FAR;
    for (var e = 0u; e < MAX_ENTRIES; e++) {
        var after = t_from;
        if walked {
            after = max(t_from - p.table.w, last_start);
        }
        let hit = nearest_hit(first, last, o, d, after, walked);
        if !hit.found || hit.t >= t_stop {
            break;
        }
        var start = Start(hit.tet, hit.face, hit.t);
        if !hit.front {
            // The first boundary ahead is an exit: the ray starts inside the mesh.
            start = locate_back(hit.tet, o, d, t_from);
        }
        walked = true;
        last_start = start.t;
        t_from = walk(&state, start, o, d, t_stop);
        if state.acc.w >= p.lut.z || t_from >= t_stop || t_from - p.table.w >= hit.fronts_until {
            break;
        }
    }
    let rest = 1.0 - state.acc.w;
    let color = vec4<f32>(state.acc.xyz + rest * bg.xyz * bg.w, state.acc.w + rest * bg.w);
    var depth = state.depth;
    if depth >= FAR {
        depth = t_stop;
    }
    out[pixel] = pack(color);
    out[w * h + pixel] = bitcast<u32>(depth);
}
