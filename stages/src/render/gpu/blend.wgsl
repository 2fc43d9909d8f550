// Kernel `blend`: one workgroup per tile, one thread per pixel (raster.rs
// blend_sums). Front to back over the tile's splats up to the last one any
// pixel blended (the forward pass's `ncontrib`), with the forward kernel's
// arithmetic, each pixel's weight alpha T multiplies its four pixel values
// (target r, g, b, pixel weight). Per instance the four products are summed
// over the tile's pixels in a fixed order (16 partial sums of 16 pixels, then
// the 16 partials) and written to the instance's slot; `blend_gather` sums a
// Gaussian's slots in tile order.

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> S: array<Splat>;
@group(0) @binding(2) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read> pix: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> ncontrib: array<u32>;
@group(0) @binding(6) var<storage, read_write> rec: array<vec4<f32>>;

var<workgroup> red: array<vec4<f32>, 256>;
var<workgroup> part: array<vec4<f32>, 16>;
var<workgroup> max_nc: atomic<u32>;
var<workgroup> last: u32;

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
    var nc = 0u;
    var v = vec4<f32>(0.0);
    if inside {
        let q = u32(y) * P.width + u32(x);
        nc = ncontrib[q];
        v = pix[q];
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
    var tr = 1.0;
    for (var k = 0u; k < n_last; k++) {
        let key = keys[base + k];
        let sp = S[key.z];
        var c = vec4<f32>(0.0);
        // k < nc: the pixel had not stopped (its last blend is at nc - 1).
        if k < nc && covers(sp.a, sp.b, sp.f0.w, x, y) {
            let raw = sp.b.y * falloff(sp.a, sp.b, px, py);
            let alpha = select(raw, P.alpha_max, raw > P.alpha_max);
            if !(alpha < P.alpha_min || !(alpha > 0.0)) {
                c = v * (alpha * tr);
                tr = tr * (1.0 - alpha);
            }
        }
        red[lid] = c;
        workgroupBarrier();
        if lid < 16u {
            var t = vec4<f32>(0.0);
            for (var e = 0u; e < 16u; e++) {
                t += red[lid * 16u + e];
            }
            part[lid] = t;
        }
        workgroupBarrier();
        if lid == 0u {
            var t = vec4<f32>(0.0);
            for (var e = 0u; e < 16u; e++) {
                t += part[e];
            }
            rec[key.w] = t;
        }
    }
}
