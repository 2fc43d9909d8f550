//! How far an image is smooth: the lag, in pixels, over which neighbouring values still vary
//! like a signal blurred beyond its pixel.
//!
//! Every rule that reads the views assumes their pixel is their resolution: the orientation
//! maps' Gabor filters have a fixed frequency per pixel, and the roots' density, the basis'
//! points per strand and the codec's component reach go by the pixel footprint. Photos softer
//! than their pixel (upscaled, out of focus, heavily compressed) break that. Inside the animal
//! (the mask eroded by [`SMOOTH_MARGIN`], so the silhouette's step does not count), `D(k)` is
//! the mean squared difference of luma between pixels `k` apart along rows and columns
//! ([`structure_function`]), and per lag the views' median of `D(2k) / D(k)`
//! ([`smoothness_ratios`]) says how the differences grow: independent pixels read 1, a
//! scale-free texture 2, a signal smooth over more than `2k` pixels 4. For white noise under a
//! Gaussian blur of `s` pixels the ratio falls through 2.86 at `k = s`, hence
//! [`SMOOTH_RATIO`]: the views are smooth over the first lag whose ratio is below it
//! ([`smooth_lag`]). Rendered and photographed captures at their native sharpness read 1.3-2.1
//! at lag 1 (the nine synthetic presets at 256 px, 1.25-1.89; the lynx and the fox at 512 px;
//! JPEG and lens-resampled copies; Blender's Cycles renders, 1.30), so their lag is 1; the
//! tiger's views upscaled 4x read 3.66, 3.14, 2.60 at lags 1-3, a lag of 3 (docs/history.md,
//! "Photos softer than their pixel").
//!
//! `working_views` box-averages soft photos by their lag.

use super::image::ImageF32;

/// The default of `working_views`' `smooth_ratio` (module doc).
pub const SMOOTH_RATIO: f64 = 2.86;

/// The largest lag, in pixels, at which the photos' smoothness is read (and so the largest
/// factor the reading can ask for).
pub const MAX_SMOOTH_LAG: usize = 8;

/// Margin, in pixels, by which the mask is eroded before a pair of pixels counts as inside the
/// animal: the silhouette's own step is not the coat's texture.
pub const SMOOTH_MARGIN: u32 = 3;

/// A view's structure function of luma inside the animal: `d[k - 1]` is the mean squared
/// difference between pixels `k` apart (along rows and columns, both pixels at least
/// [`SMOOTH_MARGIN`] inside the mask) for `k = 1..=2 MAX_SMOOTH_LAG`; `None` where a lag has
/// fewer than 256 such pairs or no difference at all (a flat or tiny animal says nothing).
pub fn structure_function(rgb: &ImageF32, mask: &ImageF32) -> Vec<Option<f64>> {
    let (w, h) = (rgb.width as usize, rgb.height as usize);
    let c = rgb.channels as usize;
    let luma: Vec<f32> = rgb
        .data
        .chunks_exact(c)
        .map(|p| {
            if c >= 3 {
                0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2]
            } else {
                p[0]
            }
        })
        .collect();
    // Inside: the mask above one half over a square of SMOOTH_MARGIN around the pixel (the
    // image's edge counts as outside), rows then columns.
    let fg: Vec<bool> = mask.data.iter().map(|v| *v > 0.5).collect();
    let r = SMOOTH_MARGIN as usize;
    let erode = |src: &[bool], step: usize, len: usize, count: usize| -> Vec<bool> {
        let mut out = vec![false; src.len()];
        for line in 0..count {
            let base = if step == 1 { line * len } else { line };
            let at = |i: usize| base + i * step;
            // Length of the run of foreground ending at each position, forward and backward.
            let mut fwd = vec![0usize; len];
            let mut run = 0;
            for i in 0..len {
                run = if src[at(i)] { run + 1 } else { 0 };
                fwd[i] = run;
            }
            let mut run = 0;
            for i in (0..len).rev() {
                run = if src[at(i)] { run + 1 } else { 0 };
                out[at(i)] = fwd[i] > r && run > r;
            }
        }
        out
    };
    let inside = erode(&erode(&fg, 1, w, h), w, h, w);
    (1..=2 * MAX_SMOOTH_LAG)
        .map(|k| {
            let (mut sum, mut n) = (0.0f64, 0usize);
            for y in 0..h {
                for x in 0..w {
                    let i = y * w + x;
                    if !inside[i] {
                        continue;
                    }
                    if x + k < w && inside[i + k] {
                        let d = (luma[i + k] - luma[i]) as f64;
                        sum += d * d;
                        n += 1;
                    }
                    if y + k < h && inside[i + k * w] {
                        let d = (luma[i + k * w] - luma[i]) as f64;
                        sum += d * d;
                        n += 1;
                    }
                }
            }
            (n >= 256 && sum > 0.0).then(|| sum / n as f64)
        })
        .collect()
}

/// The views' smoothness: for `k = 1..=MAX_SMOOTH_LAG`, the median over the views that carry
/// both lags (their [`structure_function`]s) of `D(2k) / D(k)`; `None` where no view does.
pub fn smoothness_ratios(structures: &[Vec<Option<f64>>]) -> Vec<Option<f64>> {
    (1..=MAX_SMOOTH_LAG)
        .map(|k| {
            let mut r: Vec<f64> = structures
                .iter()
                .filter_map(|d| Some(d[2 * k - 1]? / d[k - 1]?))
                .collect();
            r.sort_by(f64::total_cmp);
            (!r.is_empty()).then(|| r[r.len() / 2])
        })
        .collect()
}

/// The smallest lag at which the photos stop being smooth (`ratio < smooth_ratio`), capped at
/// [`MAX_SMOOTH_LAG`]; 1 where the reading is off or no lag could be read.
pub fn smooth_lag(ratios: &[Option<f64>], smooth_ratio: f64) -> u32 {
    if smooth_ratio <= 0.0 || ratios.iter().all(Option::is_none) {
        return 1;
    }
    ratios
        .iter()
        .position(|r| r.is_none_or(|r| r < smooth_ratio))
        .map_or(MAX_SMOOTH_LAG, |i| i + 1) as u32
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    #[test]
    fn the_lag_photos_are_smooth_over_is_the_first_where_they_stop_being_smooth() {
        let r = |v: &[f64]| v.iter().map(|x| Some(*x)).collect::<Vec<_>>();
        assert_eq!(smooth_lag(&r(&[1.9, 1.7, 1.4]), 2.86), 1);
        assert_eq!(smooth_lag(&r(&[3.7, 3.1, 2.6, 2.3]), 2.86), 3);
        assert_eq!(
            smooth_lag(&r(&[3.9; MAX_SMOOTH_LAG]), 2.86),
            MAX_SMOOTH_LAG as u32
        );
        // Off, or nothing read: the photos' own pixel.
        assert_eq!(smooth_lag(&r(&[3.7, 3.1, 2.6]), 0.0), 1);
        assert_eq!(smooth_lag(&[None, None], 2.86), 1);
        // A lag no view could read ends the smooth run.
        assert_eq!(smooth_lag(&[Some(3.5), None, Some(3.5)], 2.86), 2);
    }

    /// Grey fur-like texture at pixel `(x, y)`: independent values on a grid of `cell` px,
    /// bilinearly interpolated (`cell` 1: a value per pixel, the sharpest a photo gets).
    pub(crate) fn texture_at(x: u32, y: u32, cell: u32) -> f32 {
        let value = |i: u32, j: u32| {
            let h = (i.wrapping_mul(73_856_093) ^ j.wrapping_mul(19_349_663))
                .wrapping_mul(2_654_435_761);
            (h >> 8) as f32 / (1u32 << 24) as f32
        };
        let (u, v) = (x as f32 / cell as f32, y as f32 / cell as f32);
        let (i, j) = (u.floor() as u32, v.floor() as u32);
        let (a, b) = (u - i as f32, v - j as f32);
        let top = value(i, j) * (1.0 - a) + value(i + 1, j) * a;
        let bottom = value(i, j + 1) * (1.0 - a) + value(i + 1, j + 1) * a;
        top * (1.0 - b) + bottom * b
    }

    /// A `size` px square of [`texture_at`], and a mask over all of it.
    fn texture(size: u32, cell: u32) -> (ImageF32, ImageF32) {
        let mut rgb = ImageF32::new(size, size, 3);
        for y in 0..size {
            for x in 0..size {
                let l = texture_at(x, y, cell);
                rgb.pixel_mut(x, y).copy_from_slice(&[l, l, l]);
            }
        }
        let mut mask = ImageF32::new(size, size, 1);
        mask.data.iter_mut().for_each(|m| *m = 1.0);
        (rgb, mask)
    }

    #[test]
    fn independent_pixels_read_sharp_and_interpolated_ones_smooth() {
        let ratios = |cell: u32| {
            let (rgb, mask) = texture(96, cell);
            smoothness_ratios(&[structure_function(&rgb, &mask)])
        };
        let sharp = ratios(1);
        let r1 = sharp[0].unwrap();
        assert!(
            (r1 - 1.0).abs() < 0.15,
            "independent pixels: D(2) = D(1), read {r1}"
        );
        assert_eq!(smooth_lag(&sharp, SMOOTH_RATIO), 1);
        // Values 4 px apart, linear between: D(k) grows about as k^2 below the grid.
        let soft = ratios(4);
        let r1 = soft[0].unwrap();
        assert!(r1 > 3.0, "read {r1}");
        let lag = smooth_lag(&soft, SMOOTH_RATIO);
        assert!((2..=4).contains(&lag), "lag {lag}: {soft:?}");
        // A flat image, or a mask the margin leaves nothing of, says nothing.
        let flat = ImageF32::new(64, 64, 3);
        let (_, mask) = texture(64, 1);
        assert!(structure_function(&flat, &mask).iter().all(Option::is_none));
        let (rgb, _) = texture(64, 1);
        let mut thin = ImageF32::new(64, 64, 1);
        for y in 10..16 {
            for x in 0..64 {
                thin.pixel_mut(x, y)[0] = 1.0;
            }
        }
        assert!(structure_function(&rgb, &thin).iter().all(Option::is_none));
    }
}
