//! Orientation-map diagnostics on a pipeline run's outputs: how well the Gabor
//! maps of the training views follow the ground-truth strands, which is what the
//! orientation loss assumes. Needs a synthetic scene (its GT strands).
//!
//! ```sh
//! fure run pipelines/tiger.toml --until orientation
//! cargo run -p fure-stages --release --example orientation_diagnostics -- out/tiger [KEY=VALUE ...]
//! cargo run -p fure-stages --release --example orientation_diagnostics -- CAPTURE_DIR [KEY=VALUE ...]
//! ```
//!
//! `CAPTURE_DIR` is a capture written by `stages/src/scenes/synthetic/fur_capture.py` (`views/`, and the
//! hair Blender rendered in `gt/`): it has no depth map or fur mask, so the nearest GT segment
//! per pixel stands for the visible surface and the silhouette for the fur mask.
//!
//! The GT strands are projected into every training view directly (no renderer):
//! per pixel, the structure tensor of the GT segments whose midpoint falls in it
//! and lies at most 1.5 cm behind the GT depth map, kept where those segments
//! agree (coherence >= 0.5). The Gabor maps are recomputed from the views with
//! the given filter settings (`frequency`, `sigma_x`, `sigma_y`,
//! `dog_sigma_small`, `dog_sigma_large`, `orientations`, `downscale`; defaults as
//! the `orientation_maps` stage; `min_confidence` skips pixels below that
//! normalised confidence, as the learners' `ori_min_confidence`). Over the pixels of the GT fur mask it prints,
//! per view and in total: the mean angle between map and GT weighted by the
//! normalised confidence (the loss's weight), the unweighted mean, and the
//! confidence-weighted share of pixels within 20 degrees and beyond 60 degrees
//! (near perpendicular: what coat patterns whose stripes run across the fur
//! give). Random maps would give 45 degrees and 33 %. Figures: docs/history.md.

mod common;

use std::path::Path;

use fure_stages::data::image::ImageF32;
use fure_stages::formats::cameras::{read_view, read_views};
use fure_stages::formats::hair::read_hair;
use fure_stages::formats::images::read_image;
use fure_stages::growth::learn::image::normalise_confidence;
use fure_stages::growth::orientation::{orientation_maps, GaborParams};

use common::Res;

fn main() -> std::process::ExitCode {
    common::exit_code(run())
}

/// Accumulated agreement over pixels: (weight, weighted angle, count, angle, weight < 20, weight > 60).
#[derive(Default, Clone, Copy)]
struct Agreement {
    weight: f64,
    weighted_deg: f64,
    count: f64,
    deg: f64,
    within_20: f64,
    beyond_60: f64,
}

impl Agreement {
    fn add(&mut self, deg: f64, w: f64) {
        self.weight += w;
        self.weighted_deg += w * deg;
        self.count += 1.0;
        self.deg += deg;
        if deg < 20.0 {
            self.within_20 += w;
        }
        if deg > 60.0 {
            self.beyond_60 += w;
        }
    }
    fn merge(&mut self, o: &Agreement) {
        self.weight += o.weight;
        self.weighted_deg += o.weighted_deg;
        self.count += o.count;
        self.deg += o.deg;
        self.within_20 += o.within_20;
        self.beyond_60 += o.beyond_60;
    }
    fn line(&self) -> String {
        let w = self.weight.max(1e-12);
        format!(
            "weighted mean {:5.1} deg, unweighted {:5.1} deg, within 20 deg {:5.1} %, beyond 60 deg {:5.1} % ({} px)",
            self.weighted_deg / w,
            self.deg / self.count.max(1.0),
            100.0 * self.within_20 / w,
            100.0 * self.beyond_60 / w,
            self.count
        )
    }
}

/// Filter settings, downscale factor and the normalised confidence below which pixels are skipped.
fn params(args: &[String]) -> Res<(GaborParams, u32, f32)> {
    let mut p = GaborParams::default();
    let mut factor = 1;
    let mut min_confidence = 0.0;
    for a in args {
        let (k, v) = a
            .split_once('=')
            .ok_or(format!("expected KEY=VALUE, got `{a}`"))?;
        match k {
            "frequency" => p.frequency = v.parse()?,
            "sigma_x" => p.sigma_x = v.parse()?,
            "sigma_y" => p.sigma_y = v.parse()?,
            "dog_sigma_small" => p.dog_sigma_small = v.parse()?,
            "dog_sigma_large" => p.dog_sigma_large = v.parse()?,
            "orientations" => p.orientations = v.parse()?,
            "downscale" => factor = v.parse()?,
            "min_confidence" => min_confidence = v.parse()?,
            _ => return Err(format!("unknown key `{k}`").into()),
        }
    }
    Ok((p, factor, min_confidence))
}

/// Nearest-pixel lookup of a map of another size (downscaled maps).
fn at(m: &ImageF32, x: u32, y: u32, w: u32, h: u32) -> f32 {
    let mx = (x * m.width / w).min(m.width - 1);
    let my = (y * m.height / h).min(m.height - 1);
    m.data[(my * m.width + mx) as usize]
}

/// GT segments whose midpoint lies at most this far behind the rendered GT depth count as visible.
const DEPTH_TOLERANCE_CM: f32 = 1.5;

/// Calls `f(pixel, midpoint depth, image direction)` for every GT segment whose projected
/// midpoint falls inside a `w` x `h` view (both ends in front of the camera).
fn for_each_projected_segment(
    gt: &fure_stages::data::strands::Strands,
    cam: &fure_stages::data::camera::Camera,
    w: u32,
    h: u32,
    mut f: impl FnMut(usize, f32, glam::Vec2),
) {
    for s in 0..gt.len() {
        for seg in gt.strand(s).windows(2) {
            let (a, za) = cam.project(seg[0]);
            let (b, zb) = cam.project(seg[1]);
            if za <= 0.0 || zb <= 0.0 {
                continue;
            }
            let m = 0.5 * (a + b);
            let (x, y) = (m.x.floor() as i64, m.y.floor() as i64);
            if x < 0 || y < 0 || x >= w as i64 || y >= h as i64 {
                continue;
            }
            f((y as u32 * w + x as u32) as usize, 0.5 * (za + zb), b - a);
        }
    }
}

/// Per pixel, the structure tensor `[du du, du dv, dv dv]` of the visible GT segments whose
/// projected midpoint falls in it, each weighted by its projected length (a direct projection
/// of the polylines, independent of both renderers).
fn gt_structure_tensor(
    gt: &fure_stages::data::strands::Strands,
    cam: &fure_stages::data::camera::Camera,
    depth: &ImageF32,
    tolerance: f32,
) -> Vec<[f32; 3]> {
    let mut t = vec![[0.0f32; 3]; (depth.width * depth.height) as usize];
    for_each_projected_segment(gt, cam, depth.width, depth.height, |i, z, dir| {
        let d = depth.data[i * depth.channels as usize];
        let len = dir.length();
        if d <= 0.0 || z > d + tolerance || len <= 0.0 {
            return;
        }
        let (du, dv) = (dir.x / len, dir.y / len);
        t[i][0] += len * du * du;
        t[i][1] += len * du * dv;
        t[i][2] += len * dv * dv;
    });
    t
}

/// Per pixel, the depth of the nearest GT segment midpoint projecting into it (0 where none).
fn gt_depth(
    gt: &fure_stages::data::strands::Strands,
    cam: &fure_stages::data::camera::Camera,
    w: u32,
    h: u32,
) -> ImageF32 {
    let mut d = ImageF32::new(w, h, 1);
    for_each_projected_segment(gt, cam, w, h, |i, z, _| {
        let v = &mut d.data[i];
        if *v == 0.0 || z < *v {
            *v = z;
        }
    });
    d
}

fn run() -> Res<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let dir = Path::new(
        args.first()
            .ok_or("usage: orientation_diagnostics RUN_DIR [KEY=VALUE ...]")?,
    );
    let (gp, factor, min_confidence) = params(&args[1..])?;
    // A pipeline run (`scene/` holds the synthetic scene) or a capture written by
    // stages/src/scenes/synthetic/fur_capture.py (`views/`, and the hair it rendered in `gt/`).
    let (views, gt_dir) = if dir.join("scene/views").is_dir() {
        (dir.join("scene/views"), dir.join("scene"))
    } else {
        (dir.join("views"), dir.join("gt"))
    };
    let cams = read_views(&views)?;
    let gt = read_hair(gt_dir.join("strands.hair"))?;
    let scene: serde_json::Value =
        serde_json::from_slice(&std::fs::read(gt_dir.join("scene.json"))?)?;
    let s_cm = scene["s_cm"].as_f64().ok_or("scene.json: no s_cm")? as f32;
    let tolerance = DEPTH_TOLERANCE_CM / s_cm;
    let mut total = Agreement::default();
    for cam in &cams.train {
        let v = read_view(&views, cam)?;
        let (im, mask) = if factor > 1 {
            (
                v.rgb.box_downscaled(factor),
                v.mask.as_ref().map(|m| m.box_downscaled(factor)),
            )
        } else {
            (v.rgb, v.mask)
        };
        let (orient, mut conf) =
            orientation_maps(&im, mask.as_ref().map(|m| m.data.as_slice()), &gp);
        normalise_confidence(&mut conf);
        let stem = cam.file_path.trim_end_matches(".png");
        // Without the synthetic scene's fur mask and depth map (a Blender capture): the
        // silhouette, and the nearest GT segment per pixel as the visible surface.
        let fur = match read_image(views.join(format!("{stem}_fur.png"))) {
            Ok(f) => f,
            Err(_) => mask.clone().ok_or("no fur mask and no silhouette")?,
        };
        let depth = match read_image(views.join(format!("{stem}_depth.exr"))) {
            Ok(d) => d,
            Err(_) => gt_depth(&gt, cam, fur.width, fur.height),
        };
        let (w, h) = (depth.width, depth.height);
        let tensor = gt_structure_tensor(&gt, cam, &depth, tolerance);
        let mut a = Agreement::default();
        for y in 0..h {
            for x in 0..w {
                let i = (y * w + x) as usize;
                let fc = fur.channels as usize;
                let [xx, xy, yy] = tensor[i];
                let tr = xx + yy;
                if fur.data[i * fc] < 0.5 || tr <= 0.0 {
                    continue;
                }
                // Coherence (l1 - l2) / (l1 + l2): below 0.5 the visible GT strands disagree.
                let coherence = ((xx - yy).powi(2) + 4.0 * xy * xy).sqrt() / tr;
                if coherence < 0.5 {
                    continue;
                }
                let gt_angle = (0.5 * (2.0 * xy).atan2(xx - yy)).rem_euclid(std::f32::consts::PI);
                let c = at(&conf, x, y, w, h);
                let o = at(&orient, x, y, w, h);
                let d = (o - gt_angle).abs() % std::f32::consts::PI;
                let d = d.min(std::f32::consts::PI - d).to_degrees();
                if c >= min_confidence {
                    a.add(f64::from(d), f64::from(c));
                }
            }
        }
        println!("{stem}: {}", a.line());
        total.merge(&a);
    }
    println!("all views: {}", total.line());
    Ok(())
}
