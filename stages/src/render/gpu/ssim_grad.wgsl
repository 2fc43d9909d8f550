// Kernel `ssim_grad` (one thread per pixel and channel): the gradient of
// the weighted mean SSIM w.r.t. the image from the blurred adjoints,
// interleaved like the image (pixel q, channel c at q * channels + c).

@group(0) @binding(0) var<uniform> P: SsimParams;
@group(0) @binding(1) var<storage, read> gadj: array<f32>;
@group(0) @binding(2) var<storage, read> src: array<f32>;
@group(0) @binding(3) var<storage, read_write> grad: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg);
    let npix = P.width * P.height;
    if i >= npix * P.channels {
        return;
    }
    let c = i / npix;
    let q = i % npix;
    let x = src[c * npix + q];
    let y = src[(P.channels + c) * npix + q];
    let o = 3u * c * npix + q;
    grad[q * P.channels + c] = gadj[o] + 2.0 * x * gadj[o + npix] + y * gadj[o + 2u * npix];
}
