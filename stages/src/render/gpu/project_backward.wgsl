// Kernel `project_backward`: one thread per Gaussian: its screen-space
// gradient (mode 0: the sum of its instance records in tile order, as the
// CPU sums them; mode 1: the atomic accumulator), then the adjoint of the
// projection (project.rs project_backward). Output: 32 f32 per Gaussian:
// mean 0..3, scale 3..6, rotation (x, y, z, w) 6..10, opacity 10, sh 11..23,
// cov3d 23..29, means2d 29..31.

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> G: array<f32>;
@group(0) @binding(2) var<storage, read> S: array<Splat>;
@group(0) @binding(3) var<storage, read> offsets: array<u32>;
@group(0) @binding(4) var<storage, read> rec: array<f32>;
@group(0) @binding(5) var<storage, read_write> outg: array<f32>;

const NV: u32 = 13u;

fn visit(tile: u32, gi: u32, slot: u32) {}

fn put3(b: u32, v: vec3<f32>) {
    outg[b] = v.x;
    outg[b + 1u] = v.y;
    outg[b + 2u] = v.z;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg);
    if i >= P.n {
        return;
    }
    let ob = i * 32u;
    for (var k = 0u; k < 32u; k++) {
        outg[ob + k] = 0.0;
    }
    let sp = S[i];
    if (bitcast<u32>(sp.cov.w) & 1u) == 0u {
        return;
    }
    var g: array<f32, 13>;
    for (var v = 0u; v < NV; v++) {
        g[v] = 0.0;
    }
    if P.mode == 0u {
        for (var s = offsets[i]; s < offsets[i + 1u]; s++) {
            for (var v = 0u; v < NV; v++) {
                g[v] += rec[s * NV + v];
            }
        }
    } else {
        for (var v = 0u; v < NV; v++) {
            g[v] = rec[i * NV + v];
        }
    }
    let flags = bitcast<u32>(sp.cov.w);
    let mean = g_vec3(i, 0u);
    let scale = g_vec3(i, 3u);
    outg[ob + 10u] = g[5];
    let pr = jacobian(mean);
    let z = pr.z;
    let a = sp.cov.x;
    let b = sp.cov.y;
    let c = sp.cov.z;
    let ca = sp.a.z;
    let cb = sp.a.w;
    let cc = sp.b.x;
    let ga_c = g[2];
    let gb_c = g[3];
    let gc_c = g[4];
    var da = -(ga_c * ca * ca + gb_c * ca * cb + gc_c * cb * cb);
    var dc = -(ga_c * cb * cb + gb_c * cb * cc + gc_c * cc * cc);
    var db = -(2.0 * ga_c * ca * cb + gb_c * (ca * cc + cb * cb) + 2.0 * gc_c * cb * cc);
    let sum = a + c;
    let gox = g[10];
    let goy = g[11];
    let inv2 = 1.0 / (sum * sum);
    da += gox * 2.0 * c * inv2 - goy * 2.0 * b * inv2;
    dc += -gox * 2.0 * a * inv2 - goy * 2.0 * b * inv2;
    db += goy * 2.0 / sum;
    let r = rot_cols(g_rot(i));
    let sig = cov3(scale, r);
    let w = cam_w();
    let wt = transpose(w);
    let t0 = wt * pr.j0;
    let t1 = wt * pr.j1;
    let st0 = sig * t0;
    let st1 = sig * t1;
    let g3 = outer3(t0, t0) * da + (outer3(t0, t1) + outer3(t1, t0)) * (0.5 * db) + outer3(t1, t1) * dc;
    let dt0 = 2.0 * da * st0 + db * st1;
    let dt1 = 2.0 * dc * st1 + db * st0;
    let dj0 = w * dt0;
    let dj1 = w * dt1;
    let fx = P.fx;
    let fy = P.fy;
    let z2 = z * z;
    var dtx = 0.0;
    var dty = 0.0;
    var dz = 0.0;
    dz += dj0.x * (-fx / z2);
    if pr.clamp_x {
        dz += dj0.z * (-fx * pr.rx / z2);
    } else {
        dtx += dj0.z * fx / z2;
        dz += dj0.z * (-2.0 * fx * pr.rx / z2);
    }
    dz += dj1.y * (fy / z2);
    if pr.clamp_y {
        dz += dj1.z * (fy * pr.ry / z2);
    } else {
        dty += dj1.z * (-fy / z2);
        dz += dj1.z * (2.0 * fy * pr.ry / z2);
    }
    let gu = g[0];
    let gv = g[1];
    dtx += gu * fx / z;
    dz += -gu * fx * pr.t.x / z2;
    dty += -gv * fy / z;
    dz += gv * fy * pr.t.y / z2;
    dz += g[9];
    let dt = vec3<f32>(dtx, dty, -dz);
    var gmean = wt * dt;
    let dcol = vec3<f32>(
        select(g[6], 0.0, (flags & 2u) != 0u),
        select(g[7], 0.0, (flags & 4u) != 0u),
        select(g[8], 0.0, (flags & 8u) != 0u),
    );
    put3(ob + 11u, SH_C0 * dcol);
    if P.sh_degree >= 1u {
        let rel = mean - P.center.xyz;
        let len = length(rel);
        if len > 0.0 {
            let dir = rel / len;
            put3(ob + 14u, -SH_C1 * dir.y * dcol);
            put3(ob + 17u, SH_C1 * dir.z * dcol);
            put3(ob + 20u, -SH_C1 * dir.x * dcol);
            let ddir = SH_C1 * vec3<f32>(-dot(g_vec3(i, 21u), dcol), -dot(g_vec3(i, 15u), dcol), dot(g_vec3(i, 18u), dcol));
            gmean += (ddir - dir * dot(dir, ddir)) / len;
        }
    }
    put3(ob, gmean);
    outg[ob + 23u] = g3[0].x;
    outg[ob + 24u] = g3[1].x + g3[0].y;
    outg[ob + 25u] = g3[2].x + g3[0].z;
    outg[ob + 26u] = g3[1].y;
    outg[ob + 27u] = g3[2].y + g3[1].z;
    outg[ob + 28u] = g3[2].z;
    let s2 = scale * scale;
    let gr0 = g3 * r.r0;
    let gr1 = g3 * r.r1;
    let gr2 = g3 * r.r2;
    put3(ob + 3u, vec3<f32>(2.0 * scale.x * dot(r.r0, gr0), 2.0 * scale.y * dot(r.r1, gr1), 2.0 * scale.z * dot(r.r2, gr2)));
    let e0 = 2.0 * s2.x * gr0;
    let e1 = 2.0 * s2.y * gr1;
    let e2 = 2.0 * s2.z * gr2;
    if r.n > 0.0 && is_finite_f(r.n) {
        let x = r.q.x;
        let y = r.q.y;
        let zq = r.q.z;
        let ww = r.q.w;
        let dw = 2.0 * (e0.y * zq - e0.z * y - e1.x * zq + e1.z * x + e2.x * y - e2.y * x);
        let dx = 2.0 * (y * e0.y + zq * e0.z + y * e1.x + ww * e1.z + zq * e2.x - ww * e2.y) - 4.0 * x * (e1.y + e2.z);
        let dy = 2.0 * (x * e0.y - ww * e0.z + x * e1.x + zq * e1.z + ww * e2.x + zq * e2.y) - 4.0 * y * (e0.x + e2.z);
        let dzq = 2.0 * (ww * e0.y + x * e0.z - ww * e1.x + y * e1.z + x * e2.x + y * e2.y) - 4.0 * zq * (e0.x + e1.y);
        let dq = vec4<f32>(dx, dy, dzq, dw);
        let draw = (dq - r.q * dot(r.q, dq)) / r.n;
        outg[ob + 6u] = draw.x;
        outg[ob + 7u] = draw.y;
        outg[ob + 8u] = draw.z;
        outg[ob + 9u] = draw.w;
    }
    outg[ob + 29u] = g[0];
    outg[ob + 30u] = g[1];
}
