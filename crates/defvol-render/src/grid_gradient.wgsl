// Sampler::gradient (volume/cpu.rs) on the grid the including shader names by
// grid_dims() and grid_voxel(i, j, k) (the volume raycaster's volume, the tet raycaster's
// source): the grid's central differences (the neighbours clamped at the faces)
// interpolated in q's cell, which is the difference of clamped samples a voxel either
// side, read from 32 voxels instead of 48. Both raycasters prepend this file.
fn grid_gradient(q: vec3<f32>) -> vec3<f32> {
    let n = vec3<f32>(grid_dims());
    let c = clamp(q, vec3<f32>(0.0), n - 1.0);
    let i = min(vec3<u32>(c), max(grid_dims(), vec3<u32>(2u)) - 2u);
    let f = c - vec3<f32>(i);
    let last = grid_dims() - 1u;
    // Per axis the voxels before, at, after and two after the cell's first, clamped.
    let before = max(i, vec3<u32>(1u)) - 1u;
    let i1 = min(i + 1u, last);
    let i2 = min(i + 2u, last);
    return vec3<f32>(
        grid_gradient_axis(vec3<u32>(i1.x, i.y, i.z), vec3<u32>(i2.x, i1.y, i1.z), vec3<u32>(before.x, i.y, i.z), vec3<u32>(i.x, i1.y, i1.z), f),
        grid_gradient_axis(vec3<u32>(i.x, i1.y, i.z), vec3<u32>(i1.x, i2.y, i1.z), vec3<u32>(i.x, before.y, i.z), vec3<u32>(i1.x, i.y, i1.z), f),
        grid_gradient_axis(vec3<u32>(i.x, i.y, i1.z), vec3<u32>(i1.x, i1.y, i2.z), vec3<u32>(i.x, i.y, before.z), vec3<u32>(i1.x, i1.y, i.z), f),
    ) * 0.5;
}

// One axis of grid_gradient: at each corner of the cell (its bits choosing each component
// from the first or second position) the voxel one on minus the voxel one back,
// interpolated.
fn grid_gradient_axis(on0: vec3<u32>, on1: vec3<u32>, back0: vec3<u32>, back1: vec3<u32>, f: vec3<f32>) -> f32 {
    var d: array<f32, 8>;
    for (var c = 0u; c < 8u; c += 1u) {
        let bits = vec3<bool>((c & 1u) != 0u, (c & 2u) != 0u, (c & 4u) != 0u);
        let on = select(on0, on1, bits);
        let back = select(back0, back1, bits);
        d[c] = grid_voxel(on.x, on.y, on.z) - grid_voxel(back.x, back.y, back.z);
    }
    let c00 = d[0] + (d[1] - d[0]) * f.x;
    let c10 = d[2] + (d[3] - d[2]) * f.x;
    let c01 = d[4] + (d[5] - d[4]) * f.x;
    let c11 = d[6] + (d[7] - d[6]) * f.x;
    let c0 = c00 + (c10 - c00) * f.y;
    let c1 = c01 + (c11 - c01) * f.y;
    return c0 + (c1 - c0) * f.z;
}
