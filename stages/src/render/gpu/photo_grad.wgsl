// Kernel `photo_grad` (one thread per pixel, 256 per workgroup): the pixel
// gradients of the weighted image losses in backward.wgsl's layout, and per
// workgroup the sums of each term's per-pixel values (|x - y| and the SSIM
// over the colour channels, |alpha - mask|, |fur - fur mask|, confidence x
// region x angle error), reduced in workgroup memory in a fixed tree (the
// host sums the partials in workgroup order: the same bits on every run).

@group(0) @binding(0) var<uniform> P: PhotoParams;
@group(0) @binding(1) var<storage, read> img: array<f32>;
@group(0) @binding(2) var<storage, read> src: array<f32>;
@group(0) @binding(3) var<storage, read> ssim_map: array<f32>;
@group(0) @binding(4) var<storage, read> gssim: array<f32>;
@group(0) @binding(5) var<storage, read_write> gpix: array<f32>;
@group(0) @binding(6) var<storage, read_write> partials: array<f32>;

const PI: f32 = 3.14159265358979;
// losses.rs ORIENTATION_EPS.
const ORI_EPS: f32 = 1e-8;

var<workgroup> red4: array<vec4<f32>, 256>;
var<workgroup> red1: array<f32, 256>;

// sign(d) x scale, 0 at d = 0 (losses.rs `l1`).
fn signed(d: f32, scale: f32) -> f32 {
    if d > 0.0 {
        return scale;
    }
    if d < 0.0 {
        return -scale;
    }
    return 0.0;
}

// x mod y in [0, y) for y > 0 (Rust's rem_euclid).
fn rem_euclid(x: f32, y: f32) -> f32 {
    let r = x - y * trunc(x / y);
    if r < 0.0 {
        return r + y;
    }
    return r;
}

// render/mod.rs `orientation_from_feature`.
fn orientation_from_feature(ox: f32, oy: f32) -> f32 {
    if ox == 0.0 && oy == 0.0 {
        return 0.0;
    }
    let a = rem_euclid(0.5 * atan2(oy, ox), PI);
    if a >= PI {
        return 0.0;
    }
    return a;
}

// losses.rs `angle_diff`: (pi-periodic |a - b| in [0, pi/2], its sign).
fn angle_diff(a: f32, b: f32) -> vec2<f32> {
    var d = rem_euclid(a - b, PI);
    if d >= PI {
        d = 0.0;
    }
    if d > 0.5 * PI {
        return vec2<f32>(PI - d, -1.0);
    }
    if d > 0.0 {
        return vec2<f32>(d, 1.0);
    }
    return vec2<f32>(0.0, 0.0);
}

fn plane(p: u32, q: u32) -> f32 {
    return src[p * P.width * P.height + q];
}

@compute @workgroup_size(256)
fn main(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
) {
    let q = lin_id(gid, nwg);
    let npix = P.width * P.height;
    var sums = vec4<f32>(0.0);
    var s_ori = 0.0;
    if q < npix {
        for (var k = 0u; k < PIX; k++) {
            gpix[q * PIX + k] = 0.0;
        }
        if (P.terms & 1u) != 0u {
            for (var c = 0u; c < 3u; c++) {
                let d = plane(c, q) - plane(3u + c, q);
                sums.x += abs(d);
                sums.y += ssim_map[c * npix + q];
                let g = (1.0 - P.lambda) * signed(d, P.norm) - P.lambda * gssim[q * 3u + c];
                gpix[q * PIX + c] = g * P.w_rgb;
            }
        }
        if (P.terms & 2u) != 0u {
            let d = img[q * PIX + 3u] - plane(P_MASK, q);
            sums.z = abs(d);
            gpix[q * PIX + 3u] = signed(d, P.pix_norm) * P.w_sil;
        }
        if (P.terms & 4u) != 0u {
            let d = img[q * PIX + 7u] - plane(P_FUR, q);
            sums.w = abs(d);
            gpix[q * PIX + 7u] = signed(d, P.pix_norm) * P.w_fur;
        }
        if (P.terms & 8u) != 0u {
            let wgt = plane(P_REGION, q) * plane(P_CONF, q);
            if wgt != 0.0 {
                let ox = img[q * PIX + 5u];
                let oy = img[q * PIX + 6u];
                let ad = angle_diff(orientation_from_feature(ox, oy), plane(P_ANGLE, q));
                s_ori = wgt * ad.x;
                let r2 = ox * ox + oy * oy;
                if r2 > ORI_EPS {
                    let s = wgt * P.ori_norm * ad.y * 0.5 / r2;
                    gpix[q * PIX + 5u] = -oy * s * P.w_ori;
                    gpix[q * PIX + 6u] = ox * s * P.w_ori;
                }
            }
        }
    }
    red4[li] = sums;
    red1[li] = s_ori;
    workgroupBarrier();
    for (var s = 128u; s > 0u; s >>= 1u) {
        if li < s {
            red4[li] += red4[li + s];
            red1[li] += red1[li + s];
        }
        workgroupBarrier();
    }
    if li == 0u {
        let w = wid.x + wid.y * nwg.x;
        partials[5u * w] = red4[0].x;
        partials[5u * w + 1u] = red4[0].y;
        partials[5u * w + 2u] = red4[0].z;
        partials[5u * w + 3u] = red4[0].w;
        partials[5u * w + 4u] = red1[0];
    }
}
