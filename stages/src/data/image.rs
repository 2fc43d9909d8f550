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

    /// The image at continuous pixel coordinates `(u, v)` (pixel centres at half-integers),
    /// bilinear between centres and clamped to the edge pixels within half a pixel of the frame,
    /// into `out` (one value per channel); zero outside the frame.
    pub fn sample_bilinear(&self, u: f64, v: f64, out: &mut [f32]) {
        let (w, h) = (self.width as f64, self.height as f64);
        if !(u >= 0.0 && v >= 0.0 && u <= w && v <= h) {
            out.fill(0.0);
            return;
        }
        let (x, y) = ((u - 0.5).clamp(0.0, w - 1.0), (v - 0.5).clamp(0.0, h - 1.0));
        let (x0, y0) = (x.floor() as u32, y.floor() as u32);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (tx, ty) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let (a, b, c, d) = (
            self.pixel(x0, y0),
            self.pixel(x1, y0),
            self.pixel(x0, y1),
            self.pixel(x1, y1),
        );
        for (i, o) in out.iter_mut().enumerate() {
            let top = a[i] + (b[i] - a[i]) * tx;
            let bottom = c[i] + (d[i] - c[i]) * tx;
            *o = top + (bottom - top) * ty;
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
    fn bilinear_samples_hit_centres_and_blend_between_them() {
        let mut im = ImageF32::new(2, 2, 1);
        im.data = vec![0.0, 1.0, 2.0, 3.0];
        let at = |u, v| {
            let mut o = [f32::NAN];
            im.sample_bilinear(u, v, &mut o);
            o[0]
        };
        assert_eq!((at(0.5, 0.5), at(1.5, 1.5)), (0.0, 3.0));
        assert_eq!(at(1.0, 1.0), 1.5);
        // Clamped within the frame, empty beyond it.
        assert_eq!((at(0.1, 0.5), at(2.0, 0.5)), (0.0, 1.0));
        assert_eq!((at(-0.01, 1.0), at(1.0, 2.01)), (0.0, 0.0));
    }
}
