// Kernel `project`: one thread per Gaussian: EWA projection (project.rs
// project_one), its support rows and the number of tiles it touches.

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> G: array<f32>;
@group(0) @binding(2) var<storage, read_write> S: array<Splat>;
@group(0) @binding(3) var<storage, read_write> counts: array<u32>;

fn visit(tile: u32, gi: u32, slot: u32) {}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg);
    if i >= P.n {
        return;
    }
    var sp: Splat;
    sp.a = vec4<f32>(0.0);
    sp.b = vec4<f32>(0.0);
    sp.f0 = vec4<f32>(0.0);
    sp.f1 = vec4<f32>(0.0);
    sp.cov = vec4<f32>(0.0);
    counts[i] = 0u;
    let mean = g_vec3(i, 0u);
    let scale = g_vec3(i, 3u);
    let opacity = G[i * 24u + 10u];
    let pr = jacobian(mean);
    if !(pr.z >= P.near) || !(opacity > P.alpha_min) || !(opacity > 0.0) {
        S[i] = sp;
        return;
    }
    let r = rot_cols(g_rot(i));
    let sig = cov3(scale, r);
    let wt = transpose(cam_w());
    let t0 = wt * pr.j0;
    let t1 = wt * pr.j1;
    let st0 = sig * t0;
    let st1 = sig * t1;
    let a = dot(t0, st0) + P.low_pass;
    let b = dot(t0, st1);
    let c = dot(t1, st1) + P.low_pass;
    let det = a * c - b * b;
    if !(det > 0.0) || !is_finite_f(det) {
        S[i] = sp;
        return;
    }
    var k2 = P.extent * P.extent;
    if P.alpha_min > 0.0 {
        k2 = min(k2, 2.0 * log(opacity / P.alpha_min));
    }
    let u = P.cx + P.fx * pr.t.x / pr.z;
    let v = P.cy - P.fy * pr.t.y / pr.z;
    let ex = sqrt(k2 * a);
    let ey = sqrt(k2 * c);
    let wf = f32(P.width);
    let hf = f32(P.height);
    if !(u + ex > 0.0 && u - ex < wf && v + ey > 0.0 && v - ey < hf) {
        S[i] = sp;
        return;
    }
    // normalize_or_zero(mean - center)
    let rel = mean - P.center.xyz;
    let rcp = 1.0 / length(rel);
    var dir = vec3<f32>(0.0);
    if is_finite_f(rcp) && rcp > 0.0 {
        dir = rel * rcp;
    }
    var col = vec3<f32>(0.5) + SH_C0 * g_vec3(i, 12u);
    if P.sh_degree >= 1u {
        col += SH_C1 * (-dir.y * g_vec3(i, 15u) + dir.z * g_vec3(i, 18u) - dir.x * g_vec3(i, 21u));
    }
    let inv = 1.0 / det;
    var flags = 1u;
    if col.x < 0.0 {
        flags |= 2u;
    }
    if col.y < 0.0 {
        flags |= 4u;
    }
    if col.z < 0.0 {
        flags |= 8u;
    }
    sp.a = vec4<f32>(u, v, c * inv, -b * inv);
    sp.b = vec4<f32>(a * inv, opacity, k2, 0.0);
    sp.f0 = vec4<f32>(max(col.x, 0.0), max(col.y, 0.0), max(col.z, 0.0), 0.0);
    sp.f1 = vec4<f32>(pr.z, (a - c) / (a + c), 2.0 * b / (a + c), G[i * 24u + 11u]);
    sp.cov = vec4<f32>(a, b, c, bitcast<f32>(flags));
    let rows = sp_rows(sp);
    sp.b.w = bitcast<f32>(rows.x);
    sp.f0.w = bitcast<f32>(rows.y);
    S[i] = sp;
    counts[i] = for_each_tile(sp, i, 0u);
}
