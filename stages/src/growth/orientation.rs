//! Gabor orientation and confidence maps (stage `orientation_maps`), the image-space direction cue of
//! the orientation loss.
//!
//! # The maths (the public recipe shared by Neural Haircut, Gaussian Haircut and NeuralFur)
//! 1. Gray = 0.2989 R + 0.5870 G + 0.1140 B (the values as stored in the PNG, no linearisation).
//! 2. Difference of Gaussians: `G(sigma 0.4) * gray - G(sigma 10) * gray` (separable, each Gaussian
//!    truncated at 3 sigma and normalised; borders mirrored).
//! 3. `orientations` (default 180) filters, theta_k = k pi / orientations. Filter k is the real part of a
//!    Gabor kernel whose stripes run along theta_k: with `a` the pixel offset along direction
//!    `(cos theta_k, sin theta_k)` and `b` the offset across it,
//!    `exp(-(b^2 / (2 sigma_x^2) + a^2 / (2 sigma_y^2))) cos(2 pi f b)`, sigma_x = 1.8 across the
//!    strand, sigma_y = 2.4 along it; f = 0.4 here (wavelength 2.5 px), where the public code uses
//!    0.23 (~4.35 px): see "The wavelength" below. Kernel support: a square of half-size
//!    `ceil(3 max(sigma_x, sigma_y))` (the public code sizes it per angle; a fixed square is a superset)
//!    with taps below 1e-4 of the peak dropped (they change no response by more than ~1e-4 relative).
//! 4. Per pixel, `F_k = |response_k|`; orientation = theta of argmax F_k (first maximum on ties);
//!    variance = `sum_k (F_k / sum F) d(theta*, theta_k)^2` with the circular distance modulo pi;
//!    confidence = `1 / ((variance / pi^2)^2 + 1e-7)` (raw, up to 1e7, as in the public code; the loss
//!    decides how to normalise it).
//!
//! # The wavelength
//! The filter must respond to the strands, not to the coat's colour pattern. In our views (256 px
//! of a whole animal, about a centimetre per pixel) a strand is thinner than a pixel: what the
//! image keeps of the fur is a streaky texture at the finest scale the sampling carries. Stripes
//! and patches are coarser, and on a tiger they run *across* the fur. A filter tuned to ~4.35 px
//! (the public value, meant for hair photographed with strands several pixels apart) sits between
//! the two and follows the stripes; one tuned to 2.5 px (0.4 cycles/px, just under Nyquist's 0.5)
//! follows the fur. Measured against the GT strands projected into the training views
//! (`examples/orientation_diagnostics.rs`; figures in docs/history.md), confidence-weighted mean
//! angle, dev split: tiger 52 deg -> 28 deg (random is 45), fox 35 -> 25. The rule for other
//! captures: the wavelength is the finest the views resolve, unless the strands are themselves
//! several pixels wide, where the public 0.23 applies (`frequency`).
//!
//! # Views coarser than the rest
//! The same reasoning across the views of one capture: where a camera sees the animal with a pixel
//! much wider than the others' (a second camera at half the resolution, photographs from twice
//! the distance), its filters find the coat's pattern where the sharper views find the fur, and a
//! learner that averages both is pulled onto the pattern. Views whose pixel footprint at the
//! subject (where the optical axes meet) is more than 1.5 times the coarsest of the sharpest
//! quarter's ([`crate::data::camera::resolving_views`]) get maps of confidence 0, listed in
//! `index.json` as `coarse_views`; their photos still count for every other term. The sharpest
//! quarter, not the sharpest view, leads, so that a few close-ups leave the rest as they are.
//!
//! # Device
//! With `device = "gpu"` (feature `gpu`) steps 1-3 run here as always and step 4, the per-pixel work
//! that grows with orientations x taps x pixels, runs as `render/gpu/gabor.wgsl`; the two agree
//! within docs/gpu.md's tolerances (tested: `gpu_filtering_matches_the_cpu`).
//!
//! # Conventions
//! Angles are in [0, pi) in image coordinates, u to the right and v DOWN, and give the direction of the
//! strands (the stripes), not the normal to them: a strand whose projection moves by (du, dv) pixels has
//! angle `atan2(dv, du) mod pi`, exactly [`crate::render::orientation_angle`], so the rendered strand
//! orientation and these maps compare directly.
//!
//! # Inputs and outputs
//! Either `views` (a views directory: its training frames, colour with mask from `_mask.png` or alpha)
//! or `images` (any folder: every `.png`, `.jpg`, `.jpeg` and `.exr` in it except `*_mask.png`,
//! sorted by name; an alpha channel, if present, is the mask). Exactly one must be connected. Pixels
//! outside the mask (mask < 0.5) are not filtered (speed: fur images are mostly background) and get
//! angle 0 and confidence 0. Without a mask every pixel is processed. `downscale` (integer, default
//! 1 because our synthetic images are small; the public code usually works at half resolution, i.e.
//! 2) box-averages the image (and the mask) by that factor first; the maps then have the reduced
//! size, recorded in `index.json`.
//!
//! Output directory `maps`: `<name>_orient.exr` and `<name>_conf.exr` (one channel, f32), `<name>` being
//! the image path relative to its folder without extension (`train/r_000` -> `train/r_000_orient.exr`),
//! and `index.json` listing, in input order, `{image, orient, conf, width, height, downscale}` plus the
//! parameters used and, where there are any, the `coarse_views` (`{image, footprint_ratio}`).

use std::path::PathBuf;

use fure_stage_api::{ParamSpec, Params, PortSpec, Stage, StageContext, StageError};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::data::image::ImageF32;

/// Gabor filter-bank parameters.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GaborParams {
    pub orientations: usize,
    pub dog_sigma_small: f32,
    pub dog_sigma_large: f32,
    pub frequency: f32,
    pub sigma_x: f32,
    pub sigma_y: f32,
}

impl Default for GaborParams {
    fn default() -> Self {
        GaborParams {
            orientations: 180,
            dog_sigma_small: 0.4,
            dog_sigma_large: 10.0,
            frequency: 0.4,
            sigma_x: 1.8,
            sigma_y: 2.4,
        }
    }
}

/// Gray = 0.2989 R + 0.5870 G + 0.1140 B (1- or 2-channel images are gray already).
pub fn to_gray(im: &ImageF32) -> Vec<f32> {
    let c = im.channels as usize;
    (0..(im.width * im.height) as usize)
        .map(|i| {
            let p = &im.data[i * c..i * c + c];
            if c >= 3 {
                0.2989 * p[0] + 0.5870 * p[1] + 0.1140 * p[2]
            } else {
                p[0]
            }
        })
        .collect()
}

fn mirror(i: i64, n: i64) -> usize {
    if n == 1 {
        return 0;
    }
    let period = 2 * (n - 1);
    let m = i.rem_euclid(period);
    (if m >= n { period - m } else { m }) as usize
}

/// Separable Gaussian blur (3 sigma support, normalised, mirrored borders).
pub fn gaussian_blur(img: &[f32], w: usize, h: usize, sigma: f32) -> Vec<f32> {
    if !(sigma > 0.0) {
        return img.to_vec();
    }
    let r = (3.0 * sigma).ceil().max(1.0) as i64;
    let mut k: Vec<f32> = (-r..=r)
        .map(|x| (-(x * x) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let s: f32 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    let mut tmp = vec![0.0f32; w * h];
    tmp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            let mut acc = 0.0;
            for (i, kv) in k.iter().enumerate() {
                acc += kv * img[y * w + mirror(x as i64 + i as i64 - r, w as i64)];
            }
            *o = acc;
        }
    });
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            let mut acc = 0.0;
            for (i, kv) in k.iter().enumerate() {
                acc += kv * tmp[mirror(y as i64 + i as i64 - r, h as i64) * w + x];
            }
            *o = acc;
        }
    });
    out
}

/// One sparse Gabor kernel: (dx, dy, weight) taps.
type Kernel = Vec<(i32, i32, f32)>;

/// The filter bank: kernel k has its stripes along theta_k = k pi / n.
pub fn gabor_bank(p: &GaborParams) -> (Vec<Kernel>, i32) {
    let half = (3.0 * p.sigma_x.max(p.sigma_y)).ceil() as i32;
    let bank = (0..p.orientations)
        .map(|k| {
            let th = k as f32 * std::f32::consts::PI / p.orientations as f32;
            let (s, c) = th.sin_cos();
            let mut taps = Vec::new();
            for dy in -half..=half {
                for dx in -half..=half {
                    let a = dx as f32 * c + dy as f32 * s;
                    let b = -dx as f32 * s + dy as f32 * c;
                    let env = (-(b * b / (2.0 * p.sigma_x * p.sigma_x)
                        + a * a / (2.0 * p.sigma_y * p.sigma_y)))
                        .exp();
                    let w = env * (2.0 * std::f32::consts::PI * p.frequency * b).cos();
                    if w.abs() >= 1e-4 {
                        taps.push((dx, dy, w));
                    }
                }
            }
            taps
        })
        .collect();
    (bank, half)
}

/// What the per-pixel filtering reads: the DoG image mirror-padded by the
/// bank's half-size, and each filter's taps as (offset into the padded image
/// relative to the pixel, weight).
struct Prepared {
    padded: Vec<f32>,
    half: usize,
    flat: Vec<Vec<(isize, f32)>>,
}

/// Steps 1-3 of the module doc: gray, DoG, padding, the bank.
fn prepare(im: &ImageF32, p: &GaborParams) -> Prepared {
    let (w, h) = (im.width as usize, im.height as usize);
    let gray = to_gray(im);
    let a = gaussian_blur(&gray, w, h, p.dog_sigma_small);
    let b = gaussian_blur(&gray, w, h, p.dog_sigma_large);
    let dog: Vec<f32> = a.iter().zip(&b).map(|(x, y)| x - y).collect();
    let (bank, half) = gabor_bank(p);
    // Mirror-padded copy so the inner loop needs no bounds logic.
    let pw = w + 2 * half as usize;
    let ph = h + 2 * half as usize;
    let mut padded = vec![0.0f32; pw * ph];
    for y in 0..ph {
        for x in 0..pw {
            let sx = mirror(x as i64 - half as i64, w as i64);
            let sy = mirror(y as i64 - half as i64, h as i64);
            padded[y * pw + x] = dog[sy * w + sx];
        }
    }
    let flat = bank
        .iter()
        .map(|k| {
            k.iter()
                .map(|&(dx, dy, wt)| ((dy as isize) * pw as isize + dx as isize, wt))
                .collect()
        })
        .collect();
    Prepared {
        padded,
        half: half as usize,
        flat,
    }
}

/// Orientation (radians in [0, pi), image coordinates with v down) and confidence maps of an image.
/// `mask` (same size, one value per pixel) limits the work to pixels with mask >= 0.5.
pub fn orientation_maps(
    im: &ImageF32,
    mask: Option<&[f32]>,
    p: &GaborParams,
) -> (ImageF32, ImageF32) {
    let w = im.width as usize;
    let Prepared {
        padded: pad,
        half,
        flat,
    } = prepare(im, p);
    let pw = w + 2 * half;
    let n = p.orientations;
    let thetas: Vec<f32> = (0..n)
        .map(|k| k as f32 * std::f32::consts::PI / n as f32)
        .collect();
    let pi = std::f32::consts::PI;
    let mut orient = ImageF32::new(im.width, im.height, 1);
    let mut conf = ImageF32::new(im.width, im.height, 1);
    orient
        .data
        .par_chunks_mut(w)
        .zip(conf.data.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (orow, crow))| {
            let mut f = vec![0.0f32; n];
            for x in 0..w {
                if let Some(m) = mask {
                    if m[y * w + x] < 0.5 {
                        continue;
                    }
                }
                let centre = ((y + half) * pw + x + half) as isize;
                for (k, taps) in flat.iter().enumerate() {
                    let mut acc = 0.0f32;
                    for &(off, wt) in taps {
                        acc += wt * pad[(centre + off) as usize];
                    }
                    f[k] = acc.abs();
                }
                let mut best = 0;
                for k in 1..n {
                    if f[k] > f[best] {
                        best = k;
                    }
                }
                let sum: f32 = f.iter().sum();
                let th = thetas[best];
                let var = if sum > 0.0 {
                    f.iter()
                        .zip(&thetas)
                        .map(|(fk, tk)| {
                            let d = (th - tk).abs();
                            let d = d.min(pi - d);
                            fk / sum * d * d
                        })
                        .sum::<f32>()
                } else {
                    // A flat patch: no orientation at all.
                    pi * pi
                };
                orow[x] = th;
                crow[x] = if sum > 0.0 {
                    1.0 / ((var / (pi * pi)).powi(2) + 1e-7)
                } else {
                    0.0
                };
            }
        });
    (orient, conf)
}

/// [`orientation_maps`] on `device`: the per-pixel filtering on the GPU
/// when it is one (`render/gpu/gabor.wgsl`; the same formulas, within
/// docs/gpu.md's tolerances), else the CPU's.
pub fn orientation_maps_on(
    device: &crate::render::device::Renderer,
    im: &ImageF32,
    mask: Option<&[f32]>,
    p: &GaborParams,
) -> Result<(ImageF32, ImageF32), crate::render::RenderError> {
    match device {
        crate::render::device::Renderer::Cpu => Ok(orientation_maps(im, mask, p)),
        #[cfg(feature = "gpu")]
        crate::render::device::Renderer::Gpu(r) => {
            let pr = prepare(im, p);
            let (o, c) = r.gabor_maps(&crate::render::gpu::GaborInput {
                padded: &pr.padded,
                width: im.width,
                height: im.height,
                half: pr.half as u32,
                bank: &pr.flat,
                mask,
            })?;
            let as_image = |data| ImageF32 {
                width: im.width,
                height: im.height,
                channels: 1,
                data,
            };
            Ok((as_image(o), as_image(c)))
        }
    }
}

/// The training views that see the subject (where their optical axes meet) coarser than
/// [`crate::data::camera::resolving_views`] allows; none when the axes do not meet.
pub fn coarse_views(cams: &[crate::data::camera::Camera]) -> Vec<CoarseView> {
    use crate::data::camera;
    cams.iter()
        .zip(camera::camera_footprint_ratios(cams))
        .filter(|(_, ratio)| !camera::resolves(*ratio))
        .map(|(c, ratio)| CoarseView {
            image: c.file_path.clone(),
            footprint_ratio: ratio,
        })
        .collect()
}

/// One entry of `index.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapEntry {
    /// The source image, relative to its folder (as in transforms.json for views).
    pub image: String,
    /// Orientation map file, relative to the `maps` directory.
    pub orient: String,
    /// Confidence map file, relative to the `maps` directory.
    pub conf: String,
    pub width: u32,
    pub height: u32,
    pub downscale: u32,
}

/// `index.json` of the `maps` directory.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapIndex {
    pub params: GaborParams,
    /// `{"device": "cpu" | "gpu", "adapter": ...}`: where the filtering ran;
    /// absent when the stage's `device` parameter is unset (the CPU, and the
    /// bytes the stage wrote before it had the parameter).
    #[serde(default, skip_serializing_if = "serde_json::Value::is_null")]
    pub device: serde_json::Value,
    /// "angle in [0, pi) of the strand direction, image coordinates u right, v down".
    pub convention: String,
    pub maps: Vec<MapEntry>,
    /// Training views that see the subject coarser than the capture's sharper views
    /// (`data::camera::resolving_views`): their maps are written with confidence 0.
    /// Absent when there is none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub coarse_views: Vec<CoarseView>,
}

/// A training view whose maps carry no direction (`MapIndex::coarse_views`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CoarseView {
    pub image: String,
    /// Its pixel footprint at the subject over the coarsest of the sharpest quarter's.
    pub footprint_ratio: f64,
}

fure_stage_api::stage_params! {
    /// The `orientation_maps` stage's parameters; filter defaults from [`GaborParams::default`].
    pub struct OrientationMapsParams {
        /// number of filter orientations
        orientations: usize = int(GaborParams::default().orientations as i64).range(2.0, 3600.0),
        /// DoG small sigma (px)
        dog_sigma_small: f32 = float(GaborParams::default().dog_sigma_small as f64).range(0.0, 100.0),
        /// DoG large sigma (px)
        dog_sigma_large: f32 = float(GaborParams::default().dog_sigma_large as f64).range(0.0, 1000.0),
        /// Gabor frequency (cycles/px)
        frequency: f32 = float(GaborParams::default().frequency as f64).range(0.01, 0.5),
        /// Gabor sigma across the strand (px)
        sigma_x: f32 = float(GaborParams::default().sigma_x as f64).range(0.1, 50.0),
        /// Gabor sigma along the strand (px)
        sigma_y: f32 = float(GaborParams::default().sigma_y as f64).range(0.1, 50.0),
        /// integer box downscale before filtering (1 = none)
        downscale: u32 = int(1).range(1.0, 64.0),
    }
}

/// Stage `orientation_maps`.
pub struct OrientationMapsStage;

impl Stage for OrientationMapsStage {
    fn kind(&self) -> &'static str {
        "orientation_maps"
    }
    fn version(&self) -> u32 {
        3
    }
    fn doc(&self) -> &'static str {
        "Gabor orientation (strand direction angle in [0, pi), v down) and confidence maps of the \
         training images of `views`, or of every PNG of `images`: DoG then 180 Gabor filters."
    }
    fn params(&self) -> Vec<ParamSpec> {
        let mut specs = vec![crate::render::device::device_param()];
        specs.extend(OrientationMapsParams::specs());
        specs
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::dir("views", "views directory (training frames are used)").optional(),
            PortSpec::dir("images", "any folder of PNG, JPEG or EXR images").optional(),
        ]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![PortSpec::dir(
            "maps",
            "<name>_orient.exr, <name>_conf.exr per image and index.json",
        )]
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let device = crate::render::device::Renderer::from_params(ctx.params)?;
        ctx.progress
            .note(&format!("filters on {}", device.describe()));
        let p = OrientationMapsParams::from_params(ctx.params)?;
        let gp = GaborParams {
            orientations: p.orientations,
            dog_sigma_small: p.dog_sigma_small,
            dog_sigma_large: p.dog_sigma_large,
            frequency: p.frequency,
            sigma_x: p.sigma_x,
            sigma_y: p.sigma_y,
        };
        let factor = p.downscale;
        // (relative name, image, mask)
        type Job = (
            String,
            PathBuf,
            Option<(PathBuf, crate::data::camera::Camera)>,
        );
        let mut coarse = Vec::new();
        let jobs: Vec<Job> = match (ctx.input_opt("views"), ctx.input_opt("images")) {
            (Some(v), None) => {
                let cams = crate::formats::cameras::read_views(v)?;
                if cams.train.is_empty() {
                    return Err(StageError::input("views", v, "no training frames"));
                }
                coarse = coarse_views(&cams.train);
                if let Some(worst) = coarse.iter().map(|c| c.footprint_ratio).reduce(f64::max) {
                    ctx.progress.note(&format!(
                        "{} of {} training views see the animal more than {} times coarser than \
                         the sharpest quarter of the views (up to {worst:.2}): their maps carry \
                         no direction (confidence 0), since a coarser pixel shows the coat's \
                         pattern rather than its fur; index.json lists them",
                        coarse.len(),
                        cams.train.len(),
                        crate::data::camera::RESOLVING_RATIO,
                    ));
                }
                cams.train
                    .into_iter()
                    .map(|c| {
                        (
                            c.file_path.clone(),
                            v.join(&c.file_path),
                            Some((v.to_path_buf(), c)),
                        )
                    })
                    .collect()
            }
            (None, Some(dir)) => {
                let mut files = Vec::new();
                for e in std::fs::read_dir(dir).map_err(|e| StageError::io(dir, e))? {
                    let path = e.map_err(|e| StageError::io(dir, e))?.path();
                    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
                    let photo = crate::formats::images::IMAGE_EXTENSIONS
                        .contains(&crate::formats::extension(&path).as_str());
                    if path.is_file() && photo && !name.ends_with("_mask.png") {
                        files.push((name.to_string(), path.clone(), None));
                    }
                }
                files.sort_by(|a, b| a.0.cmp(&b.0));
                if files.is_empty() {
                    return Err(StageError::input(
                        "images",
                        dir,
                        "holds no image (.png, .jpg, .jpeg or .exr)",
                    ));
                }
                files
            }
            _ => {
                return Err(StageError::failed(
                    "connect exactly one of the inputs `views` and `images`",
                ))
            }
        };
        let out_dir = ctx.output("maps")?;
        ctx.progress.set_total(jobs.len() as u64);
        let mut entries = Vec::with_capacity(jobs.len());
        for (rel, path, view) in jobs {
            ctx.progress.check_interrupted()?;
            ctx.progress.message(&format!("Gabor filtering {rel}"));
            let (img, mask) = match view {
                Some((dir, cam)) => {
                    let v = crate::formats::cameras::read_view(&dir, &cam)?;
                    (v.rgb, v.mask)
                }
                None => {
                    let im = crate::formats::images::read_image(&path)?;
                    let mask = (im.channels == 4 || im.channels == 2).then(|| {
                        let c = im.channels as usize;
                        let mut m = ImageF32::new(im.width, im.height, 1);
                        for i in 0..m.data.len() {
                            m.data[i] = im.data[i * c + c - 1];
                        }
                        m
                    });
                    (im, mask)
                }
            };
            if img.width == 0 || img.height == 0 {
                return Err(StageError::failed(format!(
                    "{}: empty image",
                    path.display()
                )));
            }
            let img = img.box_downscaled(factor);
            let mask = mask.map(|m| m.box_downscaled(factor));
            let (o, c) = if coarse.iter().any(|c| c.image == rel) {
                let blank = ImageF32::new(img.width, img.height, 1);
                (blank.clone(), blank)
            } else {
                orientation_maps_on(&device, &img, mask.as_ref().map(|m| m.data.as_slice()), &gp)?
            };
            fure_stage_api::ensure_finite(
                &format!("orientation maps of {rel}"),
                o.data.iter().chain(&c.data).copied(),
            )?;
            let stem = crate::formats::cameras::file_stem(&rel);
            let (on, cn) = (format!("{stem}_orient.exr"), format!("{stem}_conf.exr"));
            crate::formats::images::write_exr(out_dir.join(&on), &o)?;
            crate::formats::images::write_exr(out_dir.join(&cn), &c)?;
            entries.push(MapEntry {
                image: rel,
                orient: on,
                conf: cn,
                width: o.width,
                height: o.height,
                downscale: factor,
            });
            ctx.progress.advance(1);
        }
        let index = MapIndex {
            params: gp,
            device: if ctx.params.get("device").is_some() {
                device.metrics()
            } else {
                serde_json::Value::Null
            },
            convention:
                "angle in [0, pi) of the strand direction, image coordinates u right, v down \
                         (render::orientation_angle)"
                    .into(),
            maps: entries,
            coarse_views: coarse,
        };
        crate::formats::json::write_json(out_dir.join("index.json"), &index)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Stripes whose lines run along angle `theta` (v down), period `period` px.
    fn stripes(w: u32, h: u32, theta: f32, period: f32) -> ImageF32 {
        let mut im = ImageF32::new(w, h, 3);
        let n = (-theta.sin(), theta.cos());
        for y in 0..h {
            for x in 0..w {
                let b = x as f32 * n.0 + y as f32 * n.1;
                let v = 0.5 + 0.4 * (2.0 * std::f32::consts::PI * b / period).cos();
                im.pixel_mut(x, y).copy_from_slice(&[v, v, v]);
            }
        }
        im
    }

    fn circ_deg(a: f32, b: f32) -> f32 {
        let d = (a - b).abs() % std::f32::consts::PI;
        d.min(std::f32::consts::PI - d).to_degrees()
    }

    #[test]
    fn stripes_of_known_angle() {
        let p = GaborParams::default();
        for deg in [0.0f32, 30.0, 72.0, 90.0, 135.0, 161.0] {
            let th = deg.to_radians();
            let im = stripes(48, 40, th, 1.0 / p.frequency);
            let (o, c) = orientation_maps(&im, None, &p);
            // Interior pixels (away from mirrored borders). The filters are the real (even) part only,
            // as in the public recipe, so pixels whose stripe phase sits at a zero crossing of the
            // right filter get weak, unreliable responses: they must be rare and low-confidence.
            let (mut good, mut total) = (0, 0);
            let (mut conf_good, mut conf_bad) = (0.0f64, 0.0f64);
            let mut bad = 0;
            for y in 12..28 {
                for x in 12..36 {
                    total += 1;
                    let cv = c.pixel(x, y)[0] as f64;
                    if circ_deg(o.pixel(x, y)[0], th) <= 1.01 {
                        good += 1;
                        conf_good += cv;
                    } else {
                        bad += 1;
                        conf_bad += cv;
                    }
                }
            }
            assert!(
                good as f32 >= 0.8 * total as f32,
                "{deg} deg: {good} of {total} within 1 degree"
            );
            if bad > 0 {
                assert!(conf_good / good as f64 > conf_bad / bad as f64);
            }
        }
    }

    /// Fur texture at the finest scale (2.5 px) along one direction under a stronger, coarser
    /// coat pattern (7 px stripes) across it, as a tiger at 256 px: the default filters follow the
    /// fur, the public recipe's 4.35 px filters the stripes.
    #[test]
    fn the_default_wavelength_follows_fine_fur_not_coarse_stripes() {
        let (fur, coat) = (20f32.to_radians(), 110f32.to_radians());
        let a = stripes(48, 48, fur, 2.5);
        let b = stripes(48, 48, coat, 7.0);
        let mut im = ImageF32::new(48, 48, 3);
        for i in 0..im.data.len() {
            im.data[i] = 0.5 + 0.5 * (a.data[i] - 0.5) + (b.data[i] - 0.5);
        }
        let share_near = |p: &GaborParams, th: f32| {
            let (o, _) = orientation_maps(&im, None, p);
            let mut near = 0;
            for y in 12..36 {
                for x in 12..36 {
                    near += usize::from(circ_deg(o.pixel(x, y)[0], th) <= 10.0);
                }
            }
            near as f32 / (24.0 * 24.0)
        };
        let ours = GaborParams::default();
        let public = GaborParams {
            frequency: 0.23,
            ..ours
        };
        assert!(share_near(&ours, fur) > 0.8, "{}", share_near(&ours, fur));
        assert!(
            share_near(&public, coat) > 0.8,
            "{}",
            share_near(&public, coat)
        );
    }

    #[test]
    fn convention_matches_the_renderer() {
        // A stripe along the image direction (du, dv) = (1, 2) (down-right) has the renderer's angle.
        let th = crate::render::orientation_angle(1.0, 2.0);
        let im = stripes(40, 40, (2.0f32).atan2(1.0), 2.5);
        let (o, _) = orientation_maps(&im, None, &GaborParams::default());
        assert!(circ_deg(o.pixel(20, 20)[0], th) <= 1.01);
    }

    #[test]
    fn confidence_is_higher_on_stripes_than_noise_and_mask_skips() {
        let p = GaborParams::default();
        let s = stripes(40, 40, 0.5, 4.35);
        let mut noise = ImageF32::new(40, 40, 3);
        let mut x = 12345u64;
        for v in noise.data.iter_mut() {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            *v = (x >> 40) as f32 / (1u64 << 24) as f32;
        }
        let (_, cs) = orientation_maps(&s, None, &p);
        let (_, cn) = orientation_maps(&noise, None, &p);
        let med = |c: &ImageF32| {
            let mut v: Vec<f32> = (10..30)
                .flat_map(|y| (10..30).map(move |x| (x, y)))
                .map(|(x, y)| c.pixel(x, y)[0])
                .collect();
            v.sort_by(f32::total_cmp);
            v[v.len() / 2]
        };
        assert!(med(&cs) > 10.0 * med(&cn), "{} vs {}", med(&cs), med(&cn));
        // A mask of zeros leaves everything at 0.
        let m = vec![0.0f32; 1600];
        let (o, c) = orientation_maps(&s, Some(&m), &p);
        assert!(o.data.iter().chain(&c.data).all(|v| *v == 0.0));
    }

    /// The GPU's filtering against the CPU's on stripes plus noise, with a
    /// mask: the same angle (within one filter step) on at least 99 % of
    /// the pixels, the confidence within 1e-3 relative where the angle is
    /// the same, and the masked-out pixels at 0.
    #[cfg(feature = "gpu")]
    #[test]
    fn gpu_filtering_matches_the_cpu() {
        let gpu = match crate::render::device::Renderer::from_choice("gpu") {
            Ok(r) => r,
            Err(e) => {
                eprintln!("SKIPPED: GPU parity test needs a GPU adapter: {e}");
                return;
            }
        };
        let p = GaborParams::default();
        let (w, h) = (53u32, 37u32);
        let mut im = stripes(w, h, 0.7, 3.0);
        let mut x = 99u64;
        for v in im.data.iter_mut() {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            *v = 0.7 * *v + 0.3 * ((x >> 40) as f32 / (1u64 << 24) as f32);
        }
        let mask: Vec<f32> = (0..w * h).map(|i| ((i % 7) != 0) as u8 as f32).collect();
        for m in [None, Some(mask.as_slice())] {
            let (oc, cc) = orientation_maps(&im, m, &p);
            let (og, cg) = orientation_maps_on(&gpu, &im, m, &p).unwrap();
            let step = 180.0 / p.orientations as f32 + 1e-3;
            let (mut same, mut worst) = (0usize, 0.0f32);
            for i in 0..oc.data.len() {
                if circ_deg(oc.data[i], og.data[i]) <= step {
                    same += 1;
                }
                if oc.data[i] == og.data[i] {
                    let rel = (cc.data[i] - cg.data[i]).abs() / cc.data[i].abs().max(1.0);
                    worst = worst.max(rel);
                }
            }
            let share = same as f32 / oc.data.len() as f32;
            eprintln!("gabor gpu vs cpu: same angle {share}, worst confidence {worst:e}");
            assert!(share >= 0.99, "{share}");
            assert!(worst <= 1e-3, "{worst}");
            if let Some(m) = m {
                for (i, mv) in m.iter().enumerate() {
                    if *mv < 0.5 {
                        assert!(og.data[i] == 0.0 && cg.data[i] == 0.0);
                    }
                }
            }
        }
    }

    #[test]
    fn stage_on_an_image_folder() {
        let dir = tempfile::tempdir().unwrap();
        let imgs = dir.path().join("imgs");
        std::fs::create_dir_all(&imgs).unwrap();
        // b.png: stripes at 45 degrees with an alpha mask covering the left half; a.png: RGB stripes.
        let mut rgba = ImageF32::new(32, 24, 4);
        let s = stripes(32, 24, 45f32.to_radians(), 4.35);
        for y in 0..24 {
            for x in 0..32 {
                let v = s.pixel(x, y)[0];
                let a = if x < 16 { 1.0 } else { 0.0 };
                rgba.pixel_mut(x, y).copy_from_slice(&[v, v, v, a]);
            }
        }
        crate::formats::images::write_png(imgs.join("b.png"), &rgba).unwrap();
        crate::formats::images::write_png(imgs.join("a.png"), &stripes(32, 24, 0.3, 4.35)).unwrap();
        crate::formats::images::write_png(imgs.join("a_mask.png"), &ImageF32::new(32, 24, 1))
            .unwrap();
        // c.JPG: the same 45-degree stripes as a JPEG photo; notes.txt is no image.
        let raw: Vec<u8> = s.data.iter().map(|v| (v * 255.0).round() as u8).collect();
        let mut jpg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpg, 95)
            .encode(&raw, 32, 24, image::ExtendedColorType::Rgb8)
            .unwrap();
        std::fs::write(imgs.join("c.JPG"), &jpg).unwrap();
        std::fs::write(imgs.join("notes.txt"), "not an image").unwrap();
        let out = dir.path().join("out");
        let outs = crate::evaluation::evaluate::tests::run_stage(
            &OrientationMapsStage,
            &[("images", imgs.clone())],
            &out,
        )
        .unwrap();
        let maps = &outs["maps"];
        let idx: MapIndex = crate::formats::json::read_json(maps.join("index.json")).unwrap();
        let names: Vec<&str> = idx.maps.iter().map(|m| m.image.as_str()).collect();
        assert_eq!(names, vec!["a.png", "b.png", "c.JPG"]);
        let o = crate::formats::images::read_exr(maps.join(&idx.maps[1].orient)).unwrap();
        let c = crate::formats::images::read_exr(maps.join(&idx.maps[1].conf)).unwrap();
        assert_eq!((o.width, o.height, o.channels), (32, 24, 1));
        assert!(circ_deg(o.pixel(8, 12)[0], 45f32.to_radians()) <= 1.01);
        assert!(c.pixel(8, 12)[0] > 0.0);
        assert_eq!(c.pixel(24, 12)[0], 0.0, "outside the alpha mask");
        let o = crate::formats::images::read_exr(maps.join(&idx.maps[2].orient)).unwrap();
        assert!(circ_deg(o.pixel(16, 12)[0], 45f32.to_radians()) <= 2.0);
        // Neither or both inputs: a clear error.
        let e = crate::evaluation::evaluate::tests::run_stage(
            &OrientationMapsStage,
            &[],
            &dir.path().join("o2"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("exactly one"), "{e}");
    }

    #[test]
    fn views_coarser_than_the_sharper_ones_carry_no_direction() {
        use crate::data::camera::CameraSet;
        // An orbit of eight cameras, every other one at half the resolution: the same stripes
        // in every photo, so only the footprint rule can tell the maps apart.
        let dir = tempfile::tempdir().unwrap();
        let views = dir.path().join("views");
        std::fs::create_dir_all(&views).unwrap();
        let train = crate::data::camera::orbit(8, |_| 4.0, |i| if i % 2 == 0 { 48 } else { 24 });
        for cam in &train {
            let mut rgba = ImageF32::new(cam.width, cam.height, 4);
            let s = stripes(cam.width, cam.height, 0.5, 2.5);
            for (px, v) in rgba.data.chunks_exact_mut(4).zip(&s.data) {
                px.copy_from_slice(&[*v, *v, *v, 1.0]);
            }
            crate::formats::images::write_png(views.join(&cam.file_path), &rgba).unwrap();
        }
        crate::formats::cameras::write_views(
            &views,
            &CameraSet {
                train,
                test: vec![],
            },
        )
        .unwrap();
        let outs = crate::evaluation::evaluate::tests::run_stage(
            &OrientationMapsStage,
            &[("views", views)],
            &dir.path().join("out"),
        )
        .unwrap();
        let maps = &outs["maps"];
        let idx: MapIndex = crate::formats::json::read_json(maps.join("index.json")).unwrap();
        let coarse: Vec<&str> = idx.coarse_views.iter().map(|c| c.image.as_str()).collect();
        assert_eq!(coarse, ["1.png", "3.png", "5.png", "7.png"]);
        assert!(idx
            .coarse_views
            .iter()
            .all(|c| (c.footprint_ratio - 2.0).abs() < 1e-3));
        for (k, entry) in idx.maps.iter().enumerate() {
            let c = crate::formats::images::read_exr(maps.join(&entry.conf)).unwrap();
            let confident = c.data.iter().filter(|v| **v > 0.0).count();
            if k % 2 == 0 {
                assert!(confident > c.data.len() / 2, "{}: {confident}", entry.image);
            } else {
                assert_eq!(confident, 0, "{}", entry.image);
            }
        }
    }
}
