// SSIM kernels' shared declarations (losses.rs `ssim`, in f32). Planes are
// stored plane-major: plane p, pixel q at p * npix + q.

struct SsimParams {
    width: u32,
    height: u32,
    channels: u32,
    // Planes a `ssim_blur` dispatch filters.
    planes: u32,
    // `ssim_blur`: 0 = along rows (x), 1 = along columns (y).
    dir: u32,
    pad0: u32,
    pad1: u32,
    // 1 / (sum of the weights x channels).
    norm: f32,
    // The 11 window taps (x, y, z, w of k[0], k[1], k[2]).
    k: array<vec4<f32>, 3>,
}

const SSIM_R: i32 = 5;
const SSIM_C1: f32 = 0.0001;
const SSIM_C2: f32 = 0.0009;

fn tap(P: SsimParams, j: i32) -> f32 {
    return P.k[j / 4][j % 4];
}
