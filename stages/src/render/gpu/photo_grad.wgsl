// Kernel `photo_grad` (one thread per pixel, 256 per workgroup): the pixel
// gradients of (1 - lambda) L1 + lambda (1 - SSIM) + w |alpha - mask| in
// backward.wgsl's layout, and per workgroup the sums of |x - y| over the
// channels, of the per-pixel SSIM over the channels and of |alpha - mask|,
// reduced in workgroup memory in a fixed tree (the host sums the partials in
// workgroup order: the same bits on every run).

@group(0) @binding(0) var<uniform> P: PhotoParams;
@group(0) @binding(1) var<storage, read> img: array<f32>;
@group(0) @binding(2) var<storage, read> src: array<f32>;
@group(0) @binding(3) var<storage, read> ssim_map: array<f32>;
@group(0) @binding(4) var<storage, read> gssim: array<f32>;
@group(0) @binding(5) var<storage, read_write> gpix: array<f32>;
@group(0) @binding(6) var<storage, read_write> partials: array<f32>;

var<workgroup> red: array<vec3<f32>, 256>;

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

@compute @workgroup_size(256)
fn main(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
) {
    let q = lin_id(gid, nwg);
    let npix = P.width * P.height;
    let ch = P.channels;
    var sums = vec3<f32>(0.0);
    if q < npix {
        for (var c = 0u; c < ch; c++) {
            let d = src[c * npix + q] - src[(ch + c) * npix + q];
            sums.x += abs(d);
            sums.y += ssim_map[c * npix + q];
            gpix[q * PIX + c] = (1.0 - P.lambda) * signed(d, P.norm) - P.lambda * gssim[q * ch + c];
        }
        let da = img[q * PIX + 3u] - src[(2u * ch + 1u) * npix + q];
        sums.z = abs(da);
        gpix[q * PIX + 3u] = signed(da, P.sil_norm) * P.sil_weight;
        for (var k = 4u; k < PIX; k++) {
            gpix[q * PIX + k] = 0.0;
        }
    }
    red[li] = sums;
    workgroupBarrier();
    for (var s = 128u; s > 0u; s >>= 1u) {
        if li < s {
            red[li] += red[li + s];
        }
        workgroupBarrier();
    }
    if li == 0u {
        let w = wid.x + wid.y * nwg.x;
        partials[3u * w] = red[0].x;
        partials[3u * w + 1u] = red[0].y;
        partials[3u * w + 2u] = red[0].z;
    }
}
