//! The `working_views` stage: a capture's views as every other stage works on them, pinhole
//! cameras at a working resolution.
//!
//! **Lenses.** The stages project through pinholes ([`Camera`]), and every reader but this
//! stage's refuses a camera whose lens distorts ([`cameras::read_views`]). A photo capture
//! calibrated by COLMAP has one by default (`SIMPLE_RADIAL`), nerfstudio's `OPENCV` another, so
//! this stage reads the lenses ([`cameras::read_capture`]) and resamples each distorted photo,
//! its mask and fur mask onto the pinhole with the same intrinsics and size
//! ([`crate::data::lens`]: the frame keeps its size and centre; what the lens showed beyond the
//! pinhole's frame is dropped, and where the pinhole sees past the photo its border goes on, so
//! that an animal the photo's frame cuts still reaches the working frame's border, where
//! `outer_surface` carves nothing beyond it).
//!
//! **Resolution**, so that what a large photo capture costs stays bounded.
//! Every stage that renders or filters the images pays for each pixel: the tiger's views
//! upscaled 4x (1024 px) took 207 s for the orientation maps instead of 11 and 364 s for the
//! Frosting fit instead of 20, so a photo capture at 4,000-6,000 px would run for hours. But
//! averaging also erases the strands' texture the orientation maps read: four dev scenes
//! rendered at 512 px (the animal spans 346-367 px) and run as captures, full resolution against
//! box-averaged by 2, seed 0, signed F at 1 cm: tiger 78.2 against 55.9 (the maps' coherence 0.54
//! against 0.24), lynx 46.6 against 43.1, fox 64.2 against 65.7, sheepdog 18.4 against 23.6
//! (docs/history.md, "Captures as other software writes them"). So `subject_px` is 400: a
//! capture whose animal spans up to 600 px passes as it is, and only a larger one comes down,
//! to 300-500 px, to bound the cost. `pipelines/capture.toml` reads its photos through it.
//!
//! **Soft photos.** Every rule that reads the views assumes their pixel is their resolution:
//! the orientation maps' Gabor filters have a fixed frequency per pixel, and the roots' density,
//! the basis' points per strand and the codec's component reach go by the pixel footprint.
//! Photos softer than their pixel (upscaled, out of focus, heavily compressed) break that: the
//! JPEG tiger capture upscaled 4x (bicubic) and box-averaged by 2 for its extent read no fur
//! texture (the maps' mean coherence 0.24 against 0.42), the views' elevation stood the strands
//! up (52 degrees against 19) and the strict 1 cm F-score fell from 73.5 to 8.4. So the stage
//! reads how far the photos are smooth ([`crate::data::sharpness`]: the lag over which the
//! luma inside the animal varies like a signal blurred beyond its pixel; 1 for every sharp
//! capture measured, 3 for that upscaled tiger) and box-averages them by that lag.
//!
//! The factor is one integer `f` for the whole capture: the animal's extent, the median over
//! the training views of the longer side of the mask's bounding box (mask above one half), over
//! `subject_px`, rounded (`f_extent = max(1, round(extent / subject_px))`), raised to the lag the
//! photos are smooth over where the animal keeps at least `subject_px / 2` pixels (`f =
//! max(f_extent, min(lag, max(1, floor(2 extent / subject_px))))`; `subject_px = 0` keeps every
//! view's size). The floor, because a small animal loses more with its pixels than its texture
//! gains: the same JPEG tiger capture blurred at its own 256 px (Gaussian, 2 px; the animal 183
//! px, smooth over 3) scores 10.5 / 56.2 / 81.0 / 91.9 (unsigned F, 1-4 cm) kept as it is and 7.4
//! / 37.3 / 59.4 / 78.6 averaged by 3 (61 px); the upscaled tiger (732 px) at a factor of 3 (244
//! px) scores 75.4 / 96.7 / 98.8 / 99.6 (docs/history.md, "Photos softer than their pixel"). With `f = 1` and pinhole lenses the output is the input, byte for byte (any
//! layout), so a capture already near the working size reads exactly as without the stage.
//! Otherwise every frame, training and held-out, is undistorted when its lens distorts, then
//! box-averaged by `f` ([`ImageF32::box_downscaled`]: the last partial rows and columns
//! dropped), its mask file (found as every stage finds it, [`cameras::mask_path`]) and its fur
//! mask (`<stem>_fur.png`) with it, and its camera's `fx`, `fy`, `cx`, `cy` divided by `f`
//! (exact: an output pixel covers `f x f` input pixels, centres at half-integers). The output is
//! a NeRF-style views directory (`transforms.json`, `transforms_test.json`, pinhole cameras; a
//! COLMAP capture's frames keep their names and its held-out split) of PNG images
//! (`<stem>.png`, alpha kept; `<stem>.exr` for an EXR photo, its values as they were) and
//! `<stem>_mask.png` masks: we never write lossy files.

use std::path::Path;

use fure_stage_api::{ParamSpec, Params, PortSpec, Stage, StageContext, StageError};
use rayon::prelude::*;
use serde_json::json;

use crate::data::camera::{Camera, CameraSet};
use crate::data::image::ImageF32;
use crate::data::lens::{undistorted, Distortion};
use crate::data::sharpness::{smooth_lag, smoothness_ratios, structure_function};
use crate::formats::{self, cameras, images};

fure_stage_api::stage_params! {
    /// The `working_views` stage's parameters.
    pub struct WorkingViewsParams {
        /// the animal's extent in pixels to aim for (median over the training views of the mask's bounding box's longer side); 0 keeps the views as they are
        subject_px: usize = int(400).range(0.0, 100000.0),
        /// photos count as smooth over a lag of k pixels while the mean squared luma difference at 2k over that at k (inside the animal) is at least this, and are box-averaged by the first k where it is not, as far as the animal keeps subject_px / 2 pixels (soft photos, module doc); 0 = no such reading
        smooth_ratio: f64 = float(crate::data::sharpness::SMOOTH_RATIO).range(0.0, 4.0),
    }
}

/// The longer side of the foreground's bounding box (values above one half), in pixels; 0 for
/// an empty mask.
fn extent(mask: &ImageF32) -> u32 {
    let (mut x0, mut y0, mut x1, mut y1) = (u32::MAX, u32::MAX, 0, 0);
    for y in 0..mask.height {
        for x in 0..mask.width {
            if mask.pixel(x, y)[0] > 0.5 {
                x0 = x0.min(x);
                y0 = y0.min(y);
                x1 = x1.max(x + 1);
                y1 = y1.max(y + 1);
            }
        }
    }
    if x0 == u32::MAX {
        0
    } else {
        (x1 - x0).max(y1 - y0)
    }
}

/// The capture's working factor (module doc): the larger of the factor for `subject_px` and
/// the lag over which the photos are smooth.
#[derive(Debug, Clone, PartialEq)]
pub struct WorkingFactor {
    /// The factor every frame is box-averaged by.
    pub factor: u32,
    /// The animal's extent, the median over the training views (pixels).
    pub extent: u32,
    /// The factor `subject_px` asks for.
    pub for_extent: u32,
    /// The lag over which the photos are smooth ([`smooth_lag`]).
    pub smooth_lag: u32,
    /// The median `D(2k) / D(k)` for `k = 1..=MAX_SMOOTH_LAG`.
    pub ratios: Vec<Option<f64>>,
}

/// Reads the training views once for the animal's extent and the photos' smoothness.
pub fn working_factor(
    dir: &Path,
    train: &[Camera],
    p: &WorkingViewsParams,
) -> Result<WorkingFactor, StageError> {
    let readings = train
        .par_iter()
        .map(|cam| {
            let v = cameras::read_view(dir, cam).map_err(|e| e.for_input("views"))?;
            let mask = v
                .mask
                .ok_or_else(|| cameras::missing_mask(dir, cam).for_input("views"))?;
            Ok((extent(&mask), structure_function(&v.rgb, &mask)))
        })
        .collect::<Vec<Result<(u32, Vec<Option<f64>>), StageError>>>()
        .into_iter()
        // The first bad view by index, whichever thread met it first.
        .collect::<Result<Vec<_>, StageError>>()?;
    let (mut extents, structures): (Vec<u32>, Vec<Vec<Option<f64>>>) = readings.into_iter().unzip();
    extents.sort_unstable();
    let median = extents[extents.len() / 2];
    let ratios = smoothness_ratios(&structures);
    if p.subject_px == 0 {
        return Ok(WorkingFactor {
            factor: 1,
            extent: median,
            for_extent: 1,
            smooth_lag: 1,
            ratios,
        });
    }
    let for_extent = (median as f64 / p.subject_px as f64).round().max(1.0) as u32;
    let smooth_lag = smooth_lag(&ratios, p.smooth_ratio);
    // Soft photos come down by the lag they are smooth over, but the animal keeps at least half
    // of subject_px (module doc).
    let floor = (2 * median as usize / p.subject_px).max(1) as u32;
    Ok(WorkingFactor {
        factor: for_extent.max(smooth_lag.min(floor)),
        extent: median,
        for_extent,
        smooth_lag,
        ratios,
    })
}

/// `camera` seen through images box-averaged by `f`, its image renamed `<stem>.png` (`.exr`
/// for an EXR photo, whose values may exceed 1 and want more than 8 bits).
fn scaled_camera(camera: &Camera, f: u32) -> Camera {
    let s = 1.0 / f as f32;
    let ext = match formats::extension(Path::new(&camera.file_path)).as_str() {
        "exr" => "exr",
        _ => "png",
    };
    Camera {
        file_path: format!("{}.{ext}", cameras::file_stem(&camera.file_path)),
        fx: camera.fx * s,
        fy: camera.fy * s,
        cx: camera.cx * s,
        cy: camera.cy * s,
        width: (camera.width / f).max(1),
        height: (camera.height / f).max(1),
        ..camera.clone()
    }
}

/// Writes one frame of `input` into `output`, undistorted through `lens` and box-averaged by
/// `f`; returns its new camera.
fn working_frame(
    input: &Path,
    output: &Path,
    camera: &Camera,
    lens: &Distortion,
    f: u32,
) -> Result<Camera, StageError> {
    let out_cam = scaled_camera(camera, f);
    let fmt = |e: formats::FormatError| e.for_input("views");
    let src = cameras::image_path(input, camera);
    let img = images::read_image(&src).map_err(fmt)?;
    if (img.width, img.height) != (camera.width, camera.height) {
        return Err(StageError::input(
            "views",
            &src,
            format!(
                "image is {} x {} but its camera says {} x {}",
                img.width, img.height, camera.width, camera.height
            ),
        ));
    }
    let write = |rel: &str, im: &ImageF32| -> Result<(), StageError> {
        let dst = output.join(rel);
        if let Some(parent) = dst.parent() {
            std::fs::create_dir_all(parent).map_err(|e| StageError::io(parent, e))?;
        }
        let im = if lens.is_pinhole() {
            im.box_downscaled(f)
        } else {
            undistorted(im, camera, lens).box_downscaled(f)
        };
        images::write_image(&dst, &im).map_err(fmt)
    };
    write(&out_cam.file_path, &img)?;
    // Masks are read by their first channel (cameras::read_view): resampled as one.
    let mask = cameras::mask_path(input, camera);
    if mask.is_file() {
        let m = images::read_png(&mask).map_err(fmt)?.first_channel();
        write(&cameras::mask_file_path(&out_cam.file_path), &m)?;
    }
    let fur = input.join(cameras::fur_mask_file_path(&camera.file_path));
    if fur.is_file() {
        let m = images::read_png(&fur).map_err(fmt)?.first_channel();
        write(&cameras::fur_mask_file_path(&out_cam.file_path), &m)?;
    }
    Ok(out_cam)
}

/// `D(2k) / D(k)` for `k = 1..=upto`, for the run log.
fn ratio_list(ratios: &[Option<f64>], upto: usize) -> String {
    ratios
        .iter()
        .take(upto)
        .enumerate()
        .map(|(i, r)| match r {
            Some(r) => format!("{r:.2} at {}", i + 1),
            None => format!("- at {}", i + 1),
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// Stage `working_views`.
pub struct WorkingViewsStage;

impl Stage for WorkingViewsStage {
    fn kind(&self) -> &'static str {
        "working_views"
    }
    fn version(&self) -> u32 {
        // 4: past a photo's border (a pincushion lens' corners) its border goes on.
        // 5: photos softer than their pixel are box-averaged by the lag they are smooth over.
        5
    }
    fn doc(&self) -> &'static str {
        "A capture's views as the stages work on them: photos taken through a distorting lens \
         (COLMAP's SIMPLE_RADIAL, OPENCV, fisheyes; nerfstudio's OPENCV) resampled onto pinhole \
         cameras, and every frame box-averaged by one integer factor so that the animal spans \
         about subject_px pixels (the median over the training views of the mask's bounding \
         box), or by the distance photos softer than their pixel are smooth over (the animal \
         keeping at least subject_px / 2), intrinsics scaled with it; a sharp pinhole capture \
         already near that size passes through byte for byte."
    }
    fn params(&self) -> Vec<ParamSpec> {
        WorkingViewsParams::specs()
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![PortSpec::dir(
            "views",
            "views directory (transforms.json or a COLMAP model, images, masks)",
        )]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::dir(
                "views",
                "the views as pinhole cameras at the working resolution",
            ),
            PortSpec::file(
                "metrics",
                "json",
                "the animal's extent before and after, the factor, the views undistorted",
            ),
        ]
    }
    fn validate(&self, params: &Params) -> Result<(), StageError> {
        WorkingViewsParams::from_params(params).map(|_| ())
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let p = WorkingViewsParams::from_params(ctx.params)?;
        let input = ctx.input("views")?;
        let output = ctx.output("views")?;
        let cameras::Capture { views: set, lenses } =
            cameras::read_capture(input).map_err(|e| e.for_input("views"))?;
        if set.train.is_empty() {
            return Err(cameras::no_training_views(input));
        }
        let undistorted_views = lenses.iter().filter(|l| !l.is_pinhole()).count();
        ctx.progress
            .message("measuring the animal in the training views");
        let wf = working_factor(input, &set.train, &p)?;
        let (f, extent) = (wf.factor, wf.extent);
        let files_copied = if f == 1 && undistorted_views == 0 {
            // The identity: every file as it is, copied as corrupt_views copies.
            let files = super::corrupt::list_files(input)?;
            for f in &files {
                super::corrupt::copy_file(&input.join(f), &output.join(f))?;
            }
            files.len()
        } else {
            let frames: Vec<&Camera> = set.train.iter().chain(&set.test).collect();
            ctx.progress.set_total(frames.len() as u64);
            let mut out = Vec::with_capacity(frames.len());
            for (cam, lens) in frames.into_iter().zip(&lenses) {
                ctx.progress.check_interrupted()?;
                ctx.progress
                    .message(&format!("working view {}", cam.file_path));
                out.push(working_frame(input, output, cam, lens, f)?);
                ctx.progress.advance(1);
            }
            let test = out.split_off(set.train.len());
            cameras::write_views(output, &CameraSet { train: out, test })
                .map_err(|e| e.for_input("views"))?;
            0
        };
        if wf.smooth_lag > wf.for_extent {
            ctx.progress.note(&format!(
                "the photos are smooth over {} px (inside the animal, the luma's mean squared \
                 difference at twice a lag over that at the lag: {}), softer than their pixel: \
                 {}",
                wf.smooth_lag,
                ratio_list(&wf.ratios, wf.smooth_lag as usize),
                if wf.factor >= wf.smooth_lag {
                    format!(
                        "box-averaged by {} rather than {}, so that the orientation maps' filters \
                         and every per-pixel rule meet the fur's texture at its own scale",
                        wf.factor, wf.for_extent
                    )
                } else {
                    format!(
                        "box-averaged by {} only, so that the animal keeps at least {} px; the \
                         orientation maps may show little of the fur's texture, and the \
                         widths and lengths read from the views may be long",
                        wf.factor,
                        p.subject_px / 2
                    )
                },
            ));
        }
        ctx.progress.note(&format!(
            "the animal spans {extent} px (median over {} training views): {}{}",
            set.train.len(),
            if f == 1 {
                "views kept at their size".to_string()
            } else {
                format!("views box-averaged by {f}, to about {} px", extent / f)
            },
            if undistorted_views > 0 {
                format!("; {undistorted_views} views undistorted onto pinhole cameras")
            } else {
                String::new()
            }
        ));
        formats::json::write_json(
            ctx.output("metrics")?,
            &json!({
                "subject_px": p.subject_px,
                "extent_px": extent,
                "factor": f,
                "factor_for_extent": wf.for_extent,
                "smooth_ratio": p.smooth_ratio,
                "smooth_lag_px": wf.smooth_lag,
                "smoothness_ratios": wf.ratios,
                "extent_px_after": extent / f,
                "training_views": set.train.len(),
                "test_views": set.test.len(),
                "files_copied": files_copied,
                "undistorted_views": undistorted_views,
            }),
        )?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::evaluation::evaluate::tests::{run_stage, run_stage_with};
    use crate::scenes::corrupt::tests::tree;
    use glam::{Mat4, Vec3};

    /// A views directory of `n` training frames and one held-out frame, `size` px square, a
    /// disc of radius `r` px in the middle (RGB photos, masks in `masks/`, COLMAP-style names).
    fn capture(dir: &Path, n: usize, size: u32, r: f32) -> CameraSet {
        let cam = |i: usize, split: &str| Camera {
            file_path: format!("images/{split}{i:03}.png"),
            c2w: Mat4::from_translation(Vec3::new(0.1 * i as f32, 0.0, 4.0)),
            fx: 2.0 * size as f32,
            fy: 2.0 * size as f32,
            cx: 0.5 * size as f32 + 0.25,
            cy: 0.5 * size as f32 - 0.75,
            width: size,
            height: size,
        };
        let set = CameraSet {
            train: (0..n).map(|i| cam(i, "t")).collect(),
            test: vec![cam(0, "h")],
        };
        for c in set.train.iter().chain(&set.test) {
            let mut rgb = ImageF32::new(size, size, 3);
            let mut mask = ImageF32::new(size, size, 1);
            for y in 0..size {
                for x in 0..size {
                    let (dx, dy) = (
                        x as f32 + 0.5 - 0.5 * size as f32,
                        y as f32 + 0.5 - 0.5 * size as f32,
                    );
                    let inside = (dx * dx + dy * dy).sqrt() < r;
                    mask.pixel_mut(x, y)[0] = inside as u8 as f32;
                    let v = if inside {
                        0.2 + 0.6 * (x % 2) as f32
                    } else {
                        0.9
                    };
                    rgb.pixel_mut(x, y).copy_from_slice(&[v, v, 0.5]);
                }
            }
            let png = &c.file_path;
            std::fs::create_dir_all(dir.join("images")).unwrap();
            images::write_png(dir.join(png), &rgb).unwrap();
            let stem = png.trim_start_matches("images/").trim_end_matches(".png");
            images::write_png(dir.join(format!("masks/{stem}.png")), &mask).unwrap();
        }
        cameras::write_views(dir, &set).unwrap();
        set
    }

    #[test]
    fn a_large_capture_is_box_averaged_and_its_cameras_scaled_with_it() {
        let dir = tempfile::tempdir().unwrap();
        let views = dir.path().join("views");
        let set = capture(&views, 5, 96, 37.0);
        let out = dir.path().join("out");
        // The disc spans 74 px: 74 / 18 rounds to a factor of 4.
        let outs = run_stage_with(
            &WorkingViewsStage,
            &[("subject_px", fure_stage_api::Value::Int(18))],
            &[("views", views.clone())],
            &out,
        )
        .unwrap();
        let m: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&outs["metrics"]).unwrap()).unwrap();
        assert_eq!(
            (m["extent_px"].as_u64(), m["factor"].as_u64()),
            (Some(74), Some(4))
        );
        let read = cameras::read_views(&outs["views"]).unwrap();
        assert_eq!((read.train.len(), read.test.len()), (5, 1));
        for (a, b) in set.train.iter().zip(&read.train) {
            assert_eq!((b.width, b.height), (24, 24));
            assert_eq!(b.file_path, a.file_path);
            // A world point lands on the same place of the image, in the new pixels.
            let p = Vec3::new(0.3, -0.2, 0.5);
            let (ua, _) = a.project(p);
            let (ub, _) = b.project(p);
            assert!((ub - ua / 4.0).length() < 1e-4, "{ua} / 4 vs {ub}");
            let v = cameras::read_view(&outs["views"], b).unwrap();
            let mask = v.mask.expect("the mask is written beside the photo");
            // The disc's area, in the new pixels, is the old area over 16.
            let area: f32 = mask.data.iter().sum();
            let disc = std::f32::consts::PI * (37.0f32 / 4.0).powi(2);
            assert!((area / disc - 1.0).abs() < 0.08, "{area} vs {disc}");
            // Box averages of the photo: a 4x4 block of alternating columns inside the disc.
            assert!(
                (v.rgb.pixel(12, 12)[0] - 0.5).abs() < 1e-2,
                "{:?}",
                v.rgb.pixel(12, 12)
            );
        }
    }

    #[test]
    fn a_capture_near_the_working_size_passes_through_byte_for_byte() {
        let dir = tempfile::tempdir().unwrap();
        let views = dir.path().join("views");
        capture(&views, 3, 64, 20.0);
        std::fs::write(views.join("notes.txt"), "kept").unwrap();
        let outs = run_stage(
            &WorkingViewsStage,
            &[("views", views.clone())],
            &dir.path().join("a"),
        )
        .unwrap();
        assert_eq!(tree(&outs["views"]), tree(&views));
        // subject_px = 0 keeps a large capture as it is too.
        let outs = run_stage_with(
            &WorkingViewsStage,
            &[("subject_px", fure_stage_api::Value::Int(0))],
            &[("views", views.clone())],
            &dir.path().join("b"),
        )
        .unwrap();
        assert_eq!(tree(&outs["views"]), tree(&views));
    }

    #[test]
    fn photos_through_a_distorting_lens_come_out_as_a_pinhole_sees_them() {
        let dir = tempfile::tempdir().unwrap();
        let views = dir.path().join("views");
        let set = capture(&views, 3, 64, 20.0);
        // The same frames through a barrel lens (nerfstudio's OPENCV, k1 = -0.25, focal length
        // 48 px): a disc of 0.5 (24 px) around the principal point seen by the pinhole lies at
        // r_d = 0.5 (1 - 0.25 * 0.25) in the photo.
        let (f, k1, r) = (48.0f64, -0.25, 0.5);
        for c in set.train.iter().chain(&set.test) {
            let mut mask = ImageF32::new(64, 64, 1);
            for y in 0..64 {
                for x in 0..64 {
                    let xd = (x as f64 + 0.5 - c.cx as f64) / f;
                    let yd = (y as f64 + 0.5 - c.cy as f64) / f;
                    let rd = (xd * xd + yd * yd).sqrt();
                    mask.pixel_mut(x, y)[0] = (rd < r * (1.0 + k1 * r * r)) as u8 as f32;
                }
            }
            let stem = c
                .file_path
                .trim_start_matches("images/")
                .trim_end_matches(".png");
            images::write_png(views.join(format!("masks/{stem}.png")), &mask).unwrap();
        }
        for file in ["transforms.json", "transforms_test.json"] {
            let path = views.join(file);
            let mut t: serde_json::Value =
                serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
            let top = t.as_object_mut().unwrap();
            top.remove("camera_angle_x");
            top.remove("camera_angle_y");
            top.insert("fl_x".into(), json!(f));
            top.insert("fl_y".into(), json!(f));
            top.insert("camera_model".into(), json!("OPENCV"));
            top.insert("k1".into(), json!(k1));
            std::fs::write(&path, serde_json::to_vec(&t).unwrap()).unwrap();
        }
        // Every other stage refuses the capture, naming this one.
        let e = cameras::read_views(&views).unwrap_err().to_string();
        assert!(e.contains("k1") && e.contains("working_views"), "{e}");
        let outs = run_stage(
            &WorkingViewsStage,
            &[("views", views.clone())],
            &dir.path().join("o"),
        )
        .unwrap();
        let m: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&outs["metrics"]).unwrap()).unwrap();
        assert_eq!(
            (m["factor"].as_u64(), m["undistorted_views"].as_u64()),
            (Some(1), Some(4))
        );
        let read = cameras::read_views(&outs["views"]).unwrap();
        assert_eq!((read.train.len(), read.test.len()), (3, 1));
        let pinhole_area = std::f64::consts::PI * (r * f).powi(2);
        for cam in read.train.iter().chain(&read.test) {
            assert_eq!((cam.fx as f64, cam.width), (f, 64));
            let mask = cameras::read_view(&outs["views"], cam)
                .unwrap()
                .mask
                .unwrap();
            let area: f32 = mask.data.iter().sum();
            // The photo's disc is 12 % smaller; the pinhole's is back to its area.
            assert!(
                (area as f64 / pinhole_area - 1.0).abs() < 0.02,
                "{}: {area} against {pinhole_area}",
                cam.file_path
            );
        }
    }

    #[test]
    fn exr_photos_stay_exr_with_their_values() {
        let dir = tempfile::tempdir().unwrap();
        let views = dir.path().join("views");
        let mut set = capture(&views, 2, 32, 10.0);
        // The photos as EXR, 2.5 (brighter than a PNG holds) inside the disc.
        for c in set.train.iter_mut().chain(set.test.iter_mut()) {
            let png = views.join(&c.file_path);
            let mut im = images::read_image(&png).unwrap();
            for v in &mut im.data {
                *v *= 5.0;
            }
            std::fs::remove_file(&png).unwrap();
            c.file_path = c.file_path.replace(".png", ".exr");
            images::write_exr(views.join(&c.file_path), &im).unwrap();
        }
        cameras::write_views(&views, &set).unwrap();
        let outs = run_stage_with(
            &WorkingViewsStage,
            &[("subject_px", fure_stage_api::Value::Int(10))],
            &[("views", views.clone())],
            &dir.path().join("o"),
        )
        .unwrap();
        let read = cameras::read_views(&outs["views"]).unwrap();
        let cam = &read.train[0];
        assert!(cam.file_path.ends_with(".exr"), "{}", cam.file_path);
        let v = cameras::read_view(&outs["views"], cam).unwrap();
        // Blocks of alternating columns 0.2 and 0.8, times 5, averaged: 2.5.
        let centre = v.rgb.pixel(cam.width / 2, cam.height / 2)[0];
        assert!((centre - 2.5).abs() < 1e-3, "{centre}");
    }

    #[test]
    fn a_photo_without_mask_or_alpha_is_an_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let views = dir.path().join("views");
        capture(&views, 2, 32, 10.0);
        std::fs::remove_dir_all(views.join("masks")).unwrap();
        let e = run_stage(
            &WorkingViewsStage,
            &[("views", views)],
            &dir.path().join("o"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("images/t000.png") && e.contains("no mask"),
            "{e}"
        );
    }

    /// `capture`'s frames with the disc's photo replaced by a texture on a grid of `cell` px
    /// (`data::sharpness`' test texture).
    fn textured_capture(dir: &Path, size: u32, r: f32, cell: u32) {
        let set = capture(dir, 3, size, r);
        for c in set.train.iter().chain(&set.test) {
            let mut rgb = ImageF32::new(size, size, 3);
            for y in 0..size {
                for x in 0..size {
                    let v = crate::data::sharpness::tests::texture_at(x, y, cell);
                    rgb.pixel_mut(x, y).copy_from_slice(&[v, 0.8 * v, 0.5 * v]);
                }
            }
            images::write_png(dir.join(&c.file_path), &rgb).unwrap();
        }
    }

    #[test]
    fn soft_photos_are_box_averaged_by_the_lag_they_are_smooth_over() {
        let dir = tempfile::tempdir().unwrap();
        let metrics = |cell: u32, name: &str| -> serde_json::Value {
            let views = dir.path().join(name);
            // A disc of 90 px across in 128 px frames; subject_px 60: a factor of 2 for the
            // extent, and soft photos may come down to 30 px (a factor of 3).
            textured_capture(&views, 128, 45.0, cell);
            let outs = run_stage_with(
                &WorkingViewsStage,
                &[("subject_px", fure_stage_api::Value::Int(60))],
                &[("views", views)],
                &dir.path().join(format!("out-{name}")),
            )
            .unwrap();
            serde_json::from_slice(&std::fs::read(&outs["metrics"]).unwrap()).unwrap()
        };
        // A texture value per pixel: sharp, the extent's factor alone.
        let sharp = metrics(1, "sharp");
        assert_eq!(sharp["smooth_lag_px"].as_u64(), Some(1), "{sharp}");
        assert_eq!(sharp["factor"].as_u64(), Some(2), "{sharp}");
        let r1 = sharp["smoothness_ratios"][0].as_f64().unwrap();
        assert!(r1 < 1.5, "independent pixels: D(2) about D(1), read {r1}");
        // The same texture on a 4 px grid (a photo upscaled 4x): smooth over a few pixels, so
        // box-averaged by 3 (the floor: the disc keeps 30 px).
        let soft = metrics(4, "soft");
        let lag = soft["smooth_lag_px"].as_u64().unwrap();
        assert!((2..=5).contains(&lag), "{soft}");
        assert_eq!(soft["factor_for_extent"].as_u64(), Some(2), "{soft}");
        assert_eq!(soft["factor"].as_u64(), Some(lag.min(3)), "{soft}");
        let r1 = soft["smoothness_ratios"][0].as_f64().unwrap();
        assert!(r1 > 3.0, "interpolated: D(2) near 4 D(1), read {r1}");
        // Off: the extent's factor.
        let views = dir.path().join("soft");
        let outs = run_stage_with(
            &WorkingViewsStage,
            &[
                ("subject_px", fure_stage_api::Value::Int(60)),
                ("smooth_ratio", fure_stage_api::Value::Float(0.0)),
            ],
            &[("views", views)],
            &dir.path().join("off"),
        )
        .unwrap();
        let off: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&outs["metrics"]).unwrap()).unwrap();
        assert_eq!(off["factor"].as_u64(), Some(2), "{off}");
    }
}
