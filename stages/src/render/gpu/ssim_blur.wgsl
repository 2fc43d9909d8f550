// Kernel `ssim_blur` (one thread per pixel and plane): one pass of the
// separable Gaussian window with zero padding, along rows (P.dir = 0) or
// columns (1); the taps summed in order, out-of-image ones skipped, as
// losses.rs `blur`.

@group(0) @binding(0) var<uniform> P: SsimParams;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg);
    let npix = P.width * P.height;
    if i >= npix * P.planes {
        return;
    }
    let base = (i / npix) * npix;
    let q = i % npix;
    let x = i32(q % P.width);
    let y = i32(q / P.width);
    var s = 0.0;
    for (var j = 0; j <= 2 * SSIM_R; j++) {
        if P.dir == 0u {
            let xx = x + j - SSIM_R;
            if xx >= 0 && xx < i32(P.width) {
                s += tap(P, j) * src[base + u32(y) * P.width + u32(xx)];
            }
        } else {
            let yy = y + j - SSIM_R;
            if yy >= 0 && yy < i32(P.height) {
                s += tap(P, j) * src[base + u32(yy) * P.width + u32(x)];
            }
        }
    }
    dst[i] = s;
}
