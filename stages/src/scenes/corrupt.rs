//! The `corrupt_views` stage: controlled damage to a capture's TRAINING views, for stability sweeps.
//!
//! Input `views` is a views directory (see [`crate::formats::cameras`]: `transforms.json` or
//! `transforms_train.json` for the training frames, `transforms_test.json` / `transforms_val.json` for
//! the held-out ones, images, `<stem>_mask.png` masks and any other per-view files such as the
//! synthetic stage's `<stem>_fur.png` and `<stem>_depth.exr`). Output `views` is a directory of the
//! same layout with four independent corruptions applied to the training frames only:
//!
//! - `noise_sigma`: additive Gaussian noise N(0, sigma) on the RGB of every training image (values in
//!   [0, 1], clamped after adding, then re-quantised by the writer: 8 bits for PNG). When the image has
//!   an alpha channel the noise goes only on pixels with alpha > 0: a matted capture carries no
//!   observation where alpha is 0 (the learners composite the photo over black with its own alpha, so
//!   noise there would be multiplied away anyway, and the synthetic stage's own `noise_sigma` knob
//!   does the same). Images without alpha get noise everywhere. Alpha is never changed. A JPEG
//!   training image is rewritten as a PNG next to it (`<stem>.png`, `file_path` updated): we never
//!   write lossy files.
//! - `jitter_deg`: every training camera is rotated by EXACTLY `jitter_deg` degrees about a random
//!   axis (uniform on the sphere, seeded per original frame index). Choice: the whole pose ORBITS the
//!   object centre, `c2w' = T(o) R T(-o) c2w`: the camera's orientation changes by the angle asked
//!   and its centre moves by the matching arc around `o` (a chord of `2 |c - o| sin(theta / 2)` at
//!   most), so its distance to `o` is unchanged and `o` projects to the same pixel. This is what a
//!   structure-from-motion or turntable calibration error looks like (the object stays where the
//!   images see it; the error in pixels grows with the distance from the centre, about
//!   `f |p - o| theta / d`, ~1.7 px per degree at the animal's extremities at 256 px), rather than a
//!   rotation about the camera centre, which would shift the whole image by `f theta` (~6 px per
//!   degree) and no calibration would leave uncorrected. `o` is the point closest, in least
//!   squares, to the optical axes of all input training cameras (the synthetic rigs look exactly at
//!   the object centre; a real turntable or orbit capture approximately); fewer than two
//!   non-parallel axes is an error when jitter is asked for.
//! - `views`: keep that many training frames (0 = all), evenly spread by index: original indices
//!   `floor(i n / k)` for `i = 0..k` (36 -> 18 keeps every second, 9 every fourth, 6 every sixth);
//!   the synthetic rig lays its views on a Fibonacci spiral whose elevation rises with the index, so
//!   this keeps the elevation and azimuth coverage. The files of dropped frames (image, mask and
//!   every `<stem>_*` sibling) are not copied. Asking for more views than the capture has is an
//!   error; asking for exactly as many is the identity.
//! - `mask_morph_px`: binary training masks (first channel >= 0.5) eroded (< 0) or dilated (> 0) by
//!   a DISC of radius `|mask_morph_px|` pixels (the offsets with `dx^2 + dy^2 <= r^2`; the same
//!   element as the synthetic stage's `mask_dilate_px`); pixels outside the image count as
//!   background. Only object masks (`<stem>_mask.png`) are changed, not the fur masks
//!   (`<stem>_fur.png`): a bad matting threshold moves the silhouette, which is what the outer
//!   surface and L_sil consume. A training frame without a mask file but with an alpha channel gets
//!   its morphed alpha written as a new `<stem>_mask.png` (which readers prefer over alpha).
//!
//! Held-out frames, their camera file and their images pass through untouched, so evaluation stays
//! clean. Every file that no corruption changes is copied byte for byte, and the camera file is only
//! rewritten when a camera or a `file_path` changed: with every corruption off the output is
//! BYTE-IDENTICAL to the input (same names, same bytes), so the engine's directory hash is equal and
//! every downstream stage hits the cache entries of the uncorrupted pipeline.
//!
//! Determinism: one ChaCha8 stream per (corruption, original frame index), seeded from `seed`, so a
//! frame's noise and jitter do not depend on how many other frames are kept. `metrics.json` records
//! what was done (frames kept, the measured rotation angles, noise and mask-area statistics).

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use fure_stage_api::{ensure_finite, ParamSpec, Params, PortSpec, Stage, StageContext, StageError};
use glam::{DVec3, Mat4};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::json;

use crate::data::camera::Camera;
use crate::data::image::ImageF32;
use crate::formats::{self, cameras};

fure_stage_api::stage_params! {
    /// Settings of one corruption run: the `corrupt_views` stage's parameters.
    #[derive(PartialEq)]
    pub struct Corruption {
        /// std of additive Gaussian noise on training RGB in [0, 1] (clamped; alpha > 0 pixels only when the image has alpha)
        noise_sigma: f32 = float(0.0).range(0.0, 1.0),
        /// each training camera orbits the object centre by exactly this angle (degrees) about a random axis
        jitter_deg: f32 = float(0.0).range(0.0, 180.0),
        /// training views kept, evenly spread by index (0 = all)
        views: usize = int(0).min(0.0),
        /// erode (< 0) or dilate (> 0) the training masks by a disc of this radius (pixels)
        mask_morph_px: i64 = int(0).range(-64.0, 64.0),
        /// seed of the noise and jitter streams
        seed: u64 = int(0).min(0.0),
    }
}

impl Default for Corruption {
    /// No corruption at all (every parameter's default).
    fn default() -> Self {
        Self::defaults().expect("every corruption setting has a default")
    }
}

/// What [`corrupt_dir`] did, for `metrics.json`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CorruptionReport {
    pub training_views_in: usize,
    pub training_views_out: usize,
    pub test_views: usize,
    pub files_copied: usize,
    pub files_rewritten: usize,
    /// Measured rotation angle of every kept training camera (degrees).
    pub rotation_deg: Vec<f64>,
    /// Measured distance every kept camera centre moved (scene units).
    pub centre_shift: Vec<f64>,
    /// The orbit centre (when jitter was applied).
    pub pivot: Option<[f64; 3]>,
    /// Standard deviation of the written minus the original RGB, over the noised pixels.
    pub noise_std_measured: Option<f64>,
    /// Sum of corrupted mask areas over the sum of the original areas (kept frames).
    pub mask_area_ratio: Option<f64>,
}

/// Seeds of the independent random streams.
const STREAM_NOISE: u64 = 0x006e_6f69_7365;
const STREAM_JITTER: u64 = 0x6a69_7474_6572;

fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn stream(seed: u64, kind: u64, frame: usize) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(mix(mix(seed ^ kind).wrapping_add(frame as u64)))
}

/// Standard normal sample (Box-Muller).
fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.gen::<f64>().max(1e-300);
    let u2: f64 = rng.gen();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Original indices kept when `k` of `n` frames are asked for (`k = 0`: all).
pub fn kept_indices(n: usize, k: usize) -> Result<Vec<usize>, String> {
    if k == 0 || k == n {
        return Ok((0..n).collect());
    }
    if k > n {
        return Err(format!(
            "asks for {k} training views but the capture has only {n}"
        ));
    }
    Ok((0..k).map(|i| i * n / k).collect())
}

/// A uniformly random unit axis from `rng`.
fn random_axis(rng: &mut ChaCha8Rng) -> DVec3 {
    loop {
        let v = DVec3::new(gauss(rng), gauss(rng), gauss(rng));
        let l = v.length();
        if l > 1e-6 {
            return v / l;
        }
    }
}

/// `cam` orbited about `pivot` by `angle` radians about `axis`.
pub fn orbit(cam: &Camera, pivot: DVec3, axis: DVec3, angle: f64) -> Camera {
    let r = glam::DQuat::from_axis_angle(axis, angle);
    let m = cam.c2w.as_dmat4();
    let rot = glam::DMat4::from_translation(pivot)
        * glam::DMat4::from_quat(r)
        * glam::DMat4::from_translation(-pivot);
    let mut out = cam.clone();
    out.c2w = (rot * m).as_mat4();
    out
}

/// Rotation angle (radians) between the orientations of two camera-to-world matrices.
pub fn rotation_between(a: &Mat4, b: &Mat4) -> f64 {
    let ra = glam::DMat3::from_mat4(a.as_dmat4());
    let rb = glam::DMat3::from_mat4(b.as_dmat4());
    let q = glam::DQuat::from_mat3(&(ra.transpose() * rb)).normalize();
    2.0 * q.xyz().length().atan2(q.w.abs())
}

/// Binary mask of the first channel of `img` (>= 0.5), eroded (r < 0) or dilated (r > 0) by a disc
/// of radius |r|; outside the image is background.
pub fn morph_mask(img: &ImageF32, r: i64) -> ImageF32 {
    let (w, h) = (img.width as i64, img.height as i64);
    let c = img.channels.max(1) as usize;
    let on: Vec<bool> = (0..(w * h) as usize)
        .map(|i| img.data[i * c] >= 0.5)
        .collect();
    let rr = r.abs();
    let offsets: Vec<(i64, i64)> = (-rr..=rr)
        .flat_map(|dy| (-rr..=rr).map(move |dx| (dx, dy)))
        .filter(|(dx, dy)| dx * dx + dy * dy <= rr * rr)
        .collect();
    let at = |x: i64, y: i64| x >= 0 && y >= 0 && x < w && y < h && on[(y * w + x) as usize];
    let mut out = ImageF32::new(img.width, img.height, 1);
    for y in 0..h {
        for x in 0..w {
            let v = if r > 0 {
                offsets.iter().any(|(dx, dy)| at(x + dx, y + dy))
            } else if r < 0 {
                offsets.iter().all(|(dx, dy)| at(x + dx, y + dy))
            } else {
                on[(y * w + x) as usize]
            };
            out.data[(y * w + x) as usize] = if v { 1.0 } else { 0.0 };
        }
    }
    out
}

/// Adds N(0, sigma) to the RGB of `img` (alpha > 0 only when it has alpha), clamped to [0, 1].
/// Returns (sum of squared changes, pixels touched) of the in-memory values.
fn add_noise(img: &mut ImageF32, sigma: f64, rng: &mut ChaCha8Rng) -> (f64, u64) {
    let c = img.channels as usize;
    let (colour, alpha) = match c {
        1 => (1, None),
        2 => (1, Some(1)),
        3 => (3, None),
        _ => (3, Some(3)),
    };
    let mut sq = 0.0;
    let mut n = 0;
    for px in img.data.chunks_exact_mut(c) {
        if let Some(a) = alpha {
            if px[a] <= 0.0 {
                continue;
            }
        }
        for v in &mut px[..colour] {
            let x = (*v as f64 + sigma * gauss(rng)).clamp(0.0, 1.0) as f32;
            sq += ((x - *v) as f64).powi(2);
            *v = x;
        }
        n += 1;
    }
    (sq, n)
}

/// Every regular file under `dir`, as `/`-separated relative paths, sorted.
pub(crate) fn list_files(dir: &Path) -> Result<Vec<String>, StageError> {
    fn walk(root: &Path, rel: &Path, out: &mut Vec<String>) -> Result<(), StageError> {
        let here = root.join(rel);
        let rd = std::fs::read_dir(&here).map_err(|e| StageError::io(&here, e))?;
        for entry in rd {
            let entry = entry.map_err(|e| StageError::io(&here, e))?;
            let name = entry.file_name();
            let relp = rel.join(&name);
            let p = root.join(&relp);
            let meta = std::fs::metadata(&p).map_err(|e| StageError::io(&p, e))?;
            if meta.is_dir() {
                walk(root, &relp, out)?;
            } else if meta.is_file() {
                let s = relp.to_str().ok_or_else(|| {
                    StageError::input("views", &p, "file name is not valid UTF-8")
                })?;
                out.push(s.replace('\\', "/"));
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    walk(dir, Path::new(""), &mut out)?;
    out.sort();
    Ok(out)
}

/// Files of `files` that belong to a frame: its image and every `<stem>_*` sibling.
fn frame_files<'a>(files: &'a [String], file_path: &str) -> Vec<&'a String> {
    let stem = cameras::file_stem(file_path);
    let prefix = format!("{stem}_");
    files
        .iter()
        .filter(|f| f.as_str() == file_path || f.starts_with(&prefix))
        .collect()
}

pub(crate) fn copy_file(src: &Path, dst: &Path) -> Result<(), StageError> {
    if let Some(parent) = dst.parent() {
        std::fs::create_dir_all(parent).map_err(|e| StageError::io(parent, e))?;
    }
    std::fs::copy(src, dst).map_err(|e| StageError::io(src, e))?;
    Ok(())
}

fn fmt_err(e: formats::FormatError) -> StageError {
    e.for_input("views")
}

/// Applies `cfg` to the views directory `input`, writing `output` (which must exist, empty).
pub fn corrupt_dir(
    input: &Path,
    output: &Path,
    cfg: &Corruption,
) -> Result<CorruptionReport, StageError> {
    let views = SourceViews::read(input)?;
    let (train, test) = (&views.train, &views.test);
    let kept = kept_indices(train.len(), cfg.views).map_err(|m| StageError::param("views", m))?;
    let mut report = CorruptionReport {
        training_views_in: train.len(),
        training_views_out: kept.len(),
        test_views: test.len(),
        ..Default::default()
    };
    let roles = FileRoles::of(&views, &kept);

    // The new training cameras and the files rewritten for them.
    let mut edits = Rewrites {
        cams: kept.iter().map(|&i| train[i].clone()).collect(),
        images: BTreeMap::new(),
        replaced: BTreeSet::new(),
        cameras_changed: cfg.views != 0 && kept.len() != train.len(),
    };
    if cfg.jitter_deg > 0.0 {
        jitter_cameras(&views, &kept, cfg, &mut edits, &mut report)?;
    }
    if cfg.noise_sigma > 0.0 {
        add_image_noise(
            input,
            &kept,
            cfg,
            &roles.test_files,
            &mut edits,
            &mut report,
        )?;
    }
    if cfg.mask_morph_px != 0 {
        morph_masks(input, cfg, &roles.test_files, &mut edits, &mut report)?;
    }
    write_output(input, output, &views, &roles.dropped, &edits, &mut report)?;
    Ok(report)
}

/// What `corrupt_dir` reads of its input: the camera files and the list of files.
struct SourceViews {
    /// Name of the training camera file (`transforms.json` or `transforms_train.json`).
    train_name: &'static str,
    /// Path of the training camera file.
    train_file: std::path::PathBuf,
    /// The training frames.
    train: Vec<Camera>,
    /// The held-out frames (read only to protect their files and report their count).
    test: Vec<Camera>,
    /// Every file of the directory, relative with `/` separators, sorted.
    files: Vec<String>,
}

impl SourceViews {
    /// Reads the views directory `input`; fails without a training camera file or frames.
    fn read(input: &Path) -> Result<SourceViews, StageError> {
        let train_name = ["transforms.json", "transforms_train.json"]
            .into_iter()
            .find(|n| input.join(n).is_file())
            .ok_or_else(|| {
                StageError::input(
                    "views",
                    input,
                    "no camera file: expected transforms.json or transforms_train.json",
                )
            })?;
        let train_file = input.join(train_name);
        let train = cameras::read_transforms(&train_file).map_err(fmt_err)?;
        let test = cameras::read_views(input).map_err(fmt_err)?.test;
        if train.is_empty() {
            return Err(StageError::input(
                "views",
                &train_file,
                "lists no training frames",
            ));
        }
        let files = list_files(input)?;
        Ok(SourceViews {
            train_name,
            train_file,
            train,
            test,
            files,
        })
    }
}

/// The source files the corruption drops and those it must leave untouched.
struct FileRoles<'a> {
    /// Files of dropped training frames that no kept or held-out frame also owns.
    dropped: BTreeSet<&'a String>,
    /// Files of held-out frames: never rewritten, even if a training frame shares them.
    test_files: BTreeSet<&'a String>,
}

impl<'a> FileRoles<'a> {
    /// The roles of `views`' files when the training frames `kept` are kept.
    fn of(views: &'a SourceViews, kept: &[usize]) -> FileRoles<'a> {
        let files = &views.files;
        // Files that belong to held-out frames or kept training frames are protected from dropping.
        let mut protected: BTreeSet<&String> = BTreeSet::new();
        for c in &views.test {
            protected.extend(frame_files(files, &c.file_path));
        }
        for &i in kept {
            protected.extend(frame_files(files, &views.train[i].file_path));
        }
        let mut dropped: BTreeSet<&String> = BTreeSet::new();
        let kept_set: BTreeSet<usize> = kept.iter().copied().collect();
        for (i, c) in views.train.iter().enumerate() {
            if !kept_set.contains(&i) {
                dropped.extend(
                    frame_files(files, &c.file_path)
                        .into_iter()
                        .filter(|f| !protected.contains(f)),
                );
            }
        }
        let test_files: BTreeSet<&String> = views
            .test
            .iter()
            .flat_map(|c| frame_files(files, &c.file_path))
            .collect();
        FileRoles {
            dropped,
            test_files,
        }
    }
}

/// The new training cameras and the files rewritten for them.
struct Rewrites {
    /// The kept training cameras, as they will be written.
    cams: Vec<Camera>,
    /// Relative path -> image written there instead of a copy.
    images: BTreeMap<String, ImageF32>,
    /// Lossy source images replaced by a PNG next to them (not copied).
    replaced: BTreeSet<String>,
    /// Whether the training camera file must be rewritten.
    cameras_changed: bool,
}

/// Orbits every kept camera by `cfg.jitter_deg` about a random axis through the centre of the
/// training cameras' optical axes, recording the pivot, rotation angles and centre shifts.
fn jitter_cameras(
    views: &SourceViews,
    kept: &[usize],
    cfg: &Corruption,
    edits: &mut Rewrites,
    report: &mut CorruptionReport,
) -> Result<(), StageError> {
    let pivot = crate::data::camera::axes_centre(&views.train).ok_or_else(|| {
        StageError::input(
            "views",
            &views.train_file,
            format!(
                "cannot find the object centre for the jitter orbit: the {} training camera \
                 axes do not meet (fewer than two, or all parallel)",
                views.train.len()
            ),
        )
    })?;
    report.pivot = Some(pivot.to_array());
    let angle = (cfg.jitter_deg as f64).to_radians();
    for (cam, &i) in edits.cams.iter_mut().zip(kept) {
        let mut rng = stream(cfg.seed, STREAM_JITTER, i);
        let axis = random_axis(&mut rng);
        let new = orbit(cam, pivot, axis, angle);
        ensure_finite("jittered camera", new.c2w.to_cols_array())?;
        report
            .rotation_deg
            .push(rotation_between(&cam.c2w, &new.c2w).to_degrees());
        report
            .centre_shift
            .push((new.center() - cam.center()).length() as f64);
        *cam = new;
    }
    edits.cameras_changed = true;
    Ok(())
}

/// Adds `cfg.noise_sigma` Gaussian noise to every kept training image not shared with a held-out
/// frame (lossy sources become PNGs), recording the measured noise level.
fn add_image_noise(
    input: &Path,
    kept: &[usize],
    cfg: &Corruption,
    test_files: &BTreeSet<&String>,
    edits: &mut Rewrites,
    report: &mut CorruptionReport,
) -> Result<(), StageError> {
    let (mut sq, mut n) = (0.0, 0u64);
    for (cam, &i) in edits.cams.iter_mut().zip(kept) {
        if test_files.contains(&cam.file_path) {
            continue;
        }
        let src = cameras::image_path(input, cam);
        let mut img = formats::images::read_image(&src).map_err(fmt_err)?;
        let mut rng = stream(cfg.seed, STREAM_NOISE, i);
        let (s, k) = add_noise(&mut img, cfg.noise_sigma as f64, &mut rng);
        ensure_finite("noisy image", img.data.iter().copied())?;
        sq += s;
        n += k * if img.channels >= 3 { 3 } else { 1 };
        let ext = formats_ext(&cam.file_path);
        if ext == "png" || ext == "exr" {
            edits.images.insert(cam.file_path.clone(), img);
        } else {
            // Lossy source: write a PNG next to it and point the camera there.
            let new_path = format!("{}.png", cameras::file_stem(&cam.file_path));
            edits.replaced.insert(cam.file_path.clone());
            edits.images.insert(new_path.clone(), img);
            cam.file_path = new_path;
            edits.cameras_changed = true;
        }
    }
    if n > 0 {
        report.noise_std_measured = Some((sq / n as f64).sqrt());
    }
    Ok(())
}

/// Erodes or dilates the object mask (or, without one, the alpha) of every kept training frame
/// by `cfg.mask_morph_px`, recording the ratio of mask areas after and before.
fn morph_masks(
    input: &Path,
    cfg: &Corruption,
    test_files: &BTreeSet<&String>,
    edits: &mut Rewrites,
    report: &mut CorruptionReport,
) -> Result<(), StageError> {
    let (mut before, mut after) = (0.0f64, 0.0f64);
    for cam in &edits.cams {
        let mpath = cameras::mask_path(input, cam);
        let mask_rel = cameras::mask_file_path(&cam.file_path);
        if test_files.contains(&mask_rel) {
            continue;
        }
        let src = if mpath.is_file() {
            let m = formats::images::read_png(&mpath).map_err(fmt_err)?;
            m.first_channel()
        } else {
            // Alpha as the mask, when there is one (a noisy rewrite keeps alpha unchanged).
            let img = match edits.images.get(&cam.file_path) {
                Some(img) => img.clone(),
                None => {
                    formats::images::read_image(cameras::image_path(input, cam)).map_err(fmt_err)?
                }
            };
            match img.channels {
                2 | 4 => img.channel(img.channels as usize - 1),
                _ => continue,
            }
        };
        let out = morph_mask(&src, cfg.mask_morph_px);
        before += src.data.iter().filter(|v| **v >= 0.5).count() as f64;
        after += out.data.iter().sum::<f32>() as f64;
        edits.images.insert(mask_rel, out);
    }
    if before > 0.0 {
        report.mask_area_ratio = Some(after / before);
    }
    Ok(())
}

/// Writes `output`: copies of every file neither dropped nor rewritten, the rewritten images and,
/// if a camera changed, the new training camera file.
fn write_output(
    input: &Path,
    output: &Path,
    views: &SourceViews,
    dropped: &BTreeSet<&String>,
    edits: &Rewrites,
    report: &mut CorruptionReport,
) -> Result<(), StageError> {
    let train_name = views.train_name;
    for f in &views.files {
        if dropped.contains(f) || edits.images.contains_key(f) || edits.replaced.contains(f) {
            continue;
        }
        if f == train_name && edits.cameras_changed {
            continue;
        }
        copy_file(&input.join(f), &output.join(f))?;
        report.files_copied += 1;
    }
    for (rel, img) in &edits.images {
        let dst = output.join(rel);
        if let Some(parent) = dst.parent() {
            std::fs::create_dir_all(parent).map_err(|e| StageError::io(parent, e))?;
        }
        formats::images::write_image(&dst, img)?;
        report.files_rewritten += 1;
    }
    if edits.cameras_changed {
        cameras::write_transforms(output.join(train_name), &edits.cams)?;
        report.files_rewritten += 1;
    }
    Ok(())
}

fn formats_ext(p: &str) -> String {
    Path::new(p)
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default()
}

/// Stage `corrupt_views`.
pub struct CorruptViewsStage;

impl Stage for CorruptViewsStage {
    fn kind(&self) -> &'static str {
        "corrupt_views"
    }
    fn version(&self) -> u32 {
        1
    }
    fn doc(&self) -> &'static str {
        "Corrupts the training views of a views directory for stability sweeps: Gaussian image noise, \
         camera rotation jitter (an orbit about the object centre by exactly jitter_deg), fewer views \
         (evenly spread by index) and mask erosion/dilation (disc). Held-out views pass through \
         untouched; with every corruption off the output is byte-identical to the input."
    }
    fn params(&self) -> Vec<ParamSpec> {
        Corruption::specs()
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![PortSpec::dir(
            "views",
            "views directory (transforms.json, transforms_test.json, images, masks)",
        )]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::dir(
                "views",
                "the views directory with corrupted training frames",
            ),
            PortSpec::file(
                "metrics",
                "json",
                "what was done: frames kept, rotation angles, noise and mask-area statistics",
            ),
        ]
    }
    fn validate(&self, params: &Params) -> Result<(), StageError> {
        Corruption::from_params(params).map(|_| ())
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let cfg = Corruption::from_params(ctx.params)?;
        let input = ctx.input("views")?;
        let output = ctx.output("views")?;
        ctx.progress.message("corrupting training views");
        let r = corrupt_dir(input, output, &cfg)?;
        let mean = |v: &[f64]| {
            if v.is_empty() {
                None
            } else {
                Some(v.iter().sum::<f64>() / v.len() as f64)
            }
        };
        let max = |v: &[f64]| {
            v.iter()
                .copied()
                .fold(None, |m: Option<f64>, x| Some(m.map_or(x, |m| m.max(x))))
        };
        ctx.progress.note(&format!(
            "{} of {} training views kept, {} files copied, {} rewritten",
            r.training_views_out, r.training_views_in, r.files_copied, r.files_rewritten
        ));
        let metrics = json!({
            "training_views_in": r.training_views_in,
            "training_views_out": r.training_views_out,
            "test_views": r.test_views,
            "files_copied": r.files_copied,
            "files_rewritten": r.files_rewritten,
            "noise_sigma": cfg.noise_sigma,
            "noise_std_measured": r.noise_std_measured,
            "jitter_deg": cfg.jitter_deg,
            "rotation_deg_mean": mean(&r.rotation_deg),
            "rotation_deg_max": max(&r.rotation_deg),
            "centre_shift_mean": mean(&r.centre_shift),
            "pivot": r.pivot,
            "mask_morph_px": cfg.mask_morph_px,
            "mask_area_ratio": r.mask_area_ratio,
        });
        let finite = [
            r.noise_std_measured,
            mean(&r.rotation_deg),
            mean(&r.centre_shift),
            r.mask_area_ratio,
        ];
        ensure_finite(
            "corruption metrics",
            finite.iter().flatten().map(|x| *x as f32),
        )?;
        formats::json::write_json(ctx.output("metrics")?, &metrics)?;
        Ok(())
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use glam::Vec3;

    /// A camera at `eye` looking at `target` (OpenGL axes: -z forward, +y up).
    fn look(eye: Vec3, target: Vec3, i: usize, dir: &str) -> Camera {
        let c2w = Mat4::look_at_rh(eye, target, Vec3::Y).inverse();
        Camera {
            file_path: format!("{dir}/{i:03}.png"),
            c2w,
            fx: 20.0,
            fy: 20.0,
            cx: 12.0,
            cy: 12.0,
            width: 24,
            height: 24,
        }
    }

    const PIVOT: Vec3 = Vec3::new(0.1, 0.2, -0.15);

    /// A small capture like the synthetic stage's: `n` training and 2 held-out views of 24 x 24 px,
    /// RGBA images (mid grey inside a 12 x 12 square with alpha 1, alpha 0 outside), masks, fur
    /// masks and depth EXRs, all cameras looking at `PIVOT`.
    fn capture(dir: &Path, n: usize) -> crate::data::camera::CameraSet {
        let mk = |i: usize, k: usize, el: f32, d: &str| {
            let az = i as f32 * std::f32::consts::TAU / k as f32;
            let eye = PIVOT + 3.0 * Vec3::new(el.cos() * az.cos(), el.sin(), el.cos() * az.sin());
            look(eye, PIVOT, i, d)
        };
        let set = crate::data::camera::CameraSet {
            train: (0..n)
                .map(|i| mk(i, n, -0.4 + 0.9 * i as f32 / n as f32, "train"))
                .collect(),
            test: (0..2).map(|i| mk(i, 2, 0.2, "test")).collect(),
        };
        cameras::write_views(dir, &set).unwrap();
        for (k, c) in set.train.iter().chain(&set.test).enumerate() {
            let mut img = ImageF32::new(24, 24, 4);
            let mut mask = ImageF32::new(24, 24, 1);
            for y in 0..24 {
                for x in 0..24 {
                    let inside = (6..18).contains(&x) && (6..18).contains(&y);
                    let px = img.pixel_mut(x, y);
                    px[0] = 0.5;
                    px[1] = 0.25 + 0.01 * k as f32;
                    px[2] = 0.75;
                    px[3] = if inside { 1.0 } else { 0.0 };
                    mask.data[(y * 24 + x) as usize] = if inside { 1.0 } else { 0.0 };
                }
            }
            let stem = cameras::file_stem(&c.file_path).to_string();
            formats::images::write_png(dir.join(&c.file_path), &img).unwrap();
            formats::images::write_png(dir.join(format!("{stem}_mask.png")), &mask).unwrap();
            formats::images::write_png(dir.join(format!("{stem}_fur.png")), &mask).unwrap();
            formats::images::write_exr(dir.join(format!("{stem}_depth.exr")), &mask).unwrap();
        }
        set
    }

    /// Every file under `dir`: relative path -> bytes.
    pub(crate) fn tree(dir: &Path) -> BTreeMap<String, Vec<u8>> {
        list_files(dir)
            .unwrap()
            .into_iter()
            .map(|f| {
                let b = std::fs::read(dir.join(&f)).unwrap();
                (f, b)
            })
            .collect()
    }

    fn run(cfg: &Corruption) -> (tempfile::TempDir, tempfile::TempDir, CorruptionReport) {
        let a = tempfile::tempdir().unwrap();
        let b = tempfile::tempdir().unwrap();
        capture(a.path(), 12);
        let r = corrupt_dir(a.path(), b.path(), cfg).unwrap();
        (a, b, r)
    }

    #[test]
    fn all_off_is_byte_identical() {
        for views in [0, 12] {
            let cfg = Corruption {
                views,
                seed: 7,
                ..Default::default()
            };
            let (a, b, r) = run(&cfg);
            let (ta, tb) = (tree(a.path()), tree(b.path()));
            assert!(ta.len() > 50, "{} files", ta.len());
            assert_eq!(ta, tb, "views = {views}");
            assert_eq!(r.files_rewritten, 0);
        }
    }

    #[test]
    fn test_frames_and_untouched_files_pass_through() {
        let cfg = Corruption {
            noise_sigma: 0.05,
            jitter_deg: 1.0,
            views: 6,
            mask_morph_px: -2,
            seed: 3,
        };
        let (a, b, _) = run(&cfg);
        let (ta, tb) = (tree(a.path()), tree(b.path()));
        assert_eq!(ta["transforms_test.json"], tb["transforms_test.json"]);
        for (f, bytes) in &ta {
            if f.starts_with("test/") {
                assert_eq!(Some(bytes), tb.get(f), "{f}");
            }
        }
        // Kept training frames: fur masks and depth unchanged; image, mask and cameras changed.
        assert_eq!(ta["train/002_fur.png"], tb["train/002_fur.png"]);
        assert_eq!(ta["train/002_depth.exr"], tb["train/002_depth.exr"]);
        assert_ne!(ta["train/002.png"], tb["train/002.png"]);
        assert_ne!(ta["train/002_mask.png"], tb["train/002_mask.png"]);
        assert_ne!(ta["transforms.json"], tb["transforms.json"]);
        let set = cameras::read_views(b.path()).unwrap();
        assert_eq!(set.test, cameras::read_views(a.path()).unwrap().test);
    }

    #[test]
    fn view_count_and_spread() {
        assert_eq!(
            kept_indices(36, 18).unwrap(),
            (0..18).map(|i| 2 * i).collect::<Vec<_>>()
        );
        assert_eq!(
            kept_indices(36, 9).unwrap(),
            (0..9).map(|i| 4 * i).collect::<Vec<_>>()
        );
        assert_eq!(
            kept_indices(36, 6).unwrap(),
            (0..6).map(|i| 6 * i).collect::<Vec<_>>()
        );
        let seven = kept_indices(36, 7).unwrap();
        assert_eq!(seven.len(), 7);
        let gaps: Vec<usize> = seven.windows(2).map(|w| w[1] - w[0]).collect();
        assert!(gaps.iter().all(|g| (5..=6).contains(g)), "{gaps:?}");
        assert_eq!(kept_indices(5, 0).unwrap().len(), 5);
        assert!(kept_indices(5, 6).unwrap_err().contains("only 5"));

        let cfg = Corruption {
            views: 4,
            ..Default::default()
        };
        let (a, b, r) = run(&cfg);
        assert_eq!((r.training_views_in, r.training_views_out), (12, 4));
        let orig = cameras::read_views(a.path()).unwrap();
        let set = cameras::read_views(b.path()).unwrap();
        let want: Vec<Camera> = [0, 3, 6, 9]
            .iter()
            .map(|&i| orig.train[i].clone())
            .collect();
        assert_eq!(set.train, want);
        // Dropped frames' files are gone, kept ones are byte copies.
        let (ta, tb) = (tree(a.path()), tree(b.path()));
        assert!(!tb.contains_key("train/001.png") && !tb.contains_key("train/001_mask.png"));
        assert!(!tb.contains_key("train/001_depth.exr"));
        assert_eq!(ta["train/003.png"], tb["train/003.png"]);
        assert_eq!(tb.len(), ta.len() - 8 * 4);
        // Too many views: a parameter error.
        let c = tempfile::tempdir().unwrap();
        let e = corrupt_dir(
            a.path(),
            c.path(),
            &Corruption {
                views: 13,
                ..Default::default()
            },
        )
        .unwrap_err();
        assert!(matches!(e, StageError::Param { .. }), "{e}");
    }

    #[test]
    fn noise_statistics() {
        let cfg = Corruption {
            noise_sigma: 0.05,
            ..Default::default()
        };
        let (a, b, r) = run(&cfg);
        let set = cameras::read_views(a.path()).unwrap();
        let (mut d, mut outside_changed) = (Vec::new(), 0);
        for c in &set.train {
            let x = formats::images::read_png(a.path().join(&c.file_path)).unwrap();
            let y = formats::images::read_png(b.path().join(&c.file_path)).unwrap();
            for (px, py) in x.data.chunks(4).zip(y.data.chunks(4)) {
                assert_eq!(px[3], py[3], "alpha is never changed");
                if px[3] > 0.0 {
                    d.extend((0..3).map(|k| (py[k] - px[k]) as f64));
                } else if px[..3] != py[..3] {
                    outside_changed += 1;
                }
            }
        }
        assert_eq!(outside_changed, 0, "no noise where alpha = 0");
        // 12 views x 144 pixels x 3 channels; values far from 0 and 1, so clamping is rare.
        let n = d.len() as f64;
        assert_eq!(d.len(), 12 * 144 * 3);
        let mean = d.iter().sum::<f64>() / n;
        let std = (d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
        assert!(mean.abs() < 3.0 * 0.05 / n.sqrt() + 0.002, "mean {mean}");
        assert!((std - 0.05).abs() < 0.003, "std {std}");
        let m = r.noise_std_measured.unwrap();
        assert!((m - 0.05).abs() < 0.003, "{m}");
        // Same seed, same bytes; another seed, other noise.
        let (_, b2, _) = run(&cfg);
        assert_eq!(tree(b.path()), tree(b2.path()));
        let (_, b3, _) = run(&Corruption { seed: 1, ..cfg });
        assert_ne!(
            tree(b.path())["train/000.png"],
            tree(b3.path())["train/000.png"]
        );
    }

    #[test]
    fn jitter_angle_is_exact_and_orbits_the_centre() {
        for deg in [0.5f32, 2.0, 10.0] {
            let cfg = Corruption {
                jitter_deg: deg,
                seed: 11,
                ..Default::default()
            };
            let (a, b, r) = run(&cfg);
            let pivot = Vec3::from_array(r.pivot.unwrap().map(|x| x as f32));
            assert!((pivot - PIVOT).length() < 1e-4, "{pivot}");
            let orig = cameras::read_views(a.path()).unwrap();
            let new = cameras::read_views(b.path()).unwrap();
            assert_eq!(orig.train.len(), new.train.len());
            let mut axes = Vec::new();
            for (o, n) in orig.train.iter().zip(&new.train) {
                let ang = rotation_between(&o.c2w, &n.c2w).to_degrees();
                assert!((ang - deg as f64).abs() < 2e-3, "{ang} vs {deg}");
                // The centre keeps its distance to the pivot and the pivot its pixel.
                let (d0, d1) = ((o.center() - PIVOT).length(), (n.center() - PIVOT).length());
                assert!((d0 - d1).abs() < 1e-4);
                let (u0, _) = o.project(PIVOT);
                let (u1, _) = n.project(PIVOT);
                assert!((u0 - u1).length() < 1e-3, "{u0} {u1}");
                // Another point moves.
                let p = PIVOT + Vec3::new(0.5, 0.3, -0.4);
                assert!((o.project(p).0 - n.project(p).0).length() > 1e-3);
                let q = glam::DQuat::from_mat3(
                    &(glam::DMat3::from_mat4(o.c2w.as_dmat4()).transpose()
                        * glam::DMat3::from_mat4(n.c2w.as_dmat4())),
                );
                axes.push(q.xyz().normalize());
            }
            // Random axes: not all the same.
            assert!(axes.windows(2).any(|w| w[0].dot(w[1]).abs() < 0.9));
            assert!(r.rotation_deg.iter().all(|a| (a - deg as f64).abs() < 2e-3));
        }
    }

    #[test]
    fn erosion_and_dilation_on_a_synthetic_mask() {
        // A 9 x 9 square at (10..19) in a 30 x 30 image.
        let mut m = ImageF32::new(30, 30, 1);
        for y in 10..19 {
            for x in 10..19 {
                m.data[y * 30 + x] = 1.0;
            }
        }
        let area = |i: &ImageF32| i.data.iter().filter(|v| **v >= 0.5).count();
        let at = |i: &ImageF32, x: usize, y: usize| i.data[y * 30 + x] >= 0.5;
        assert_eq!(morph_mask(&m, 0).data, m.data);
        // Erosion by a disc of radius 2: a 5 x 5 square remains.
        let e = morph_mask(&m, -2);
        assert_eq!(area(&e), 25);
        assert!(at(&e, 12, 12) && !at(&e, 11, 12) && at(&e, 16, 16) && !at(&e, 17, 16));
        // Dilation by a disc of radius 2: 13 x 13 minus the four corners the disc misses
        // (offsets (2, 2), (2, 1), (1, 2) are outside the disc: 3 pixels per corner).
        let d = morph_mask(&m, 2);
        assert_eq!(area(&d), 13 * 13 - 4 * 3);
        assert!(at(&d, 8, 14) && !at(&d, 7, 14) && at(&d, 9, 9) && !at(&d, 8, 8));
        // Radius 1 dilation is the 4-neighbourhood (a plus): 11 x 11 minus 4 corners.
        assert_eq!(area(&morph_mask(&m, 1)), 121 - 4);
        // The border counts as background.
        let full = ImageF32 {
            width: 30,
            height: 30,
            channels: 1,
            data: vec![1.0; 900],
        };
        assert_eq!(area(&morph_mask(&full, -1)), 28 * 28);

        // Through the stage: masks of kept training views shrink, 12 x 12 -> 8 x 8.
        let (_, b, r) = run(&Corruption {
            mask_morph_px: -2,
            ..Default::default()
        });
        let mk = formats::images::read_png(b.path().join("train/000_mask.png")).unwrap();
        assert_eq!(mk.data.iter().filter(|v| **v >= 0.5).count(), 64);
        assert!((r.mask_area_ratio.unwrap() - 64.0 / 144.0).abs() < 1e-9);
    }

    #[test]
    fn parameters_are_validated() {
        let stage = CorruptViewsStage;
        let mut p = Params::default();
        for s in stage.params() {
            p.0.insert(s.name.to_string(), s.default.clone().unwrap());
        }
        assert!(stage.validate(&p).is_ok());
        for (name, v) in [
            ("noise_sigma", fure_stage_api::Value::Float(-0.1)),
            ("jitter_deg", fure_stage_api::Value::Float(f64::NAN)),
            ("views", fure_stage_api::Value::Int(-1)),
            ("seed", fure_stage_api::Value::Int(-3)),
        ] {
            let mut q = p.clone();
            q.0.insert(name.to_string(), v);
            let e = stage.validate(&q).unwrap_err();
            assert!(e.to_string().contains(name), "{e}");
        }
    }

    #[test]
    fn bad_input_names_the_file() {
        let a = tempfile::tempdir().unwrap();
        let b = tempfile::tempdir().unwrap();
        let e = corrupt_dir(a.path(), b.path(), &Corruption::default()).unwrap_err();
        assert!(e.to_string().contains("transforms.json"), "{e}");
        capture(a.path(), 3);
        std::fs::write(a.path().join("train/001.png"), b"\x89PNG truncated").unwrap();
        let e = corrupt_dir(
            a.path(),
            b.path(),
            &Corruption {
                noise_sigma: 0.1,
                ..Default::default()
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("001.png"), "{e}");
        // Jitter with a single camera: no centre to orbit.
        let c = tempfile::tempdir().unwrap();
        let d = tempfile::tempdir().unwrap();
        capture(c.path(), 1);
        let e = corrupt_dir(
            c.path(),
            d.path(),
            &Corruption {
                jitter_deg: 1.0,
                ..Default::default()
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("object centre"), "{e}");
    }
}
