// The multigrid coarse correction on the device, the twin of `Amg::coarse_correction`
// (amg.rs): CSR products for the restrictions down and the prolongations up, the additive
// levels' damped Jacobi term, and the coarsest level's dense inverse. One invocation a row.

struct Params {
    rows: u32,      // rows of the product
    groups: u32,    // workgroups per row of the dispatch grid
    cols: u32,      // columns of the dense inverse
    omega: f32,     // damping of the Jacobi term
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> indptr: array<u32>;
@group(0) @binding(2) var<storage, read> indices: array<u32>;
@group(0) @binding(3) var<storage, read> values: array<f32>;
@group(0) @binding(4) var<storage, read> x: array<f32>;
@group(0) @binding(5) var<storage, read_write> y: array<f32>;

fn row_of(gid: vec3<u32>) -> u32 {
    return gid.x + gid.y * params.groups * 64u;
}

// y = M x, M in CSR (indptr, indices, values).
@compute @workgroup_size(64)
fn csr_product(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = row_of(gid);
    if (r >= params.rows) {
        return;
    }
    var sum = 0.0;
    for (var k = indptr[r]; k < indptr[r + 1u]; k = k + 1u) {
        sum = sum + values[k] * x[indices[k]];
    }
    y[r] = sum;
}

// y += ω D⁻¹ x, values = D⁻¹ of the level, x its right-hand side.
@compute @workgroup_size(64)
fn add_jacobi(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = row_of(gid);
    if (r >= params.rows) {
        return;
    }
    y[r] = y[r] + params.omega * values[r] * x[r];
}

// y = M x, M dense and row-major (rows x cols): the coarsest level's inverse.
@compute @workgroup_size(64)
fn dense_product(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = row_of(gid);
    if (r >= params.rows) {
        return;
    }
    var sum = 0.0;
    let base = r * params.cols;
    for (var c = 0u; c < params.cols; c = c + 1u) {
        sum = sum + values[base + c] * x[c];
    }
    y[r] = sum;
}
