// Node positions on the device: nodes[i] = (base[i].xyz + A · displacement[i].xyz, base[i].w).
// `displacement` is another stage's buffer (the solver's displacements from rest); `base`
// and `A` put the result in the consumer's own units and frame. The CPU twin is
// `place` in nodes.rs.

struct Params {
    a0: vec4<f32>,      // rows of A (xyz)
    a1: vec4<f32>,
    a2: vec4<f32>,
    count: vec4<u32>,   // nodes, workgroups per row of the dispatch grid
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> base: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> displacement: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> nodes: array<vec4<f32>>;

@compute @workgroup_size(64)
fn place(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * params.count.y * 64u;
    if (i >= params.count.x) {
        return;
    }
    let u = displacement[i].xyz;
    let b = base[i];
    nodes[i] = vec4<f32>(b.xyz + vec3<f32>(dot(params.a0.xyz, u), dot(params.a1.xyz, u), dot(params.a2.xyz, u)), b.w);
}
