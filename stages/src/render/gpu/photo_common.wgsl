// The image-loss step's shared declarations (`photo_planes`, `photo_grad`;
// device.rs `image_step`, the CPU's `l1_dssim`, `silhouette`, `fur_mask`
// and `orientation`). Planes as in ssim_common.wgsl, plane p at p * npix:
// x (3, the rendered colour), y (3), the SSIM weights (1), then the
// silhouette mask, the fur mask, the Gabor angle, its confidence and the
// orientation region (1 each; zero where the view has none).

struct PhotoParams {
    width: u32,
    height: u32,
    // Which terms run: 1 colour, 2 silhouette, 4 fur mask, 8 orientation.
    terms: u32,
    pad0: u32,
    // 1 / (pixels x 3): the L1 and SSIM means' normaliser.
    norm: f32,
    // D-SSIM weight lambda of (1 - lambda) L1 + lambda (1 - SSIM).
    lambda: f32,
    // 1 / pixels: the silhouette and fur-mask means' normaliser.
    pix_norm: f32,
    // 1 / (sum of the orientation region), 0 when it is empty.
    ori_norm: f32,
    // The terms' weights.
    w_rgb: f32,
    w_sil: f32,
    w_fur: f32,
    w_ori: f32,
}

// Floats per pixel of the forward image and of the pixel gradients
// (r, g, b, alpha, depth, ox, oy, fur).
const PIX: u32 = 8u;
// The plane of each input (see above).
const P_MASK: u32 = 7u;
const P_FUR: u32 = 8u;
const P_ANGLE: u32 = 9u;
const P_CONF: u32 = 10u;
const P_REGION: u32 = 11u;
