// Shared by raycast.wgsl and tet_raycast.wgsl, which are compiled with this file in front:
// Camera::ray, ToolPicture::hit with volume::nearest_tool, and the RGBA8 of Rendered.

struct Ray {
    origin: vec3<f32>,
    dir: vec3<f32>,
}

// Camera::ray for pixel `px` of an image of `size`: the camera's rotation columns and eye,
// proj = (perspective 1 or orthographic 0, tan(fov/2) or the view's height, aspect, -).
fn camera_ray(px: vec2<u32>, size: vec2<u32>, cam_x: vec3<f32>, cam_y: vec3<f32>, cam_z: vec3<f32>, eye: vec3<f32>, proj: vec4<f32>) -> Ray {
    let u = ((f32(px.x) + 0.5) / f32(size.x)) * 2.0 - 1.0;
    let v = ((f32(px.y) + 0.5) / f32(size.y)) * 2.0 - 1.0;
    var local_origin = vec3<f32>(0.0);
    var local_dir = vec3<f32>(0.0, 0.0, 1.0);
    if proj.x > 0.5 {
        local_dir = normalize(vec3<f32>(u * proj.y * proj.z, v * proj.y, 1.0));
    } else {
        local_origin = vec3<f32>(u * proj.y / 2.0 * proj.z, v * proj.y / 2.0, 0.0);
    }
    let origin = eye + cam_x * local_origin.x + cam_y * local_origin.y + cam_z * local_origin.z;
    let dir = cam_x * local_dir.x + cam_y * local_dir.y + cam_z * local_dir.z;
    return Ray(origin, dir);
}

// ToolPicture::hit (sphere tracing a capsule), then nearest_tool: (t, lit colour), t < 0
// when no tool is hit. Per tool: tip and radius, tail, colour.
fn tool_hit(tools_in: array<vec4<f32>, 12>, count: u32, ambient: f32, origin: vec3<f32>, dir: vec3<f32>, light: vec3<f32>) -> vec4<f32> {
    var tools = tools_in;
    var best = vec4<f32>(-1.0, 0.0, 0.0, 0.0);
    var best_t = 1e30;
    for (var k = 0u; k < count; k++) {
        let a = tools[3u * k].xyz;
        let radius = tools[3u * k].w;
        let ab = tools[3u * k + 1u].xyz - a;
        var t = 0.0;
        for (var n = 0; n < 128; n++) {
            let q = origin + dir * t;
            var h = 0.0;
            if dot(ab, ab) > 0.0 {
                h = clamp(dot(q - a, ab) / dot(ab, ab), 0.0, 1.0);
            }
            let outward = q - (a + ab * h);
            let dist = length(outward) - radius;
            if dist < 1e-6 * (1.0 + t) {
                if t < best_t {
                    best_t = t;
                    var normal = -dir;
                    if length(outward) > 1e-12 {
                        normal = outward / length(outward);
                    }
                    let f = ambient + (1.0 - ambient) * max(dot(normal, light), 0.0);
                    best = vec4<f32>(t, tools[3u * k + 2u].xyz * f);
                }
                break;
            }
            t += dist;
            if t > 1e7 {
                break;
            }
        }
    }
    return best;
}

fn pack(c: vec4<f32>) -> u32 {
    let b = vec4<u32>(round(clamp(c, vec4<f32>(0.0), vec4<f32>(1.0)) * 255.0));
    return b.x | (b.y << 8u) | (b.z << 16u) | (b.w << 24u);
}
