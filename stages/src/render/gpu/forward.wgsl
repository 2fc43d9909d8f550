// Kernel `forward`: one workgroup per 16x16 tile, one thread per pixel
// (raster.rs render, step 4). The tile's depth-sorted splats are loaded by
// batches into workgroup memory; each pixel visits them front to back and
// blends only those whose support ellipse contains it (the same row
// intervals as the CPU), stops when its transmittance would drop below
// t_min, and the tile stops when every pixel has.
// Output per pixel: 8 values (r, g, b over the background, alpha, depth,
// ox, oy, fur), the final transmittance and 1 + the in-tile index of the
// last blended splat; per tile the number of Gaussian-pixel evaluations.

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> S: array<Splat>;
@group(0) @binding(2) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read_write> img: array<f32>;
@group(0) @binding(5) var<storage, read_write> tfinal: array<f32>;
@group(0) @binding(6) var<storage, read_write> ncontrib: array<u32>;
@group(0) @binding(7) var<storage, read_write> tile_evals: array<u32>;

const BATCH: u32 = 128u;
// (mean.x, mean.y, conic A, conic B), (conic C, opacity, k2, bits(row0)),
// (r, g, b, bits(row1)), (depth, ox, oy, fur).
var<workgroup> sa: array<vec4<f32>, BATCH>;
var<workgroup> sb: array<vec4<f32>, BATCH>;
var<workgroup> sf0: array<vec4<f32>, BATCH>;
var<workgroup> sf1: array<vec4<f32>, BATCH>;
var<workgroup> n_done: atomic<u32>;
var<workgroup> n_evals: atomic<u32>;
var<workgroup> all_done: u32;

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid3: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let tp = tile_pixel(wid, lid3);
    let tile = tp.tile;
    let x = tp.x;
    let y = tp.y;
    let inside = tp.inside;
    if lid == 0u {
        atomicStore(&n_done, 0u);
        atomicStore(&n_evals, 0u);
    }
    workgroupBarrier();
    var done = !inside;
    if done {
        atomicAdd(&n_done, 1u);
    }
    let px = f32(x) + 0.5;
    let py = f32(y) + 0.5;
    var tr = 1.0;
    var acc0 = vec4<f32>(0.0);
    var acc1 = vec4<f32>(0.0);
    var nc = 0u;
    var evals = 0u;
    let range = ranges[tile];
    let count = range.y - range.x;
    let n_batches = (count + BATCH - 1u) / BATCH;
    for (var bi = 0u; bi < n_batches; bi++) {
        workgroupBarrier();
        if lid == 0u {
            all_done = select(0u, 1u, atomicLoad(&n_done) == TP);
        }
        if workgroupUniformLoad(&all_done) == 1u {
            break;
        }
        let k0 = bi * BATCH;
        if lid < BATCH && k0 + lid < count {
            let sp = S[keys[range.x + k0 + lid].z];
            sa[lid] = sp.a;
            sb[lid] = sp.b;
            sf0[lid] = sp.f0;
            sf1[lid] = sp.f1;
        }
        workgroupBarrier();
        let m = min(BATCH, count - k0);
        for (var kk = 0u; kk < m; kk++) {
            if done {
                break;
            }
            let a = sa[kk];
            let b = sb[kk];
            if !covers(a, b, sf0[kk].w, x, y) {
                continue;
            }
            evals += 1u;
            let raw = b.y * falloff(a, b, px, py);
            let alpha = select(raw, P.alpha_max, raw > P.alpha_max);
            if alpha < P.alpha_min || !(alpha > 0.0) {
                continue;
            }
            let tn = tr * (1.0 - alpha);
            if tn < P.t_min {
                done = true;
                atomicAdd(&n_done, 1u);
                break;
            }
            let wgt = alpha * tr;
            acc0 += vec4<f32>(sf0[kk].xyz, 1.0) * wgt;
            acc1 += sf1[kk] * wgt;
            tr = tn;
            nc = k0 + kk + 1u;
        }
    }
    atomicAdd(&n_evals, evals);
    workgroupBarrier();
    if lid == 0u {
        tile_evals[tile] = atomicLoad(&n_evals);
    }
    if inside {
        let q = u32(y) * P.width + u32(x);
        img[q * 8u + 0u] = acc0.x + tr * P.bg.x;
        img[q * 8u + 1u] = acc0.y + tr * P.bg.y;
        img[q * 8u + 2u] = acc0.z + tr * P.bg.z;
        img[q * 8u + 3u] = 1.0 - tr;
        img[q * 8u + 4u] = acc1.x;
        img[q * 8u + 5u] = acc1.y;
        img[q * 8u + 6u] = acc1.z;
        img[q * 8u + 7u] = acc1.w;
        tfinal[q] = tr;
        ncontrib[q] = nc;
    }
}
