// The photometric step's shared declarations (`photo_planes`, `photo_grad`;
// device.rs `photometric_step`, the CPU's `l1_dssim` + weighted `silhouette`).
// Planes as in ssim_common.wgsl: x (channels), y (channels), the SSIM
// weights (1), the silhouette mask (1), plane p at p * npix.

struct PhotoParams {
    width: u32,
    height: u32,
    channels: u32,
    pad0: u32,
    // 1 / (pixels x channels): the L1 and SSIM means' normaliser.
    norm: f32,
    // D-SSIM weight lambda of (1 - lambda) L1 + lambda (1 - SSIM).
    lambda: f32,
    // Weight of the silhouette term.
    sil_weight: f32,
    // 1 / pixels: the silhouette mean's normaliser.
    sil_norm: f32,
}

// Floats per pixel of the forward image and of the pixel gradients
// (r, g, b, alpha, depth, ox, oy, fur).
const PIX: u32 = 8u;
