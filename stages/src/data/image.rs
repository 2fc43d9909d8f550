//! Float images in memory (row-major, interleaved channels, top row first).

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImageF32 {
    pub width: u32,
    pub height: u32,
    pub channels: u32,
    pub data: Vec<f32>,
}

impl ImageF32 {
    pub fn new(width: u32, height: u32, channels: u32) -> Self {
        ImageF32 {
            width,
            height,
            channels,
            data: vec![0.0; (width * height * channels) as usize],
        }
    }
    #[inline]
    pub fn index(&self, x: u32, y: u32) -> usize {
        ((y * self.width + x) * self.channels) as usize
    }
    #[inline]
    pub fn pixel(&self, x: u32, y: u32) -> &[f32] {
        let i = self.index(x, y);
        &self.data[i..i + self.channels as usize]
    }
    #[inline]
    pub fn pixel_mut(&mut self, x: u32, y: u32) -> &mut [f32] {
        let i = self.index(x, y);
        let c = self.channels as usize;
        &mut self.data[i..i + c]
    }

    /// Channel `ch` alone, as a one-channel image.
    pub fn channel(&self, ch: usize) -> ImageF32 {
        let c = self.channels as usize;
        ImageF32 {
            width: self.width,
            height: self.height,
            channels: 1,
            data: self.data.chunks_exact(c).map(|p| p[ch]).collect(),
        }
    }

    /// The first channel alone (a mask or a scalar map stored with more channels).
    pub fn first_channel(self) -> ImageF32 {
        if self.channels == 1 {
            self
        } else {
            self.channel(0)
        }
    }

    /// The image at continuous pixel coordinates `(u, v)` (pixel centres at half-integers),
    /// interpolated with the Lanczos-3 kernel (6 x 6 taps, weights normalised, taps beyond the
    /// frame clamped to the edge pixels), into `out` (one value per channel); zero outside the
    /// frame. Values may overshoot a step by a few percent, as every sharp kernel does.
    ///
    /// Lanczos-3 and not bilinear: a resampled photo feeds the orientation maps, which read
    /// strands a pixel wide, and bilinear weights at half-pixel offsets average neighbours as a
    /// box filter would (docs/history.md, "Photos through a lens").
    pub fn sample_lanczos3(&self, u: f64, v: f64, out: &mut [f32]) {
        let (w, h) = (self.width as f64, self.height as f64);
        if !(u >= 0.0 && v >= 0.0 && u <= w && v <= h) {
            out.fill(0.0);
            return;
        }
        let (x, y) = (u - 0.5, v - 0.5);
        let (x0, y0) = (x.floor() as i64, y.floor() as i64);
        let taps = |origin: i64, at: f64, size: u32| {
            let mut idx = [0u32; 6];
            let mut wgt = [0f64; 6];
            for (i, d) in (-2i64..=3).enumerate() {
                let p = origin + d;
                wgt[i] = lanczos3(at - p as f64);
                idx[i] = p.clamp(0, size as i64 - 1) as u32;
            }
            (idx, wgt)
        };
        let (xi, xw) = taps(x0, x, self.width);
        let (yi, yw) = taps(y0, y, self.height);
        let mut acc = [0f64; 4];
        let c = out.len().min(4);
        let mut total = 0.0;
        for (yy, wy) in yi.iter().zip(&yw) {
            for (xx, wx) in xi.iter().zip(&xw) {
                let wgt = wy * wx;
                total += wgt;
                for (a, p) in acc.iter_mut().zip(&self.pixel(*xx, *yy)[..c]) {
                    *a += wgt * *p as f64;
                }
            }
        }
        for (o, a) in out.iter_mut().zip(acc) {
            *o = (a / total) as f32;
        }
    }

    /// Box-averages the image by an integer factor (the last partial rows and columns are
    /// dropped): output pixel `(x, y)` covers input pixels `[x f, (x + 1) f)`, so a camera's
    /// intrinsics scale by `1 / f` exactly (pixel centres at half-integers).
    pub fn box_downscaled(&self, factor: u32) -> ImageF32 {
        if factor <= 1 {
            return self.clone();
        }
        let (w, h) = ((self.width / factor).max(1), (self.height / factor).max(1));
        let c = self.channels as usize;
        let mut out = ImageF32::new(w, h, self.channels);
        for y in 0..h {
            for x in 0..w {
                let mut acc = vec![0.0f32; c];
                let mut cnt = 0.0;
                for yy in y * factor..((y + 1) * factor).min(self.height) {
                    for xx in x * factor..((x + 1) * factor).min(self.width) {
                        for (a, v) in acc.iter_mut().zip(self.pixel(xx, yy)) {
                            *a += v;
                        }
                        cnt += 1.0;
                    }
                }
                for (o, a) in out.pixel_mut(x, y).iter_mut().zip(acc) {
                    *o = a / cnt;
                }
            }
        }
        out
    }
}

/// The Lanczos-3 kernel: `sinc(t) sinc(t / 3)` within 3 pixels.
fn lanczos3(t: f64) -> f64 {
    let t = t.abs();
    if t < 1e-9 {
        1.0
    } else if t >= 3.0 {
        0.0
    } else {
        let pt = std::f64::consts::PI * t;
        3.0 * pt.sin() * (pt / 3.0).sin() / (pt * pt)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_downscaled_averages_blocks() {
        let mut im = ImageF32::new(4, 2, 1);
        im.data = vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0];
        let d = im.box_downscaled(2);
        assert_eq!((d.width, d.height), (2, 1));
        assert_eq!(d.data, vec![2.5, 4.5]);
        // An odd size drops the last column; factor 1 is the identity.
        let mut odd = ImageF32::new(5, 2, 1);
        odd.data = (0..10).map(|v| v as f32).collect();
        assert_eq!(odd.box_downscaled(2).data, vec![3.0, 5.0]);
        assert_eq!(odd.box_downscaled(1), odd);
    }

    #[test]
    fn lanczos_samples_hit_centres_and_keep_a_ramp() {
        let mut im = ImageF32::new(8, 8, 1);
        im.data = (0..64).map(|i| (i % 8) as f32).collect();
        let at = |u, v| {
            let mut o = [f32::NAN];
            im.sample_lanczos3(u, v, &mut o);
            o[0]
        };
        // At a pixel centre, the pixel.
        assert!((at(3.5, 2.5) - 3.0).abs() < 1e-6);
        // Between centres on a ramp, the ramp (the weights sum to one and are symmetric).
        assert!((at(3.75, 4.0) - 3.25).abs() < 0.02, "{}", at(3.75, 4.0));
        // Empty beyond the frame.
        assert_eq!((at(-0.01, 1.0), at(1.0, 8.01)), (0.0, 0.0));
    }
}
