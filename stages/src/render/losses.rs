//! Image losses with their gradients w.r.t. the rendered image.
//!
//! Every function returns `(loss, dloss/dimage)` with the gradient laid out
//! like the rendered image, ready for [`super::OutputGrads`]. Optional masks
//! are 1-channel images in [0, 1] that weight pixels; every loss is a
//! *weighted mean* (sum of weight x term divided by the sum of weights, times
//! the channel count where channels are averaged), so its scale does not
//! depend on the image size. An all-zero mask gives loss 0 and zero gradient.
//!
//! Choices where the paper is vague:
//! - Photometric: 3DGS's `(1 - lambda) L1 + lambda (1 - SSIM)` (lambda = 0.2
//!   there). SSIM uses an 11x11 Gaussian window with sigma 1.5, C1 = 0.01^2,
//!   C2 = 0.03^2, per channel, zero padding at the borders (as the public
//!   PyTorch implementation used by 3DGS); the mask weights the per-pixel
//!   SSIM map and the per-pixel L1.
//! - Silhouette and fur mask: mean absolute difference (L1), as the other
//!   photometric term.
//! - Orientation: the predicted angle is `theta_p = atan2(oy, ox) / 2` from
//!   the rendered orientation feature (see [`super::orientation_from_feature`]);
//!   the per-pixel term is the pi-periodic absolute difference `d = min(|dt|,
//!   pi - |dt|)` with `dt = (theta_p - theta_gabor) mod pi`, weighted by
//!   `confidence x mask` and divided by the sum of the mask (so confidence
//!   scales the loss; normalise it beforehand if needed). Where `|o|^2` is
//!   below [`ORIENTATION_EPS`] the orientation is undefined and the
//!   gradient is zero.

#![allow(clippy::needless_range_loop)]

use rayon::prelude::*;

use super::raster::check_image;
use super::RenderError;
use crate::data::image::ImageF32;

/// Below this squared feature magnitude the rendered orientation carries no
/// gradient.
pub const ORIENTATION_EPS: f32 = 1e-8;

pub(crate) const SSIM_C1: f64 = 0.01 * 0.01;
pub(crate) const SSIM_C2: f64 = 0.03 * 0.03;
pub(crate) const SSIM_RADIUS: usize = 5;
const SSIM_SIGMA: f64 = 1.5;

/// The renderer's shape check, plus finiteness: loss inputs come from files.
pub(crate) fn check(
    what: &'static str,
    img: &ImageF32,
    width: u32,
    height: u32,
    channels: u32,
) -> Result<(), RenderError> {
    check_image(what, img, width, height, channels)?;
    if let Some(i) = img.data.iter().position(|v| !v.is_finite()) {
        return Err(RenderError::NonFinite { what, index: i });
    }
    Ok(())
}

fn mask_weights(mask: Option<&ImageF32>, w: u32, h: u32) -> Result<Vec<f64>, RenderError> {
    match mask {
        Some(m) => {
            check("mask", m, w, h, 1)?;
            Ok(m.data.iter().map(|&v| v as f64).collect())
        }
        None => Ok(vec![1.0; (w * h) as usize]),
    }
}

/// SSIM's normalised 11-tap Gaussian window.
pub(crate) fn gauss_kernel() -> [f64; 2 * SSIM_RADIUS + 1] {
    let mut k = [0.0; 2 * SSIM_RADIUS + 1];
    for (i, v) in k.iter_mut().enumerate() {
        let x = i as f64 - SSIM_RADIUS as f64;
        *v = (-x * x / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let s: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    k
}

/// Separable Gaussian blur with zero padding (self-adjoint). Rows in
/// parallel, and within a row the taps outermost so the pixels vectorise;
/// every output value is still the sum over taps in tap order (out-of-image
/// taps skipped), whatever the threads.
fn blur(src: &[f64], w: usize, h: usize, k: &[f64]) -> Vec<f64> {
    let r = SSIM_RADIUS;
    let mut tmp = vec![0.0; w * h];
    tmp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let line = &src[y * w..(y + 1) * w];
        for (j, &kv) in k.iter().enumerate() {
            // Output x reads input x + j - r, inside [0, w).
            let lo = r.saturating_sub(j);
            let hi = (w + r).saturating_sub(j).min(w);
            if lo >= hi {
                continue;
            }
            let off = lo + j - r;
            for (t, v) in row[lo..hi].iter_mut().zip(&line[off..off + (hi - lo)]) {
                *t += kv * v;
            }
        }
    });
    let mut out = vec![0.0; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (j, &kv) in k.iter().enumerate() {
            let yy = y as isize + j as isize - r as isize;
            if yy < 0 || yy as usize >= h {
                continue;
            }
            let line = &tmp[yy as usize * w..(yy as usize + 1) * w];
            for (o, v) in row.iter_mut().zip(line) {
                *o += kv * v;
            }
        }
    });
    out
}

/// One channel of [`ssim`]: the per-pixel SSIM (unweighted) and the
/// gradient of `norm * sum_p m_p SSIM_p` w.r.t. the channel's pixels.
fn ssim_channel(
    x: &[f64],
    y: &[f64],
    m: &[f64],
    norm: f64,
    w: usize,
    h: usize,
) -> (Vec<f64>, Vec<f64>) {
    let k = gauss_kernel();
    let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
    let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
    let xy: Vec<f64> = x.iter().zip(y).map(|(a, b)| a * b).collect();
    let (mx, my) = (blur(x, w, h, &k), blur(y, w, h, &k));
    let (bxx, byy, bxy) = (
        blur(&xx, w, h, &k),
        blur(&yy, w, h, &k),
        blur(&xy, w, h, &k),
    );
    let n = w * h;
    let mut ssim_p = vec![0.0; n];
    let mut d_mu = vec![0.0; n];
    let mut d_xx = vec![0.0; n];
    let mut d_xy = vec![0.0; n];
    (&mut ssim_p, &mut d_mu, &mut d_xx, &mut d_xy)
        .into_par_iter()
        .enumerate()
        .for_each(|(p, (sp, dmu, dxx, dxy))| {
            let (ux, uy) = (mx[p], my[p]);
            let sx = bxx[p] - ux * ux;
            let sy = byy[p] - uy * uy;
            let sxy = bxy[p] - ux * uy;
            let a1 = 2.0 * ux * uy + SSIM_C1;
            let a2 = 2.0 * sxy + SSIM_C2;
            let b1 = ux * ux + uy * uy + SSIM_C1;
            let b2 = sx + sy + SSIM_C2;
            let s = a1 * a2 / (b1 * b2);
            *sp = s;
            let ds = m[p] * norm;
            let ds_dux = 2.0 * uy * a2 / (b1 * b2) - s * 2.0 * ux / b1;
            let ds_dsx = -s / b2;
            let ds_dsxy = 2.0 * a1 / (b1 * b2);
            *dmu = ds * (ds_dux - 2.0 * ux * ds_dsx - uy * ds_dsxy);
            *dxx = ds * ds_dsx;
            *dxy = ds * ds_dsxy;
        });
    let (g_mu, g_xx, g_xy) = (
        blur(&d_mu, w, h, &k),
        blur(&d_xx, w, h, &k),
        blur(&d_xy, w, h, &k),
    );
    let grad = (0..n)
        .into_par_iter()
        .map(|p| g_mu[p] + 2.0 * x[p] * g_xx[p] + y[p] * g_xy[p])
        .collect();
    (ssim_p, grad)
}

/// Weighted mean SSIM of `img` vs `target` (same size, any channel count)
/// and its gradient w.r.t. `img`. Channels and pixels run in parallel; the
/// mean is summed channel by channel, pixel by pixel, so its bits do not
/// depend on the threads.
pub fn ssim(
    img: &ImageF32,
    target: &ImageF32,
    mask: Option<&ImageF32>,
) -> Result<(f32, ImageF32), RenderError> {
    let (w, h, ch) = (img.width, img.height, img.channels);
    let m = ssim_weights(img, target, mask)?;
    let msum: f64 = m.iter().sum();
    let mut grad = ImageF32::new(w, h, ch);
    if msum <= 0.0 {
        return Ok((0.0, grad));
    }
    let (wu, hu, c) = (w as usize, h as usize, ch as usize);
    let norm = 1.0 / (msum * c as f64);
    let channels: Vec<(Vec<f64>, Vec<f64>)> = (0..c)
        .into_par_iter()
        .map(|cc| {
            let x: Vec<f64> = (0..wu * hu).map(|p| img.data[p * c + cc] as f64).collect();
            let y: Vec<f64> = (0..wu * hu)
                .map(|p| target.data[p * c + cc] as f64)
                .collect();
            ssim_channel(&x, &y, &m, norm, wu, hu)
        })
        .collect();
    let mut total = 0.0f64;
    for (cc, (ssim_p, g)) in channels.iter().enumerate() {
        for p in 0..wu * hu {
            total += m[p] * ssim_p[p];
            grad.data[p * c + cc] = g[p] as f32;
        }
    }
    Ok(((total * norm) as f32, grad))
}

/// [`ssim`]'s input checks (sizes, finite values, the mask) and its pixel
/// weights; shared with the GPU's SSIM so both refuse the same inputs.
pub(crate) fn ssim_weights(
    img: &ImageF32,
    target: &ImageF32,
    mask: Option<&ImageF32>,
) -> Result<Vec<f64>, RenderError> {
    let (w, h, ch) = (img.width, img.height, img.channels);
    check("image", img, w, h, ch)?;
    check("target", target, w, h, ch)?;
    mask_weights(mask, w, h)
}

/// Weighted mean absolute difference over pixels and channels.
pub fn l1(
    img: &ImageF32,
    target: &ImageF32,
    mask: Option<&ImageF32>,
) -> Result<(f32, ImageF32), RenderError> {
    let (w, h, ch) = (img.width, img.height, img.channels);
    check("image", img, w, h, ch)?;
    check("target", target, w, h, ch)?;
    let m = mask_weights(mask, w, h)?;
    let msum: f64 = m.iter().sum();
    let mut grad = ImageF32::new(w, h, ch);
    if msum <= 0.0 {
        return Ok((0.0, grad));
    }
    let c = ch as usize;
    let norm = 1.0 / (msum * c as f64);
    let mut total = 0.0f64;
    for p in 0..(w * h) as usize {
        for k in 0..c {
            let d = img.data[p * c + k] as f64 - target.data[p * c + k] as f64;
            total += m[p] * d.abs();
            grad.data[p * c + k] = if d > 0.0 {
                (m[p] * norm) as f32
            } else if d < 0.0 {
                -(m[p] * norm) as f32
            } else {
                0.0
            };
        }
    }
    Ok(((total * norm) as f32, grad))
}

/// Photometric loss `(1 - lambda) L1 + lambda (1 - SSIM)`.
pub fn l1_dssim(
    img: &ImageF32,
    target: &ImageF32,
    mask: Option<&ImageF32>,
    lambda: f32,
) -> Result<(f32, ImageF32), RenderError> {
    l1_dssim_with(img, target, mask, lambda, ssim)
}

/// [`l1_dssim`] with the SSIM term computed by `ssim_fn` (the CPU's
/// [`ssim`] or the GPU's, which must return what [`ssim`] does).
pub fn l1_dssim_with(
    img: &ImageF32,
    target: &ImageF32,
    mask: Option<&ImageF32>,
    lambda: f32,
    ssim_fn: impl FnOnce(
        &ImageF32,
        &ImageF32,
        Option<&ImageF32>,
    ) -> Result<(f32, ImageF32), RenderError>,
) -> Result<(f32, ImageF32), RenderError> {
    if !(0.0..=1.0).contains(&lambda) {
        return Err(RenderError::Settings(format!(
            "D-SSIM weight lambda = {lambda}, expected a value in [0, 1]"
        )));
    }
    let (l, mut g) = l1(img, target, mask)?;
    let (s, gs) = ssim_fn(img, target, mask)?;
    let any = mask.is_none_or(|m| m.data.iter().any(|&v| v > 0.0));
    for (a, b) in g.data.iter_mut().zip(&gs.data) {
        *a = (1.0 - lambda) * *a - lambda * b;
    }
    let dssim = if any { 1.0 - s } else { 0.0 };
    Ok(((1.0 - lambda) * l + lambda * dssim, g))
}

/// Silhouette loss: weighted mean |alpha - mask| (both 1 channel).
pub fn silhouette(
    alpha: &ImageF32,
    mask: &ImageF32,
    valid: Option<&ImageF32>,
) -> Result<(f32, ImageF32), RenderError> {
    check("alpha", alpha, alpha.width, alpha.height, 1)?;
    l1(alpha, mask, valid)
}

/// Fur-mask loss: weighted mean |fur - fur_mask| (both 1 channel).
pub fn fur_mask(
    fur: &ImageF32,
    fur_mask: &ImageF32,
    valid: Option<&ImageF32>,
) -> Result<(f32, ImageF32), RenderError> {
    check("fur", fur, fur.width, fur.height, 1)?;
    l1(fur, fur_mask, valid)
}

/// pi-periodic absolute angle difference in [0, pi/2] and its sign
/// (derivative w.r.t. the first angle).
pub fn angle_diff(a: f32, b: f32) -> (f32, f32) {
    use std::f32::consts::PI;
    let mut d = (a - b).rem_euclid(PI);
    if d >= PI {
        d = 0.0;
    }
    if d > 0.5 * PI {
        (PI - d, -1.0)
    } else if d > 0.0 {
        (d, 1.0)
    } else {
        (0.0, 0.0)
    }
}

/// Orientation loss of the rendered orientation feature `pred` (2 channels)
/// against a Gabor angle map (1 channel, radians, [`super::orientation_angle`]
/// convention), weighted by `confidence` (1 channel) and an optional mask.
pub fn orientation(
    pred: &ImageF32,
    gabor_angle: &ImageF32,
    confidence: &ImageF32,
    mask: Option<&ImageF32>,
) -> Result<(f32, ImageF32), RenderError> {
    let (w, h) = (pred.width, pred.height);
    check("orientation", pred, w, h, 2)?;
    check("gabor angle", gabor_angle, w, h, 1)?;
    check("confidence", confidence, w, h, 1)?;
    let m = mask_weights(mask, w, h)?;
    let msum: f64 = m.iter().sum();
    let mut grad = ImageF32::new(w, h, 2);
    if msum <= 0.0 {
        return Ok((0.0, grad));
    }
    let mut total = 0.0f64;
    for p in 0..(w * h) as usize {
        let wgt = m[p] * confidence.data[p] as f64;
        if wgt == 0.0 {
            continue;
        }
        let (ox, oy) = (pred.data[2 * p], pred.data[2 * p + 1]);
        let theta = super::orientation_from_feature(ox, oy);
        let (d, sign) = angle_diff(theta, gabor_angle.data[p]);
        total += wgt * d as f64;
        let r2 = ox * ox + oy * oy;
        if r2 > ORIENTATION_EPS {
            let s = (wgt / msum) as f32 * sign * 0.5 / r2;
            grad.data[2 * p] = -oy * s;
            grad.data[2 * p + 1] = ox * s;
        }
    }
    Ok(((total / msum) as f32, grad))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn rand_img(rng: &mut ChaCha8Rng, w: u32, h: u32, c: u32) -> ImageF32 {
        let mut im = ImageF32::new(w, h, c);
        im.data
            .iter_mut()
            .for_each(|v| *v = rng.gen_range(0.0..1.0));
        im
    }

    type LossFn<'a> = &'a dyn Fn(&ImageF32) -> (f32, ImageF32);

    fn fd_check(name: &str, img: &ImageF32, f: LossFn<'_>) {
        let (_, g) = f(img);
        let h = 1e-3f32;
        let gmax = g.data.iter().fold(0.0f32, |a, v| a.max(v.abs()));
        assert!(gmax > 0.0, "{name}: zero gradient");
        for i in (0..img.data.len()).step_by(7) {
            let mut a = img.clone();
            let mut b = img.clone();
            a.data[i] += h;
            b.data[i] -= h;
            let fd = (f(&a).0 as f64 - f(&b).0 as f64) / (2.0 * h as f64);
            let an = g.data[i] as f64;
            let tol = 0.02 * an.abs().max(fd.abs()) + 2e-3 * gmax as f64;
            assert!((an - fd).abs() <= tol, "{name}[{i}]: {an:e} vs fd {fd:e}");
        }
    }

    #[test]
    fn ssim_and_photometric_gradients_match_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let img = rand_img(&mut rng, 13, 9, 3);
        let tgt = rand_img(&mut rng, 13, 9, 3);
        let mask = rand_img(&mut rng, 13, 9, 1);
        fd_check("ssim", &img, &|x| ssim(x, &tgt, Some(&mask)).unwrap());
        fd_check("l1_dssim", &img, &|x| l1_dssim(x, &tgt, None, 0.2).unwrap());
        // SSIM of an image with itself is 1 and the loss is 0; different images score lower.
        let (s, _) = ssim(&img, &img, None).unwrap();
        assert!((s - 1.0).abs() < 1e-5, "{s}");
        let (s2, _) = ssim(&img, &tgt, None).unwrap();
        assert!(s2 < 0.5, "{s2}");
        let (l, _) = l1_dssim(&img, &img, None, 0.2).unwrap();
        assert!(l.abs() < 1e-5);
        assert!(l1_dssim(&img, &tgt, Some(&img), 0.2).is_err());
    }

    #[test]
    fn orientation_loss_is_pi_periodic_and_its_gradient_matches() {
        use std::f32::consts::PI;
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (w, h) = (6u32, 5u32);
        let mut pred = ImageF32::new(w, h, 2);
        pred.data
            .iter_mut()
            .for_each(|v| *v = rng.gen_range(-1.0..1.0));
        let mut ang = ImageF32::new(w, h, 1);
        ang.data
            .iter_mut()
            .for_each(|v| *v = rng.gen_range(0.0..PI));
        let conf = rand_img(&mut rng, w, h, 1);
        fd_check("orientation", &pred, &|x| {
            orientation(x, &ang, &conf, None).unwrap()
        });
        // A feature encoding exactly the Gabor angle (or that angle + pi) costs nothing.
        let mut exact = ImageF32::new(w, h, 2);
        for p in 0..(w * h) as usize {
            let t = ang.data[p] + if p % 2 == 0 { PI } else { 0.0 };
            exact.data[2 * p] = 0.7 * (2.0 * t).cos();
            exact.data[2 * p + 1] = 0.7 * (2.0 * t).sin();
        }
        let (l, _) = orientation(&exact, &ang, &conf, None).unwrap();
        assert!(l < 1e-5, "{l}");
        // A perpendicular one costs pi/2 times the mean confidence.
        let mut perp = exact.clone();
        perp.data.iter_mut().for_each(|v| *v = -*v);
        let (l, _) = orientation(&perp, &ang, &conf, None).unwrap();
        let mean_conf = conf.data.iter().sum::<f32>() / conf.data.len() as f32;
        assert!((l - 0.5 * PI * mean_conf).abs() < 1e-4, "{l}");
    }

    #[test]
    fn masks_and_l1_losses() {
        let mut a = ImageF32::new(4, 1, 1);
        a.data = vec![0.0, 1.0, 0.5, 0.2];
        let mut m = ImageF32::new(4, 1, 1);
        m.data = vec![0.0, 1.0, 1.0, 0.0];
        let mut valid = ImageF32::new(4, 1, 1);
        valid.data = vec![1.0, 1.0, 0.0, 1.0];
        let (l, g) = silhouette(&a, &m, Some(&valid)).unwrap();
        assert!((l - 0.2 / 3.0).abs() < 1e-6, "{l}");
        assert_eq!(g.data[2], 0.0);
        assert!(g.data[3] > 0.0);
        let (l, g) = fur_mask(&a, &m, Some(&ImageF32::new(4, 1, 1))).unwrap();
        assert_eq!(l, 0.0);
        assert!(g.data.iter().all(|v| *v == 0.0));
        assert!(silhouette(&a, &ImageF32::new(3, 1, 1), None).is_err());
    }
}
