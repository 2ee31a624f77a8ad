// Mass-spring solver kernels: the GPU twin of kernels.rs and cpu/ beside this file.
// The state is displacements u from rest (f32 resolution follows the deformation, not the
// distance from the origin); a spring's current edge is rest_edge + u_b - u_a.
// Spring e joins (a, b); spring_force[e] is the force on a; spring_kv[e] = K_e (v_b - v_a);
// spring_block[e] = h D_e + h^2 K_e (the off-diagonal block of A is its negative).
// Nodes gather their springs through the adjacency lists: no atomics anywhere.
// The system's rows are the nodes', then one per simulated tool (a coupled tool's body);
// surface contacts add rank-one terms h²k g gᵀ over their rows (contact_* kernels, the twin
// of cpu/contact.rs), found on the host each step and gathered per touched row.

struct Tool {
    a: vec4<f32>, // segment start (tip), radius in w
    b: vec4<f32>, // segment end, contact stiffness in w
}

struct Params {
    gravity_h: vec4<f32>,  // gravity xyz, time step h
    counts: vec4<u32>,     // nodes, springs, tools, -
    cg: vec4<f32>,         // tolerance^2, max iterations, multigrid's fine damping ω (0: block Jacobi), -
    tools: array<Tool, 4>,
    system: vec4<u32>,     // rows (nodes + simulated tools' rows), contacts, touched rows, simulated tools' rows
}

// A surface contact's terms (cpu::ContactTerms): rows (NO_ROW where none), the gradient
// of its penetration on each, and h²k, h k (φ + h φ̇).
struct ContactTerm {
    rows: array<vec4<u32>, 5>,
    gradients: array<vec4<f32>, 18>,
    scale: vec4<f32>,
}

struct CgScalars {
    rz: f32,
    rr: f32,
    bb: f32,
    alpha: f32,
    beta: f32,
    pq: f32,
    iterations: u32,
    done: u32,
    contact_pq: f32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> springs: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> spring_params: array<vec4<f32>>; // rest, k, damping, -
@group(0) @binding(3) var<storage, read> offsets: array<u32>;
@group(0) @binding(4) var<storage, read> adjacency: array<vec2<u32>>;      // neighbour, spring
@group(0) @binding(5) var<storage, read> node_params: array<vec4<f32>>;    // mass, fixed, -, -
@group(0) @binding(6) var<storage, read_write> u: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> v: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read> external_force: array<vec4<f32>>;
@group(0) @binding(9) var<storage, read_write> spring_force: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read_write> spring_kv: array<vec4<f32>>;
@group(0) @binding(11) var<storage, read_write> spring_block: array<mat3x3<f32>>;
@group(0) @binding(12) var<storage, read_write> diag: array<mat3x3<f32>>;
@group(0) @binding(13) var<storage, read_write> precond: array<mat3x3<f32>>;
@group(0) @binding(14) var<storage, read_write> rhs: array<vec4<f32>>;
@group(0) @binding(15) var<storage, read_write> dv: array<vec4<f32>>;
@group(0) @binding(16) var<storage, read_write> r: array<vec4<f32>>;
@group(0) @binding(17) var<storage, read_write> z: array<vec4<f32>>;
@group(0) @binding(18) var<storage, read_write> p: array<vec4<f32>>;
@group(0) @binding(19) var<storage, read_write> q: array<vec4<f32>>;
@group(0) @binding(20) var<storage, read_write> partials: array<vec4<f32>>;
@group(0) @binding(21) var<storage, read_write> scalars: CgScalars;
@group(0) @binding(22) var<storage, read_write> aux: array<vec4<f32>>;   // previous u (Verlet) or acceleration (velocity Verlet)
@group(0) @binding(23) var<storage, read_write> force: array<vec4<f32>>; // node forces of the explicit schemes
@group(0) @binding(24) var<storage, read> rest_edge: array<vec4<f32>>;  // x_b - x_a at rest, per spring
@group(0) @binding(25) var<storage, read> rest_pos: array<vec4<f32>>;   // rest positions, for contact
@group(0) @binding(26) var<storage, read> contact_terms: array<ContactTerm>;
@group(0) @binding(27) var<storage, read> touched: array<vec4<u32>>;     // row, first incidence, count, -
@group(0) @binding(28) var<storage, read> incidence: array<vec2<u32>>;   // contact, slot
@group(0) @binding(29) var<storage, read_write> contact_y: array<vec4<f32>>; // h²k g·p per contact
@group(0) @binding(30) var<storage, read_write> outcome: array<vec4<f32>>;   // simulated tools' Δv, then contacts' g·Δv

const CONTACT_ROWS: u32 = 18u;
const NO_ROW: u32 = 0xffffffffu;

const WG: u32 = 256u;
var<workgroup> shared_sum: array<vec4<f32>, 256>;

fn outer(u: vec3<f32>) -> mat3x3<f32> {
    return mat3x3<f32>(u * u.x, u * u.y, u * u.z);
}

fn identity3() -> mat3x3<f32> {
    return mat3x3<f32>(vec3<f32>(1.0, 0.0, 0.0), vec3<f32>(0.0, 1.0, 0.0), vec3<f32>(0.0, 0.0, 1.0));
}

fn is_fixed(i: u32) -> bool {
    return node_params[i].y != 0.0;
}

// ---- per spring --------------------------------------------------------------------------

fn spring_force_of(e: u32, va: vec3<f32>, vb: vec3<f32>) -> vec3<f32> {
    let ab = springs[e];
    let sp = spring_params[e];
    let d = rest_edge[e].xyz + u[ab.y].xyz - u[ab.x].xyz;
    let l = length(d);
    if (l <= 1.1920929e-7) {
        return vec3<f32>(0.0);
    }
    let u = d / l;
    return u * (sp.y * (l - sp.x) + sp.z * dot(vb - va, u));
}

@compute @workgroup_size(256)
fn spring_terms(@builtin(global_invocation_id) gid: vec3<u32>) {
    let e = gid.x;
    if (e >= params.counts.y) {
        return;
    }
    let h = params.gravity_h.w;
    let ab = springs[e];
    let sp = spring_params[e];
    let rest = sp.x;
    let k = sp.y;
    let damping = sp.z;
    let d = rest_edge[e].xyz + u[ab.y].xyz - u[ab.x].xyz;
    let l = length(d);
    if (l <= 1.1920929e-7) {
        spring_force[e] = vec4<f32>(0.0);
        spring_kv[e] = vec4<f32>(0.0);
        spring_block[e] = mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
        return;
    }
    let u = d / l;
    let dvel = v[ab.y].xyz - v[ab.x].xyz;
    let f = u * (k * (l - rest) + damping * dot(dvel, u));
    let uu = outer(u);
    let geometric = max(1.0 - rest / l, 0.0);
    let stiffness_block = uu * k + (identity3() - uu) * (k * geometric);
    spring_force[e] = vec4<f32>(f, 0.0);
    spring_kv[e] = vec4<f32>(stiffness_block * dvel, 0.0);
    spring_block[e] = uu * (h * damping) + stiffness_block * (h * h);
}

// Explicit schemes: spring forces only, at velocities `v` (or `q` holding predicted ones).
@compute @workgroup_size(256)
fn spring_forces(@builtin(global_invocation_id) gid: vec3<u32>) {
    let e = gid.x;
    if (e >= params.counts.y) {
        return;
    }
    let ab = springs[e];
    spring_force[e] = vec4<f32>(spring_force_of(e, v[ab.x].xyz, v[ab.y].xyz), 0.0);
}

@compute @workgroup_size(256)
fn spring_forces_predicted(@builtin(global_invocation_id) gid: vec3<u32>) {
    let e = gid.x;
    if (e >= params.counts.y) {
        return;
    }
    let ab = springs[e];
    spring_force[e] = vec4<f32>(spring_force_of(e, q[ab.x].xyz, q[ab.y].xyz), 0.0);
}

// ---- per node ----------------------------------------------------------------------------

struct Contact {
    inside: bool,
    f: vec3<f32>,
    nn: mat3x3<f32>,
}

fn contact(pos: vec3<f32>, tool: Tool) -> Contact {
    var c: Contact;
    c.inside = false;
    let a = tool.a.xyz;
    let ab = tool.b.xyz - a;
    let len2 = dot(ab, ab);
    var t = 0.0;
    if (len2 > 0.0) {
        t = clamp(dot(pos - a, ab) / len2, 0.0, 1.0);
    }
    let d = pos - (a + ab * t);
    let dist = length(d);
    let radius = tool.a.w;
    if (dist >= radius) {
        return c;
    }
    var n = vec3<f32>(0.0, 0.0, 1.0);
    if (dist > 1e-12) {
        n = d / dist;
    }
    c.inside = true;
    c.f = n * (tool.b.w * (radius - dist));
    c.nn = outer(n) * tool.b.w;
    return c;
}

fn gathered_force(i: u32) -> vec3<f32> {
    let m = node_params[i].x;
    var f = params.gravity_h.xyz * m + external_force[i].xyz;
    for (var s = offsets[i]; s < offsets[i + 1u]; s = s + 1u) {
        let e = adjacency[s].y;
        if (springs[e].x == i) {
            f = f + spring_force[e].xyz;
        } else {
            f = f - spring_force[e].xyz;
        }
    }
    for (var t = 0u; t < params.counts.z; t = t + 1u) {
        let c = contact(rest_pos[i].xyz + u[i].xyz, params.tools[t]);
        if (c.inside) {
            f = f + c.f;
        }
    }
    return f;
}

@compute @workgroup_size(256)
fn node_terms(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.counts.x) {
        return;
    }
    let h = params.gravity_h.w;
    let m = node_params[i].x;
    var f = params.gravity_h.xyz * m + external_force[i].xyz;
    var dg = identity3() * m;
    var kv = vec3<f32>(0.0);
    for (var s = offsets[i]; s < offsets[i + 1u]; s = s + 1u) {
        let e = adjacency[s].y;
        if (springs[e].x == i) {
            f = f + spring_force[e].xyz;
            kv = kv + spring_kv[e].xyz;
        } else {
            f = f - spring_force[e].xyz;
            kv = kv - spring_kv[e].xyz;
        }
        dg = dg + spring_block[e];
    }
    for (var t = 0u; t < params.counts.z; t = t + 1u) {
        let c = contact(rest_pos[i].xyz + u[i].xyz, params.tools[t]);
        if (c.inside) {
            f = f + c.f;
            dg = dg + c.nn * (h * h);
            kv = kv - c.nn * v[i].xyz;
        }
    }
    diag[i] = dg;
    if (is_fixed(i)) {
        rhs[i] = vec4<f32>(0.0);
        precond[i] = mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
        dv[i] = vec4<f32>(0.0);
        return;
    }
    rhs[i] = vec4<f32>((f + kv * h) * h, 0.0);
    precond[i] = inverse_or_zero(dg);
}

// Inverse of a 3x3 by cofactors; zero when singular.
fn inverse_or_zero(m: mat3x3<f32>) -> mat3x3<f32> {
    let det = determinant(m);
    if (det == 0.0) {
        return mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    }
    let inv_t = mat3x3<f32>(cross(m[1], m[2]), cross(m[2], m[0]), cross(m[0], m[1])) * (1.0 / det);
    return transpose(inv_t);
}

// ---- surface contacts (cpu/contact.rs: add_contacts, contact_product) ----------------------

fn contact_row(c: u32, k: u32) -> u32 {
    return contact_terms[c].rows[k / 4u][k % 4u];
}

// Per touched row: the contacts' part of b, and of the diagonal block block Jacobi inverts.
@compute @workgroup_size(256)
fn contact_rows(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = gid.x;
    if (t >= params.system.z) {
        return;
    }
    let entry = touched[t];
    let row = entry.x;
    var b = rhs[row].xyz;
    var dg = diag[row];
    for (var s = entry.y; s < entry.y + entry.z; s = s + 1u) {
        let at = incidence[s];
        let g = contact_terms[at.x].gradients[at.y].xyz;
        let scale = contact_terms[at.x].scale;
        b = b - g * scale.y;
        dg = dg + outer(g) * scale.x;
    }
    rhs[row] = vec4<f32>(b, 0.0);
    precond[row] = inverse_or_zero(dg);
}

// y_c = h²k (g_c·p) per contact, and Σ_c y_c (g_c·p), the contacts' part of p·Ap (one workgroup).
@compute @workgroup_size(256)
fn contact_dot(@builtin(local_invocation_id) lid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    var sum = 0.0;
    for (var c = lid.x; c < params.system.y; c = c + WG) {
        var gp = 0.0;
        for (var k = 0u; k < CONTACT_ROWS; k = k + 1u) {
            let row = contact_row(c, k);
            if (row != NO_ROW) {
                gp = gp + dot(contact_terms[c].gradients[k].xyz, p[row].xyz);
            }
        }
        let y = contact_terms[c].scale.x * gp;
        contact_y[c] = vec4<f32>(y, 0.0, 0.0, 0.0);
        sum = sum + y * gp;
    }
    shared_sum[lid.x] = vec4<f32>(sum, 0.0, 0.0, 0.0);
    workgroupBarrier();
    for (var stride = WG / 2u; stride > 0u; stride = stride / 2u) {
        if (lid.x < stride) {
            shared_sum[lid.x] = shared_sum[lid.x] + shared_sum[lid.x + stride];
        }
        workgroupBarrier();
    }
    if (lid.x == 0u) {
        scalars.contact_pq = shared_sum[0].x;
    }
}

// q += the contacts' part of A p, per touched row.
@compute @workgroup_size(256)
fn contact_scatter(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    let t = gid.x;
    if (t >= params.system.z) {
        return;
    }
    let entry = touched[t];
    var acc = q[entry.x].xyz;
    for (var s = entry.y; s < entry.y + entry.z; s = s + 1u) {
        let at = incidence[s];
        acc = acc + contact_terms[at.x].gradients[at.y].xyz * contact_y[at.x].x;
    }
    q[entry.x] = vec4<f32>(acc, 0.0);
}

// bᵀΔv for the probe stored after the contacts (the local model's compliance solve).
@compute @workgroup_size(256)
fn probe_outcome(@builtin(global_invocation_id) gid: vec3<u32>) {
    // Queued behind a solve that may not be done yet: nothing until it is.
    if (gid.x != 0u || scalars.done == 0u) {
        return;
    }
    let c = params.system.y;
    var gd = 0.0;
    for (var k = 0u; k < CONTACT_ROWS; k = k + 1u) {
        let row = contact_row(c, k);
        if (row != NO_ROW) {
            gd = gd + dot(contact_terms[c].gradients[k].xyz, dv[row].xyz);
        }
    }
    outcome[0] = vec4<f32>(gd, 0.0, 0.0, 0.0);
}

// After the solve: the simulated tools' rows of Δv, then each contact's g·Δv. Queued
// behind a solve that may not be done yet: nothing until it is.
@compute @workgroup_size(256)
fn contact_outcome(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (scalars.done == 0u) {
        return;
    }
    let i = gid.x;
    let tools = params.system.w;
    if (i < tools) {
        outcome[i] = dv[params.counts.x + i];
        return;
    }
    let c = i - tools;
    if (c >= params.system.y) {
        return;
    }
    var gd = 0.0;
    for (var k = 0u; k < CONTACT_ROWS; k = k + 1u) {
        let row = contact_row(c, k);
        if (row != NO_ROW) {
            gd = gd + dot(contact_terms[c].gradients[k].xyz, dv[row].xyz);
        }
    }
    outcome[i] = vec4<f32>(gd, 0.0, 0.0, 0.0);
}

fn spmv_row(i: u32) -> vec3<f32> {
    if (is_fixed(i)) {
        return vec3<f32>(0.0);
    }
    var acc = diag[i] * p[i].xyz;
    for (var s = offsets[i]; s < offsets[i + 1u]; s = s + 1u) {
        let nb = adjacency[s];
        acc = acc - spring_block[nb.y] * p[nb.x].xyz;
    }
    return acc;
}

// Workgroup sum of `value` into partials[workgroup].
fn workgroup_sum(value: vec4<f32>, lid: u32, wid: u32) {
    shared_sum[lid] = value;
    workgroupBarrier();
    for (var stride = WG / 2u; stride > 0u; stride = stride / 2u) {
        if (lid < stride) {
            shared_sum[lid] = shared_sum[lid] + shared_sum[lid + stride];
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        partials[wid] = shared_sum[0];
    }
}

// Single-workgroup sum of all partials: one a workgroup of the system's rows (the
// simulated tools' rows too, which can open a workgroup of their own).
fn reduce_partials(lid: u32) -> vec4<f32> {
    var acc = vec4<f32>(0.0);
    let slots = (params.system.x + WG - 1u) / WG;
    for (var k = lid; k < slots; k = k + WG) {
        acc = acc + partials[k];
    }
    shared_sum[lid] = acc;
    workgroupBarrier();
    for (var stride = WG / 2u; stride > 0u; stride = stride / 2u) {
        if (lid < stride) {
            shared_sum[lid] = shared_sum[lid] + shared_sum[lid + stride];
        }
        workgroupBarrier();
    }
    return shared_sum[0];
}

// ---- conjugate gradient ------------------------------------------------------------------

// CG's start, extrapolated from the last two steps' Δv (the previous one copied into q
// beforehand), as cpu/implicit.rs `implicit_euler` starts it.
@compute @workgroup_size(256)
fn cg_extrapolate(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i < params.system.x) {
        dv[i] = vec4<f32>(dv[i].xyz * 2.0 - q[i].xyz, 0.0);
    }
}

// q = A dv (dv copied into p beforehand), for the warm-started initial residual.
@compute @workgroup_size(256)
fn cg_start_spmv(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i < params.system.x) {
        q[i] = vec4<f32>(spmv_row(i), 0.0);
    }
}

@compute @workgroup_size(256)
fn cg_init(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let i = gid.x;
    var sums = vec4<f32>(0.0);
    if (i < params.system.x) {
        let ri = rhs[i].xyz - q[i].xyz;
        let zi = precond[i] * ri;
        r[i] = vec4<f32>(ri, 0.0);
        z[i] = vec4<f32>(zi, 0.0);
        p[i] = vec4<f32>(zi, 0.0);
        sums = vec4<f32>(dot(ri, zi), dot(ri, ri), dot(rhs[i].xyz, rhs[i].xyz), 0.0);
    }
    workgroup_sum(sums, lid.x, wid.x);
}

@compute @workgroup_size(256)
fn cg_init_reduce(@builtin(local_invocation_id) lid: vec3<u32>) {
    let s = reduce_partials(lid.x);
    if (lid.x == 0u) {
        scalars.rz = s.x;
        scalars.rr = s.y;
        scalars.bb = s.z;
        scalars.iterations = 0u;
        scalars.done = select(0u, 1u, s.y <= params.cg.x * s.z);
    }
}

@compute @workgroup_size(256)
fn cg_spmv(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    let i = gid.x;
    var sums = vec4<f32>(0.0);
    if (i < params.system.x) {
        let qi = spmv_row(i);
        q[i] = vec4<f32>(qi, 0.0);
        sums.x = dot(p[i].xyz, qi);
    }
    workgroup_sum(sums, lid.x, wid.x);
}

@compute @workgroup_size(256)
fn cg_alpha(@builtin(local_invocation_id) lid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    let s = reduce_partials(lid.x);
    if (lid.x == 0u) {
        let pq = s.x + scalars.contact_pq;
        scalars.pq = pq;
        if (pq <= 0.0) {
            scalars.done = 1u;
            scalars.alpha = 0.0;
        } else {
            scalars.alpha = scalars.rz / pq;
        }
    }
}

@compute @workgroup_size(256)
fn cg_update(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    let i = gid.x;
    let alpha = scalars.alpha;
    var sums = vec4<f32>(0.0);
    if (i < params.system.x) {
        dv[i] = vec4<f32>(dv[i].xyz + p[i].xyz * alpha, 0.0);
        let ri = r[i].xyz - q[i].xyz * alpha;
        let zi = precond[i] * ri;
        r[i] = vec4<f32>(ri, 0.0);
        z[i] = vec4<f32>(zi, 0.0);
        sums = vec4<f32>(dot(ri, zi), dot(ri, ri), 0.0, 0.0);
    }
    workgroup_sum(sums, lid.x, wid.x);
}

@compute @workgroup_size(256)
fn cg_beta(@builtin(local_invocation_id) lid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    let s = reduce_partials(lid.x);
    if (lid.x == 0u) {
        scalars.beta = s.x / scalars.rz;
        scalars.rz = s.x;
        scalars.rr = s.y;
        scalars.iterations = scalars.iterations + 1u;
        let converged = s.y <= params.cg.x * scalars.bb;
        let exhausted = f32(scalars.iterations) >= params.cg.y;
        // Done: every later kernel of this batch returns at once.
        scalars.done = select(0u, 1u, converged || exhausted);
    }
}

@compute @workgroup_size(256)
fn cg_direction(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    let i = gid.x;
    if (i < params.system.x) {
        p[i] = vec4<f32>(z[i].xyz + p[i].xyz * scalars.beta, 0.0);
    }
}

// ---- multigrid preconditioner -------------------------------------------------------------
// z = M⁻¹ r by one symmetric V-cycle, as cpu/implicit.rs `apply_amg`: z₀ = ω B r (B the
// inverse diagonal blocks), z₁ = z₀ + P (cycle) R (r - A z₀) over the nodes, z = z₁ + ω B (r -
// A z₁). The products reuse the CG's own (q = A p, contacts included), so p holds z₀ and z₁
// meanwhile (the host saves the direction around them); the coarse cycle (coarse.wgsl) reads
// the nodes' residual from `aux` and writes its correction to `force`, both idle in an
// implicit step.

@compute @workgroup_size(256)
fn amg_presmooth(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    let i = gid.x;
    if (i < params.system.x) {
        p[i] = vec4<f32>(precond[i] * r[i].xyz * params.cg.z, 0.0);
    }
}

@compute @workgroup_size(256)
fn amg_residual(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    let i = gid.x;
    if (i < params.counts.x) {
        aux[i] = vec4<f32>(r[i].xyz - q[i].xyz, 0.0);
    }
}

@compute @workgroup_size(256)
fn amg_correct(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    let i = gid.x;
    if (i < params.counts.x) {
        p[i] = vec4<f32>(p[i].xyz + force[i].xyz, 0.0);
    }
}

// z = z₁ + ω B (r - A z₁), with r·z and r·r into the partial sums (as cg_update leaves them).
@compute @workgroup_size(256)
fn amg_postsmooth(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    let i = gid.x;
    var sums = vec4<f32>(0.0);
    if (i < params.system.x) {
        let ri = r[i].xyz;
        let zi = p[i].xyz + precond[i] * (ri - q[i].xyz) * params.cg.z;
        z[i] = vec4<f32>(zi, 0.0);
        sums = vec4<f32>(dot(ri, zi), dot(ri, ri), 0.0, 0.0);
    }
    workgroup_sum(sums, lid.x, wid.x);
}

// The start's r·z with the multigrid's z (cg_init_reduce set the rest).
@compute @workgroup_size(256)
fn amg_init_reduce(@builtin(local_invocation_id) lid: vec3<u32>) {
    if (scalars.done != 0u) {
        return;
    }
    let s = reduce_partials(lid.x);
    if (lid.x == 0u) {
        scalars.rz = s.x;
    }
}

// ---- integration -------------------------------------------------------------------------

@compute @workgroup_size(256)
fn implicit_update(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    // Queued behind a solve that may not be done yet: nothing until it is.
    if (i >= params.counts.x || scalars.done == 0u) {
        return;
    }
    if (is_fixed(i)) {
        v[i] = vec4<f32>(0.0);
        return;
    }
    let vi = v[i].xyz + dv[i].xyz;
    v[i] = vec4<f32>(vi, 0.0);
    u[i] = vec4<f32>(u[i].xyz + vi * params.gravity_h.w, 0.0);
}

@compute @workgroup_size(256)
fn node_forces(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i < params.counts.x) {
        force[i] = vec4<f32>(gathered_force(i), 0.0);
    }
}

@compute @workgroup_size(256)
fn explicit_euler_update(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.counts.x) {
        return;
    }
    if (is_fixed(i)) {
        v[i] = vec4<f32>(0.0);
        return;
    }
    let h = params.gravity_h.w;
    let vi = v[i].xyz;
    u[i] = vec4<f32>(u[i].xyz + vi * h, 0.0);
    v[i] = vec4<f32>(vi + force[i].xyz * (h / node_params[i].x), 0.0);
}

@compute @workgroup_size(256)
fn verlet_update(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.counts.x) {
        return;
    }
    let xi = u[i].xyz;
    if (is_fixed(i)) {
        v[i] = vec4<f32>(0.0);
        aux[i] = vec4<f32>(xi, 0.0);
        return;
    }
    let h = params.gravity_h.w;
    let accel = force[i].xyz / node_params[i].x;
    let next = xi * 2.0 - aux[i].xyz + accel * (h * h);
    v[i] = vec4<f32>((next - xi) / h + accel * (h * 0.5), 0.0);
    aux[i] = vec4<f32>(xi, 0.0);
    u[i] = vec4<f32>(next, 0.0);
}

// Velocity Verlet, first half: positions, and the predicted velocities (in q) for damping.
@compute @workgroup_size(256)
fn velocity_verlet_positions(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.counts.x) {
        return;
    }
    let h = params.gravity_h.w;
    let a = aux[i].xyz;
    if (!is_fixed(i)) {
        u[i] = vec4<f32>(u[i].xyz + v[i].xyz * h + a * (0.5 * h * h), 0.0);
    }
    q[i] = vec4<f32>(v[i].xyz + a * h, 0.0);
}

@compute @workgroup_size(256)
fn velocity_verlet_velocities(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.counts.x) {
        return;
    }
    let h = params.gravity_h.w;
    let a_new = force[i].xyz / node_params[i].x;
    if (is_fixed(i)) {
        v[i] = vec4<f32>(0.0);
    } else {
        v[i] = vec4<f32>(v[i].xyz + (aux[i].xyz + a_new) * (0.5 * h), 0.0);
    }
    aux[i] = vec4<f32>(a_new, 0.0);
}

// Velocity Verlet start: a = f / m at the initial state.
@compute @workgroup_size(256)
fn acceleration_from_force(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i < params.counts.x) {
        aux[i] = vec4<f32>(force[i].xyz / node_params[i].x, 0.0);
    }
}
