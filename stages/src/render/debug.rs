//! Writing renders to disk for inspection (the only file I/O of the renderer).
//!
//! [`write_render`] writes, for a file stem `S` in a directory:
//! - `S_rgb.png` (sRGB-unaware 8-bit copy of the linear RGB, clamped),
//!   `S_alpha.png`, `S_fur.png`;
//! - `S_orientation.png`: the orientation as a hue (angle `theta` in [0, pi)
//!   -> hue `theta / pi`), saturation 1, value = feature magnitude (so
//!   uncovered and isotropic regions are black);
//! - `S_depth.png`: depth divided by alpha, mapped linearly from the nearest
//!   to the farthest covered depth onto 1 -> 0.2 (near is bright), 0 where
//!   alpha < 0.01;
//! - `S_rgba.exr` (RGB + alpha, f32), `S_depth.exr` (raw blended depth, f32),
//!   `S_orientation.exr` (the two raw feature channels, f32).

use std::path::{Path, PathBuf};

use super::{orientation_from_feature, RenderOutput};
use crate::data::image::ImageF32;
use crate::formats::images::{write_exr, write_png};
use crate::formats::FormatError;

/// HSV (all in [0, 1]) to RGB.
fn hsv(h: f32, s: f32, v: f32) -> [f32; 3] {
    let h6 = (h.rem_euclid(1.0)) * 6.0;
    let i = h6.floor() as i32 % 6;
    let f = h6 - h6.floor();
    let (p, q, t) = (v * (1.0 - s), v * (1.0 - s * f), v * (1.0 - s * (1.0 - f)));
    match i {
        0 => [v, t, p],
        1 => [q, v, p],
        2 => [p, v, t],
        3 => [p, q, v],
        4 => [t, p, v],
        _ => [v, p, q],
    }
}

/// The orientation channel as a colour image (see the module doc).
pub fn orientation_image(out: &RenderOutput) -> ImageF32 {
    let o = &out.orientation;
    let mut img = ImageF32::new(o.width, o.height, 3);
    for p in 0..(o.width * o.height) as usize {
        let (ox, oy) = (o.data[2 * p], o.data[2 * p + 1]);
        let mag = (ox * ox + oy * oy).sqrt().min(1.0);
        let theta = orientation_from_feature(ox, oy);
        let c = hsv(theta / std::f32::consts::PI, 1.0, mag);
        img.data[3 * p..3 * p + 3].copy_from_slice(&c);
    }
    img
}

/// Depth / alpha mapped for display (see the module doc).
pub fn depth_image(out: &RenderOutput) -> ImageF32 {
    let (d, a) = (&out.depth, &out.alpha);
    let vals: Vec<Option<f32>> = d
        .data
        .iter()
        .zip(&a.data)
        .map(|(&d, &a)| (a >= 0.01 && d.is_finite()).then(|| d / a))
        .collect();
    let lo = vals.iter().flatten().fold(f32::INFINITY, |m, &v| m.min(v));
    let hi = vals
        .iter()
        .flatten()
        .fold(f32::NEG_INFINITY, |m, &v| m.max(v));
    let mut img = ImageF32::new(d.width, d.height, 1);
    for (o, v) in img.data.iter_mut().zip(&vals) {
        if let Some(v) = v {
            let t = if hi > lo { (v - lo) / (hi - lo) } else { 0.0 };
            *o = 1.0 - 0.8 * t;
        }
    }
    img
}

/// Writes the render as PNGs and EXRs (see the module doc); returns the paths written.
pub fn write_render(
    dir: &Path,
    stem: &str,
    out: &RenderOutput,
) -> Result<Vec<PathBuf>, FormatError> {
    std::fs::create_dir_all(dir).map_err(|e| FormatError::io(dir, e))?;
    let mut written = Vec::new();
    let mut put = |name: String, img: &ImageF32, exr: bool| -> Result<(), FormatError> {
        let path = dir.join(name);
        if exr {
            write_exr(&path, img)?;
        } else {
            write_png(&path, img)?;
        }
        written.push(path);
        Ok(())
    };
    put(format!("{stem}_rgb.png"), &out.rgb, false)?;
    put(format!("{stem}_alpha.png"), &out.alpha, false)?;
    put(format!("{stem}_fur.png"), &out.fur, false)?;
    put(
        format!("{stem}_orientation.png"),
        &orientation_image(out),
        false,
    )?;
    put(format!("{stem}_depth.png"), &depth_image(out), false)?;
    let (w, h) = (out.rgb.width, out.rgb.height);
    let mut rgba = ImageF32::new(w, h, 4);
    for p in 0..(w * h) as usize {
        rgba.data[4 * p..4 * p + 3].copy_from_slice(&out.rgb.data[3 * p..3 * p + 3]);
        rgba.data[4 * p + 3] = out.alpha.data[p];
    }
    put(format!("{stem}_rgba.exr"), &rgba, true)?;
    put(format!("{stem}_depth.exr"), &out.depth, true)?;
    put(format!("{stem}_orientation.exr"), &out.orientation, true)?;
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::images::{read_exr, read_png};
    use crate::render::{render, tests::test_camera, Gaussians, RenderSettings};
    use glam::{Quat, Vec3};

    #[test]
    fn writes_pngs_and_exrs_that_read_back() {
        let mut g = Gaussians::default();
        g.push(
            Vec3::ZERO,
            Vec3::new(0.4, 0.05, 0.05),
            Quat::IDENTITY,
            0.9,
            Vec3::new(0.8, 0.3, 0.1),
            true,
        );
        let cam = test_camera(24, Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO);
        let (out, _) = render(&g, &cam, &RenderSettings::default()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let paths = write_render(dir.path(), "v0", &out).unwrap();
        assert_eq!(paths.len(), 8);
        let rgba = read_exr(dir.path().join("v0_rgba.exr")).unwrap();
        assert_eq!(rgba.channels, 4);
        let c = out.rgb.index(12, 12);
        assert!((rgba.data[(12 * 24 + 12) * 4] - out.rgb.data[c]).abs() < 1e-6);
        let o = read_png(dir.path().join("v0_orientation.png")).unwrap();
        // A horizontal strand: hue 0 (red) at the centre.
        let px = o.pixel(12, 12);
        assert!(px[0] > 0.5 && px[1] < 0.2 && px[2] < 0.2, "{px:?}");
    }
}
