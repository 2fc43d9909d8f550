// Kernel `ssim_terms` (one thread per pixel and channel): from the blurred
// planes (mu_x, mu_y, E[x^2], E[y^2], E[xy] per channel) the per-pixel SSIM
// into `ssim_map` (plane c) and the adjoints that the window spreads back:
// planes 3c .. 3c + 2 of `adj` = d/dmu_x, d/dE[x^2], d/dE[xy] of
// norm x weight x SSIM (losses.rs `ssim_channel`).

@group(0) @binding(0) var<uniform> P: SsimParams;
@group(0) @binding(1) var<storage, read> blurred: array<f32>;
@group(0) @binding(2) var<storage, read> src: array<f32>;
@group(0) @binding(3) var<storage, read_write> ssim_map: array<f32>;
@group(0) @binding(4) var<storage, read_write> adj: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg);
    let npix = P.width * P.height;
    if i >= npix * P.channels {
        return;
    }
    let c = i / npix;
    let q = i % npix;
    let b = 5u * c * npix + q;
    let ux = blurred[b];
    let uy = blurred[b + npix];
    let sx = blurred[b + 2u * npix] - ux * ux;
    let sy = blurred[b + 3u * npix] - uy * uy;
    let sxy = blurred[b + 4u * npix] - ux * uy;
    let a1 = 2.0 * ux * uy + SSIM_C1;
    let a2 = 2.0 * sxy + SSIM_C2;
    let b1 = ux * ux + uy * uy + SSIM_C1;
    let b2 = sx + sy + SSIM_C2;
    let s = a1 * a2 / (b1 * b2);
    ssim_map[i] = s;
    // The weights are the last plane of `src` (after x and y).
    let ds = src[2u * P.channels * npix + q] * P.norm;
    let ds_dux = 2.0 * uy * a2 / (b1 * b2) - s * 2.0 * ux / b1;
    let ds_dsx = -s / b2;
    let ds_dsxy = 2.0 * a1 / (b1 * b2);
    let o = 3u * c * npix + q;
    adj[o] = ds * (ds_dux - 2.0 * ux * ds_dsx - uy * ds_dsxy);
    adj[o + npix] = ds * ds_dsx;
    adj[o + 2u * npix] = ds * ds_dsxy;
}
