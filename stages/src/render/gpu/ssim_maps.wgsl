// Kernel `ssim_maps` (one thread per pixel and channel): from the planes
// x (channels), y (channels), the products SSIM blurs: per channel c the
// planes 5c .. 5c + 4 = x, y, x^2, y^2, x y.

@group(0) @binding(0) var<uniform> P: SsimParams;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> maps: array<f32>;

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
    let o = 5u * c * npix + q;
    maps[o] = x;
    maps[o + npix] = y;
    maps[o + 2u * npix] = x * x;
    maps[o + 3u * npix] = y * y;
    maps[o + 4u * npix] = x * y;
}
