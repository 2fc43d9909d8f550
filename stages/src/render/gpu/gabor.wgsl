// Kernel `gabor` (one thread per pixel): `growth/orientation.rs`
// `orientation_maps`' per-pixel work on the mirror-padded DoG image: the
// |response| of every filter of the bank, the first maximum's angle, and the
// confidence from the responses' circular variance around it. Sums run in
// the CPU's order: taps in bank order, filters in angle order.

struct GaborParams {
    width: u32,
    height: u32,
    // Row length of the padded image.
    pw: u32,
    // Padding on each side (the bank's half-size).
    half: u32,
    // Number of filters (orientations).
    n: u32,
    // 1 when `mask` holds a mask (pixels below 0.5 are skipped).
    has_mask: u32,
    pad0: u32,
    pad1: u32,
}

@group(0) @binding(0) var<uniform> P: GaborParams;
@group(0) @binding(1) var<storage, read> padded: array<f32>;
// Tap k's taps are starts[k] .. starts[k + 1]: offsets into `padded`
// relative to the pixel, and weights.
@group(0) @binding(2) var<storage, read> tap_off: array<i32>;
@group(0) @binding(3) var<storage, read> tap_w: array<f32>;
@group(0) @binding(4) var<storage, read> starts: array<u32>;
@group(0) @binding(5) var<storage, read> mask: array<f32>;
// Per pixel: angle, confidence.
@group(0) @binding(6) var<storage, read_write> maps: array<f32>;

const PI: f32 = 3.14159265358979;
// The most filters the kernel takes (gabor.rs checks).
const MAX_ORIENTATIONS: u32 = 360u;

fn response(k: u32, centre: i32) -> f32 {
    var acc = 0.0;
    for (var t = starts[k]; t < starts[k + 1u]; t++) {
        acc += tap_w[t] * padded[u32(centre + tap_off[t])];
    }
    return abs(acc);
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let q = lin_id(gid, nwg);
    if q >= P.width * P.height {
        return;
    }
    if P.has_mask != 0u && mask[q] < 0.5 {
        maps[2u * q] = 0.0;
        maps[2u * q + 1u] = 0.0;
        return;
    }
    let x = q % P.width;
    let y = q / P.width;
    let centre = i32((y + P.half) * P.pw + x + P.half);
    // The responses are kept per thread: computing them again in a second
    // loop gave wrong values on lavapipe (measured).
    var f: array<f32, MAX_ORIENTATIONS>;
    var best = 0u;
    var sum = 0.0;
    for (var k = 0u; k < P.n; k++) {
        f[k] = response(k, centre);
        if f[k] > f[best] {
            best = k;
        }
        sum += f[k];
    }
    let th = f32(best) * PI / f32(P.n);
    var conf = 0.0;
    if sum > 0.0 {
        var v = 0.0;
        for (var k = 0u; k < P.n; k++) {
            let tk = f32(k) * PI / f32(P.n);
            var d = abs(th - tk);
            d = min(d, PI - d);
            v += f[k] / sum * d * d;
        }
        let r = v / (PI * PI);
        conf = 1.0 / (r * r + 1e-7);
    }
    maps[2u * q] = th;
    maps[2u * q + 1u] = conf;
}
