// Kernel `photo_planes` (one thread per pixel and colour channel): the
// rendered colour, read in place from the forward image, as the SSIM's
// planes x.

@group(0) @binding(0) var<uniform> P: PhotoParams;
@group(0) @binding(1) var<storage, read> img: array<f32>;
@group(0) @binding(2) var<storage, read_write> src: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg);
    let npix = P.width * P.height;
    if i >= npix * 3u {
        return;
    }
    let c = i / npix;
    let q = i % npix;
    src[c * npix + q] = img[q * PIX + c];
}
