// Projection helpers shared by `project`, `emit` and `project_backward`
// (render/project.rs).

fn cam_w() -> mat3x3<f32> {
    return mat3x3<f32>(P.w0.xyz, P.w1.xyz, P.w2.xyz);
}

const SH_C0: f32 = 0.2820948;
const SH_C1: f32 = 0.4886025;

// Normalised quaternion (x, y, z, w) and the rotation matrix columns (rot_cols).
struct Rot {
    n: f32,
    q: vec4<f32>,
    r0: vec3<f32>,
    r1: vec3<f32>,
    r2: vec3<f32>,
}

fn rot_cols(q0: vec4<f32>) -> Rot {
    let n = length(q0);
    var q = vec4<f32>(0.0, 0.0, 0.0, 1.0);
    if n > 0.0 && is_finite_f(n) {
        q = q0 / n;
    }
    let x = q.x;
    let y = q.y;
    let z = q.z;
    let w = q.w;
    var o: Rot;
    o.n = n;
    o.q = q;
    o.r0 = vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y));
    o.r1 = vec3<f32>(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x));
    o.r2 = vec3<f32>(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));
    return o;
}

fn outer3(a: vec3<f32>, b: vec3<f32>) -> mat3x3<f32> {
    return mat3x3<f32>(a * b.x, a * b.y, a * b.z);
}

fn cov3(scale: vec3<f32>, r: Rot) -> mat3x3<f32> {
    let s2 = scale * scale;
    return outer3(r.r0, r.r0) * s2.x + outer3(r.r1, r.r1) * s2.y + outer3(r.r2, r.r2) * s2.z;
}

struct Proj {
    t: vec3<f32>,
    z: f32,
    rx: f32,
    ry: f32,
    clamp_x: bool,
    clamp_y: bool,
    j0: vec3<f32>,
    j1: vec3<f32>,
}

fn jacobian(p: vec3<f32>) -> Proj {
    var o: Proj;
    o.t = cam_w() * p + P.tw.xyz;
    o.z = -o.t.z;
    let rx0 = o.t.x / o.z;
    let ry0 = o.t.y / o.z;
    o.rx = clamp(rx0, P.rx_lo, P.rx_hi);
    o.ry = clamp(ry0, P.ry_lo, P.ry_hi);
    o.clamp_x = o.rx != rx0;
    o.clamp_y = o.ry != ry0;
    o.j0 = vec3<f32>(P.fx / o.z, 0.0, P.fx * o.rx / o.z);
    o.j1 = vec3<f32>(0.0, -P.fy / o.z, -P.fy * o.ry / o.z);
    return o;
}

// Gaussian record (layout = 24 f32 per Gaussian, `gpu::pack_gaussians`):
// mean 0..3, scale 3..6, rotation (x, y, z, w) 6..10, opacity 10, fur 11, sh 12..24.
fn g_vec3(i: u32, o: u32) -> vec3<f32> {
    let b = i * 24u + o;
    return vec3<f32>(G[b], G[b + 1u], G[b + 2u]);
}

fn g_rot(i: u32) -> vec4<f32> {
    let b = i * 24u + 6u;
    return vec4<f32>(G[b], G[b + 1u], G[b + 2u], G[b + 3u]);
}

// Rows of the support (raster.rs row_range).
fn sp_rows(sp: Splat) -> vec2<i32> {
    let ey = sqrt(sp.b.z * sp.cov.z);
    return vec2<i32>(ceil_i(sp.a.y - ey - 0.5), floor_i(sp.a.y + ey - 0.5));
}

// Calls visit(tile, j) for every tile the support touches, in increasing tile
// order (raster.rs for_each_tile: per band of tile rows, the union of the
// exact row intervals); returns the number of tiles.
fn for_each_tile(sp: Splat, gi: u32, base: u32) -> u32 {
    let rr = sp_rows(sp);
    let r0 = max(rr.x, 0);
    let r1 = min(rr.y, i32(P.height) - 1);
    let ex = sqrt(sp.b.z * sp.cov.x);
    let c0 = max(ceil_i(sp.a.x - ex - 0.5), 0);
    let c1 = min(floor_i(sp.a.x + ex - 0.5), i32(P.width) - 1);
    if r0 > r1 || c0 > c1 {
        return 0u;
    }
    let t = i32(TILE);
    var count = 0u;
    var band = r0 / t;
    var lo = 2147483647;
    var hi = -2147483647 - 1;
    let mean = sp.a.xy;
    for (var y = r0; y <= r1 + 1; y++) {
        if y > r1 || y / t != band {
            if lo <= hi {
                for (var tx = lo / t; tx <= hi / t; tx++) {
                    visit(u32(band) * P.tiles_x + u32(tx), gi, base + count);
                    count += 1u;
                }
            }
            if y > r1 {
                break;
            }
            band = y / t;
            lo = 2147483647;
            hi = -2147483647 - 1;
        }
        let s = row_span(mean, sp.a.z, sp.a.w, sp.b.x, sp.b.z, y);
        let a = max(s.x, c0);
        let b = min(s.y, c1);
        if s.x <= s.y && a <= b {
            lo = min(lo, a);
            hi = max(hi, b);
        }
    }
    return count;
}
