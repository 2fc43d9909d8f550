// Kernel `backward`: one workgroup per tile, one thread per pixel (raster.rs
// backward): the tile's splats back to front from the last one any pixel
// blended, transmittance recovered by division. Each instance's gradient
// (13 values: mean 2, conic 3, opacity, r, g, b, depth, ox, oy, fur) is the
// sum over the tile's pixels, reduced in workgroup memory in a fixed order
// (16 partial sums of 16 pixels each, then the 16 partials), so it does not
// depend on scheduling. P.mode = 0 (deterministic): the record goes to the
// instance's slot, and `project_backward` sums each Gaussian's slots in tile
// order. P.mode = 1 (atomic): it is added at once to the Gaussian's
// accumulator with a compare-exchange loop (faster, less memory; the
// order of the per-tile additions, so the last bits, vary run to run).

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> S: array<Splat>;
@group(0) @binding(2) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read> gpix: array<f32>;
@group(0) @binding(5) var<storage, read> tfinal: array<f32>;
@group(0) @binding(6) var<storage, read> ncontrib: array<u32>;
@group(0) @binding(7) var<storage, read_write> out: array<atomic<u32>>;

const NV: u32 = 13u;
var<workgroup> red: array<f32, 3328>; // NV * 256
var<workgroup> part: array<f32, 208>; // NV * 16
var<workgroup> max_nc: atomic<u32>;
var<workgroup> last: u32;

fn add_f32(i: u32, v: f32) {
    if v == 0.0 {
        return;
    }
    var old = atomicLoad(&out[i]);
    loop {
        let r = atomicCompareExchangeWeak(&out[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if r.exchanged {
            break;
        }
        old = r.old_value;
    }
}

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid3: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let tp = tile_pixel(wid, lid3);
    let tile = tp.tile;
    let x = tp.x;
    let y = tp.y;
    let inside = tp.inside;
    if lid == 0u {
        atomicStore(&max_nc, 0u);
    }
    workgroupBarrier();
    var tr = 0.0;
    var nc = 0u;
    var s0 = vec4<f32>(0.0); // r, g, b, alpha
    var s1 = vec4<f32>(0.0); // depth, ox, oy, fur
    var g0 = vec4<f32>(0.0);
    var g1 = vec4<f32>(0.0);
    if inside {
        let q = u32(y) * P.width + u32(x);
        tr = tfinal[q];
        nc = ncontrib[q];
        s0 = vec4<f32>(P.bg.x * tr, P.bg.y * tr, P.bg.z * tr, 0.0);
        g0 = vec4<f32>(gpix[q * 8u], gpix[q * 8u + 1u], gpix[q * 8u + 2u], gpix[q * 8u + 3u]);
        g1 = vec4<f32>(gpix[q * 8u + 4u], gpix[q * 8u + 5u], gpix[q * 8u + 6u], gpix[q * 8u + 7u]);
        atomicMax(&max_nc, nc);
    }
    workgroupBarrier();
    if lid == 0u {
        last = atomicLoad(&max_nc);
    }
    let n_last = workgroupUniformLoad(&last);
    let base = ranges[tile].x;
    let px = f32(x) + 0.5;
    let py = f32(y) + 0.5;
    for (var kr = 0u; kr < n_last; kr++) {
        let k = n_last - 1u - kr;
        let key = keys[base + k];
        let sp = S[key.z];
        var gm = vec2<f32>(0.0);
        var gc = vec3<f32>(0.0);
        var gop = 0.0;
        var gf0 = vec3<f32>(0.0);
        var gf1 = vec4<f32>(0.0);
        if k < nc && covers(sp.a, sp.b, sp.f0.w, x, y) {
            let ca = sp.a.z;
            let cb = sp.a.w;
            let cc = sp.b.x;
            let dx = px - sp.a.x;
            let dy = py - sp.a.y;
            let gauss = falloff(sp.a, sp.b, px, py);
            let raw = sp.b.y * gauss;
            let clamped = raw > P.alpha_max;
            let alpha = select(raw, P.alpha_max, clamped);
            if !(alpha < P.alpha_min || !(alpha > 0.0)) {
                let inv_one_m = 1.0 / (1.0 - alpha);
                let ti = tr * inv_one_m;
                let wgt = alpha * ti;
                let f0 = vec4<f32>(sp.f0.xyz, 1.0);
                let f1 = sp.f1;
                // dalpha summed over the 8 features in the CPU's order.
                let d0 = g0 * (f0 * ti - s0 * inv_one_m);
                let d1 = g1 * (f1 * ti - s1 * inv_one_m);
                let dalpha = (((((((d0.x + d0.y) + d0.z) + d0.w) + d1.x) + d1.y) + d1.z) + d1.w);
                gf0 = g0.xyz * wgt;
                gf1 = g1 * wgt;
                s0 += f0 * wgt;
                s1 += f1 * wgt;
                tr = ti;
                if !clamped {
                    gop = dalpha * gauss;
                    let dp = dalpha * alpha;
                    gm = vec2<f32>(dp * (ca * dx + cb * dy), dp * (cb * dx + cc * dy));
                    gc = vec3<f32>(-0.5 * dp * dx * dx, -dp * dx * dy, -0.5 * dp * dy * dy);
                }
            }
        }
        red[0u * TP + lid] = gm.x;
        red[1u * TP + lid] = gm.y;
        red[2u * TP + lid] = gc.x;
        red[3u * TP + lid] = gc.y;
        red[4u * TP + lid] = gc.z;
        red[5u * TP + lid] = gop;
        red[6u * TP + lid] = gf0.x;
        red[7u * TP + lid] = gf0.y;
        red[8u * TP + lid] = gf0.z;
        red[9u * TP + lid] = gf1.x;
        red[10u * TP + lid] = gf1.y;
        red[11u * TP + lid] = gf1.z;
        red[12u * TP + lid] = gf1.w;
        workgroupBarrier();
        if lid < NV * 16u {
            let v = lid / 16u;
            let o = v * TP + (lid % 16u) * 16u;
            var t = 0.0;
            for (var e = 0u; e < 16u; e++) {
                t += red[o + e];
            }
            part[lid] = t;
        }
        workgroupBarrier();
        if lid < NV {
            var t = 0.0;
            for (var e = 0u; e < 16u; e++) {
                t += part[lid * 16u + e];
            }
            if P.mode == 0u {
                atomicStore(&out[key.w * NV + lid], bitcast<u32>(t));
            } else {
                add_f32(key.z * NV + lid, t);
            }
        }
    }
}
