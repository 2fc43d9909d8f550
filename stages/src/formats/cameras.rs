//! Camera sets in the NeRF / instant-ngp / NeuS2 `transforms.json` convention, or a COLMAP model.
//!
//! A *views directory* holds the cameras and the images they saw, in one of two layouts, read
//! by [`read_views`], the one function every stage reads views through:
//!
//! - NeRF-style: the `transforms*.json` files below;
//! - COLMAP: no `transforms*.json`, a sparse model in `sparse/0/` or `sparse/` (`cameras` and
//!   `images`, `.bin` or `.txt`), the photos under `images/`, optional masks under `masks/`; every
//!   8th image (sorted by name, from the first) is held out. See [`super::colmap`].
//!
//! The NeRF-style files:
//!
//! - training frames: `transforms.json` (instant-ngp, NeuS2, our own writer) or, when that file is
//!   absent, `transforms_train.json` (Blender NeRF synthetic). When both exist `transforms.json` wins:
//!   it is the file our writer produces and the one instant-ngp reads.
//! - held-out frames: `transforms_test.json`, or `transforms_val.json` when there is no test file
//!   (Blender NeRF synthetic ships both; test is the held-out set by convention). Neither file means
//!   no held-out views.
//!
//! Each file is a JSON object with a `frames` array. Per frame: `file_path` (relative to the
//! directory) and `transform_matrix`, the camera-to-world matrix as rows, OpenGL camera axes (the
//! camera looks down -z, +y up), 4x4 or 3x4. Intrinsics can sit at the top level (shared) or in a
//! frame (per-frame values win), in any of these forms, first match wins at each level:
//!
//! - `fl_x`, `fl_y`, `cx`, `cy` in pixels (instant-ngp, nerfstudio); `fl_y` defaults to `fl_x`;
//! - `intrinsic_matrix` (NeuS2): a 3x3 or 4x4 K as rows, `fx = K[0][0]`, `fy = K[1][1]`,
//!   `cx = K[0][2]`, `cy = K[1][2]`;
//! - `camera_angle_x` (full horizontal field of view, radians; `fx = 0.5 w / tan(angle_x / 2)`) with
//!   optional `camera_angle_y` for `fy`; without it `fy = fx` (square pixels, as instant-ngp does).
//!
//! The principal point defaults to the image centre `(w / 2, h / 2)`, which in our pixel convention
//! (pixel centres at half-integers, see [`Camera`]) is exactly the middle of the image. `w` and `h`
//! come from the frame, then the file, then the image header (PNG, EXR or JPEG) when missing.
//!
//! nerfstudio's lens (`camera_model` and `k1 k2 k3 k4 p1 p2`, at either level; a frame that names
//! any of them has its own lens, not merged with the file's) is read as a [`Distortion`]: `OPENCV` (or no model) radial-tangential, `OPENCV_FISHEYE`
//! the equidistant fisheye; other models are an error naming the field. [`read_views`], which
//! every stage but one reads views through, takes a lens with every coefficient zero for a pinhole
//! and refuses any other a frame uses (the file's lens only where a frame names none of its own),
//! naming the field and what to do; [`read_capture`] keeps the lenses for
//! the `working_views` stage, which undistorts the photos. Other extra keys
//! (`aabb_scale`, `sharpness`, `scale`, `offset`, `colmap_im_id`, ...)
//! are ignored: instant-ngp's `scale`/`offset` only move its own training box, so the cameras stay
//! in the file's world frame.
//!
//! `file_path` must lie inside the directory (relative, no `..`): the directory's hash is the
//! views' cache key, and stages name per-view outputs after it. It is normalised when read:
//! backslashes become `/`, a leading `./` is dropped, and a
//! path without an image extension gets one (`./train/r_0` -> `train/r_0.png`): the first of `.png`,
//! `.jpg`, `.jpeg`, `.exr` (any case) that exists next to it, `.png` when none does.
//! Foreground masks (PNG, white = object; the first channel is read) are looked for, in this
//! order ([`mask_path`]): `<stem>_mask.png` next to the image; `masks/<stem>.png` and
//! `masks/<name>.png` (COLMAP's own naming, e.g. `masks/0001.jpg.png`), the image's path taken
//! relative to `images/` when it lies there (`images/a/0001.jpg` -> `masks/a/0001.png`). Without a
//! mask file the image's alpha channel is the mask ([`read_view`]); an RGB image with neither is
//! an error wherever a mask is needed ([`missing_mask`]).
//!
//! Written `file_path`s keep their extension, as instant-ngp, nerfstudio and NeuS2 expect (the
//! original NeRF code's Blender loader, which appends `.png` itself, would not read them).
//!
//! Writing puts intrinsics at the top level when every camera of a file shares them (and then also
//! `camera_angle_x`/`camera_angle_y`, which Blender-NeRF-style loaders require), otherwise in every
//! frame. Both `transforms.json` and `transforms_test.json` are always written (an empty `frames`
//! list for no held-out views), so a directory we wrote reads back to the same [`CameraSet`].

use std::path::{Path, PathBuf};

use glam::{Mat4, Vec4};
use serde::Serialize;
use serde_json::{Map, Value};

use super::colmap::{Lenses, UNDISTORT_HINT};
use super::json::{from_slice, to_pretty_bytes};
use super::{check_finite, read_bytes, write_bytes, FormatError, Position};
use crate::data::camera::{Camera, CameraSet};
use crate::data::image::ImageF32;
use crate::data::lens::Distortion;

// The image extensions, probed in this order for extension-less `file_path`s.
use super::images::IMAGE_EXTENSIONS;

/// [`read_views`] for stages that fit to the training views: a capture without
/// training frames is an error naming the `views` input.
pub fn read_training_views(dir: &Path) -> Result<CameraSet, fure_stage_api::StageError> {
    let set = read_views(dir)?;
    if set.train.is_empty() {
        return Err(no_training_views(dir));
    }
    Ok(set)
}

/// The error for a views directory `dir` that lists no training frame, naming the `views` input.
pub fn no_training_views(dir: &Path) -> fure_stage_api::StageError {
    let what =
        if super::colmap::find_sparse(dir).is_some() && !dir.join("transforms.json").is_file() {
            "the COLMAP model lists no images"
        } else {
            "transforms.json lists no training frames"
        };
    fure_stage_api::StageError::input("views", dir, what)
}

/// Reads a views directory (see the module doc for which files count) as pinhole cameras: a
/// camera whose lens distorts is an error naming it ([`read_capture`] keeps the lens).
pub fn read_views(dir: impl AsRef<Path>) -> Result<CameraSet, FormatError> {
    Ok(read_views_with(dir.as_ref(), Lenses::Refuse)?.views)
}

/// A views directory's cameras and each one's lens, as [`read_capture`] reads them.
#[derive(Debug, Clone, PartialEq)]
pub struct Capture {
    pub views: CameraSet,
    /// The lens of each training view, then of each held-out view.
    pub lenses: Vec<Distortion>,
}

/// Reads a views directory keeping each camera's lens distortion (the `working_views` stage,
/// which undoes it; [`crate::data::lens`]).
pub fn read_capture(dir: impl AsRef<Path>) -> Result<Capture, FormatError> {
    read_views_with(dir.as_ref(), Lenses::Keep)
}

fn read_views_with(dir: &Path, lenses: Lenses) -> Result<Capture, FormatError> {
    let Some(train_path) = ["transforms.json", "transforms_train.json"]
        .iter()
        .map(|n| dir.join(n))
        .find(|p| p.is_file())
    else {
        return match super::colmap::find_sparse(dir) {
            Some(sparse) => {
                let (views, lenses) = super::colmap::read_colmap_views(dir, &sparse, lenses)?;
                Ok(Capture { views, lenses })
            }
            None => Err(FormatError::invalid(
                dir,
                "no cameras: expected transforms.json or transforms_train.json, or a COLMAP model (cameras and images, .bin or .txt) in sparse/0/ or sparse/, in this directory",
            )),
        };
    };
    let (train, mut all_lenses): (Vec<Camera>, Vec<Distortion>) =
        read_transforms_with(&train_path, lenses)?
            .into_iter()
            .unzip();
    let test = match ["transforms_test.json", "transforms_val.json"]
        .iter()
        .map(|n| dir.join(n))
        .find(|p| p.is_file())
    {
        Some(p) => read_transforms_with(&p, lenses)?,
        None => Vec::new(),
    };
    let (test, test_lenses): (Vec<Camera>, Vec<Distortion>) = test.into_iter().unzip();
    all_lenses.extend(test_lenses);
    Ok(Capture {
        views: CameraSet { train, test },
        lenses: all_lenses,
    })
}

/// Writes `transforms.json` (training) and `transforms_test.json` (held-out) into `dir`.
pub fn write_views(dir: impl AsRef<Path>, cameras: &CameraSet) -> Result<(), FormatError> {
    let dir = dir.as_ref();
    write_transforms(dir.join("transforms.json"), &cameras.train)?;
    write_transforms(dir.join("transforms_test.json"), &cameras.test)
}

/// Absolute (or `dir`-relative) path of a camera's image.
pub fn image_path(dir: impl AsRef<Path>, camera: &Camera) -> PathBuf {
    dir.as_ref().join(&camera.file_path)
}

/// Path of a camera's foreground mask: the first of [`mask_candidates`] that exists, else the
/// default `<stem>_mask.png` next to the image (`train/r_000.png` -> `train/r_000_mask.png`).
pub fn mask_path(dir: impl AsRef<Path>, camera: &Camera) -> PathBuf {
    let dir = dir.as_ref();
    mask_candidates(&camera.file_path)
        .into_iter()
        .map(|m| dir.join(m))
        .find(|p| p.is_file())
        .unwrap_or_else(|| dir.join(mask_file_path(&camera.file_path)))
}

/// Where a camera's mask may be, relative like its `file_path`, in the order they are tried (see
/// the module doc): `<stem>_mask.png`, `masks/<stem>.png`, `masks/<name>.png`.
pub fn mask_candidates(file_path: &str) -> Vec<String> {
    let rel = file_path.strip_prefix("images/").unwrap_or(file_path);
    let stem = file_stem(rel);
    vec![
        mask_file_path(file_path),
        format!("masks/{stem}.png"),
        format!("masks/{rel}.png"),
    ]
}

/// The error for a view that needs a mask and has none: it names the image and where a mask was
/// looked for.
pub fn missing_mask(dir: impl AsRef<Path>, camera: &Camera) -> FormatError {
    let c = mask_candidates(&camera.file_path);
    FormatError::invalid(
        &image_path(dir, camera),
        format!(
            "the image has no alpha channel and no mask: expected a mask PNG (white = object) at {} or {} (or {}), or the object in the image's alpha channel",
            c[1], c[0], c[2]
        ),
    )
}

/// An image's relative path without its extension (`train/r_000.png` -> `train/r_000`): the
/// name a stage gives the files it writes for that view.
pub fn file_stem(file_path: &str) -> &str {
    match Path::new(file_path).extension() {
        Some(ext) => &file_path[..file_path.len() - ext.len() - 1],
        None => file_path,
    }
}

/// `file_path` of a camera's mask, relative like the image's.
pub fn mask_file_path(file_path: &str) -> String {
    format!("{}_mask.png", file_stem(file_path))
}

/// `file_path` of a camera's fur mask (`<stem>_fur.png`: the pixels where a strand is seen
/// first, which synthetic scenes write and the learners' L_mask reads), relative like the
/// image's.
pub fn fur_mask_file_path(file_path: &str) -> String {
    format!("{}_fur.png", file_stem(file_path))
}

/// One view's pixels: colour (3 channels, [0, 1]), the foreground mask (1 channel, [0, 1]) if
/// the capture has one, and the image's own alpha channel if it has one.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewImages {
    pub rgb: ImageF32,
    pub mask: Option<ImageF32>,
    /// The image's alpha (soft coverage where a renderer wrote it: a translucent fur fringe
    /// reads below 1), whether or not a mask file takes precedence as [`ViewImages::mask`].
    pub alpha: Option<ImageF32>,
}

/// Reads a camera's image and mask. The mask is `<stem>_mask.png` when that file exists (its first
/// channel), else the image's alpha channel when it has one, else `None`. Gray images are expanded
/// to RGB. The image size must match the camera's `w` x `h`.
pub fn read_view(dir: impl AsRef<Path>, camera: &Camera) -> Result<ViewImages, FormatError> {
    let dir = dir.as_ref();
    let path = image_path(dir, camera);
    let img = super::images::read_image(&path).map_err(|e| match e {
        // Say where the name came from: a frame of the views' camera file.
        FormatError::Io { path, source } if source.kind() == std::io::ErrorKind::NotFound => {
            FormatError::invalid(
                &path,
                format!(
                    "missing image: a frame of the transforms file lists `file_path` = `{}`, but there is no such file ({source})",
                    camera.file_path
                ),
            )
        }
        other => other,
    })?;
    if (img.width, img.height) != (camera.width, camera.height) {
        return Err(FormatError::invalid(
            &path,
            format!(
                "image is {} x {} but its camera says {} x {}",
                img.width, img.height, camera.width, camera.height
            ),
        ));
    }
    let n = (img.width * img.height) as usize;
    let c = img.channels as usize;
    let mut rgb = ImageF32::new(img.width, img.height, 3);
    for i in 0..n {
        let px = &img.data[i * c..i * c + c];
        let (r, g, b) = match c {
            1 | 2 => (px[0], px[0], px[0]),
            _ => (px[0], px[1], px[2]),
        };
        rgb.data[3 * i..3 * i + 3].copy_from_slice(&[r, g, b]);
    }
    let alpha = (c == 2 || c == 4).then(|| img.channel(c - 1));
    let mpath = mask_path(dir, camera);
    let mask = if mpath.is_file() {
        let m = super::images::read_png(&mpath)?;
        if (m.width, m.height) != (img.width, img.height) {
            return Err(FormatError::invalid(
                &mpath,
                format!(
                    "mask is {} x {} but its image is {} x {}",
                    m.width, m.height, img.width, img.height
                ),
            ));
        }
        Some(m.first_channel())
    } else {
        alpha.clone()
    };
    Ok(ViewImages { rgb, mask, alpha })
}

/// Reads one `transforms*.json` file as pinhole cameras (a distorting lens is an error).
/// `file_path`s are resolved against the file's directory.
pub fn read_transforms(path: impl AsRef<Path>) -> Result<Vec<Camera>, FormatError> {
    Ok(read_transforms_with(path.as_ref(), Lenses::Refuse)?
        .into_iter()
        .map(|(c, _)| c)
        .collect())
}

/// Reads one `transforms*.json` file, each camera with its lens (module doc).
fn read_transforms_with(
    path: &Path,
    lenses: Lenses,
) -> Result<Vec<(Camera, Distortion)>, FormatError> {
    let bytes = read_bytes(path)?;
    let root: Value = from_slice(path, &bytes)?;
    let dir = path.parent().unwrap_or(Path::new(""));
    let top = root.as_object().ok_or_else(|| {
        FormatError::at(
            path,
            Position::Line(1),
            "expected a JSON object at the top level",
        )
    })?;
    let frames = match top.get("frames") {
        Some(Value::Array(f)) => f,
        Some(_) => {
            return Err(FormatError::at(
                path,
                field("frames"),
                "expected an array of frame objects",
            ))
        }
        None => {
            return Err(FormatError::at(
                path,
                field("frames"),
                "missing (no frames list)",
            ))
        }
    };
    // The file's lens is refused only where a frame takes it: a frame that names its own lens
    // replaces the file's whole.
    let top_intr = Level::read(path, top, "", Lenses::Keep)?;
    let mut cameras = Vec::with_capacity(frames.len());
    for (i, frame) in frames.iter().enumerate() {
        let prefix = format!("frames[{i}]");
        let obj = frame
            .as_object()
            .ok_or_else(|| FormatError::at(path, field(&prefix), "expected a frame object"))?;
        let (camera, lens) = read_frame(path, dir, obj, &prefix, &top_intr, lenses)?;
        // A frame's own distorting lens was refused as it was read, so this one is the file's.
        if lenses == Lenses::Refuse && !lens.is_pinhole() {
            Level::read(path, top, "", Lenses::Refuse)?;
        }
        cameras.push((camera, lens));
    }
    Ok(cameras)
}

fn field(name: &str) -> Position {
    Position::Field(name.to_string())
}

fn join_field(prefix: &str, key: &str) -> String {
    if prefix.is_empty() {
        key.to_string()
    } else {
        format!("{prefix}.{key}")
    }
}

/// nerfstudio's distortion coefficients (OpenCV's radial `k`, tangential `p`).
const DISTORTION_KEYS: [&str; 6] = ["k1", "k2", "k3", "k4", "p1", "p2"];
/// nerfstudio `camera_model` values read (the first three radial-tangential, a pinhole when
/// every coefficient is zero).
const LENS_MODELS: [&str; 4] = ["PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "OPENCV_FISHEYE"];

/// Intrinsics as found at one level (the file or a frame); every entry optional.
#[derive(Default)]
struct Level {
    w: Option<u32>,
    h: Option<u32>,
    fl_x: Option<f64>,
    fl_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    /// (fx, fy, cx, cy) from `intrinsic_matrix`.
    k: Option<[f64; 4]>,
    angle_x: Option<f64>,
    angle_y: Option<f64>,
    /// The lens, when this level gives distortion coefficients or a `camera_model`.
    lens: Option<Distortion>,
}

impl Level {
    /// Reads and checks the intrinsics entries of `obj` (the file's top level or a frame, whose
    /// field names start with `prefix`), refusing lens distortion under [`Lenses::Refuse`].
    fn read(
        path: &Path,
        obj: &Map<String, Value>,
        prefix: &str,
        lenses: Lenses,
    ) -> Result<Level, FormatError> {
        let fields = LevelFields { path, obj, prefix };
        let k = fields.intrinsic_matrix()?;
        let lens = fields.lens(lenses)?;
        Ok(Level {
            lens,
            w: fields.size("w")?,
            h: fields.size("h")?,
            fl_x: fields.positive("fl_x")?,
            fl_y: fields.positive("fl_y")?,
            cx: fields.num("cx")?,
            cy: fields.num("cy")?,
            k,
            angle_x: fields.angle("camera_angle_x")?,
            angle_y: fields.angle("camera_angle_y")?,
        })
    }

    /// (fx, fy) from this level, given the image size.
    fn focal(&self, w: u32, h: u32) -> Option<(f64, f64)> {
        if let Some(fx) = self.fl_x {
            return Some((fx, self.fl_y.unwrap_or(fx)));
        }
        if let Some(k) = self.k {
            return Some((k[0], k[1]));
        }
        if let Some(ax) = self.angle_x {
            let fx = 0.5 * w as f64 / (0.5 * ax).tan();
            let fy = match self.angle_y {
                Some(ay) => 0.5 * h as f64 / (0.5 * ay).tan(),
                None => fx,
            };
            return Some((fx, fy));
        }
        None
    }

    fn principal(&self) -> (Option<f64>, Option<f64>) {
        match (self.cx, self.cy, self.k) {
            (None, None, Some(k)) => (Some(k[2]), Some(k[3])),
            (cx, cy, _) => (cx, cy),
        }
    }
}

/// Typed access to the intrinsics entries of one level, errors naming the field.
struct LevelFields<'a> {
    path: &'a Path,
    obj: &'a Map<String, Value>,
    /// Field path of the level (empty at the top level).
    prefix: &'a str,
}

impl LevelFields<'_> {
    /// The field position of `key` at this level.
    fn at(&self, key: &str) -> Position {
        field(&join_field(self.prefix, key))
    }

    /// A finite number, or `None` when absent or null.
    fn num(&self, key: &str) -> Result<Option<f64>, FormatError> {
        match self.obj.get(key) {
            None | Some(Value::Null) => Ok(None),
            Some(Value::Number(n)) => {
                let v = n.as_f64().unwrap_or(f64::NAN);
                if v.is_finite() {
                    Ok(Some(v))
                } else {
                    Err(FormatError::at(
                        self.path,
                        self.at(key),
                        "expected a finite number",
                    ))
                }
            }
            Some(other) => Err(FormatError::at(
                self.path,
                self.at(key),
                format!("expected a number, found {}", kind(other)),
            )),
        }
    }

    /// A positive number, or `None`.
    fn positive(&self, key: &str) -> Result<Option<f64>, FormatError> {
        match self.num(key)? {
            Some(v) if v <= 0.0 => Err(FormatError::at(
                self.path,
                self.at(key),
                format!("expected a positive value, found {v}"),
            )),
            other => Ok(other),
        }
    }

    /// A positive whole number of pixels, or `None`.
    fn size(&self, key: &str) -> Result<Option<u32>, FormatError> {
        match self.positive(key)? {
            None => Ok(None),
            Some(v) if v.fract() == 0.0 && v <= u32::MAX as f64 => Ok(Some(v as u32)),
            Some(v) => Err(FormatError::at(
                self.path,
                self.at(key),
                format!("expected a whole number of pixels, found {v}"),
            )),
        }
    }

    /// A positive field of view in radians below pi, or `None`.
    fn angle(&self, key: &str) -> Result<Option<f64>, FormatError> {
        match self.positive(key)? {
            Some(a) if a >= std::f64::consts::PI => Err(FormatError::at(
                self.path,
                self.at(key),
                format!("expected a field of view in radians below pi, found {a}"),
            )),
            other => Ok(other),
        }
    }

    /// (fx, fy, cx, cy) of a 3x3 or 4x4 `intrinsic_matrix`, or `None`.
    fn intrinsic_matrix(&self) -> Result<Option<[f64; 4]>, FormatError> {
        let path = self.path;
        match self.obj.get("intrinsic_matrix") {
            None | Some(Value::Null) => Ok(None),
            Some(v) => {
                let f = join_field(self.prefix, "intrinsic_matrix");
                let rows = matrix_rows(path, &f, v)?;
                if !(rows.len() == 3 || rows.len() == 4) || rows.iter().any(|r| r.len() < 3) {
                    return Err(FormatError::at(
                        path,
                        field(&f),
                        "expected a 3x3 or 4x4 matrix as rows",
                    ));
                }
                let kk = [rows[0][0], rows[1][1], rows[0][2], rows[1][2]];
                if kk[0] <= 0.0 || kk[1] <= 0.0 {
                    return Err(FormatError::at(
                        path,
                        field(&f),
                        "expected positive focal lengths K[0][0] and K[1][1]",
                    ));
                }
                Ok(Some(kk))
            }
        }
    }

    /// The lens of this level (nerfstudio's `camera_model` and `k1 k2 k3 k4 p1 p2`,
    /// [`crate::data::lens`]), `None` when it names neither; under [`Lenses::Refuse`] a lens that
    /// distorts is an error naming the field.
    fn lens(&self, lenses: Lenses) -> Result<Option<Distortion>, FormatError> {
        let mut c = [0.0; 6];
        let mut given = None;
        for (i, key) in DISTORTION_KEYS.iter().enumerate() {
            if let Some(v) = self.num(key)? {
                c[i] = v;
                if v != 0.0 && given.is_none() {
                    given = Some((*key, v));
                }
            }
        }
        let keys_present = DISTORTION_KEYS.iter().any(|k| self.obj.contains_key(*k));
        let model = match self.obj.get("camera_model") {
            None | Some(Value::Null) => None,
            Some(Value::String(m)) => Some(m.as_str()),
            Some(other) => {
                return Err(FormatError::at(
                    self.path,
                    self.at("camera_model"),
                    format!("expected a string, found {}", kind(other)),
                ))
            }
        };
        let lens =
            match model {
                None | Some("PINHOLE" | "SIMPLE_PINHOLE" | "OPENCV") => {
                    Distortion::radial_tangential([c[0], c[1], c[2], c[3]], [c[4], c[5]])
                }
                Some("OPENCV_FISHEYE") if c[4] == 0.0 && c[5] == 0.0 => Distortion::Fisheye {
                    k: [c[0], c[1], c[2], c[3]],
                },
                Some("OPENCV_FISHEYE") => return Err(FormatError::at(
                    self.path,
                    self.at(if c[4] != 0.0 { "p1" } else { "p2" }),
                    "a fisheye (OPENCV_FISHEYE) has no tangential distortion: expected p1 = p2 = 0",
                )),
                Some(other) => {
                    return Err(FormatError::at(
                        self.path,
                        self.at("camera_model"),
                        format!(
                            "camera model `{other}`: expected one of {}; undistort other captures \
                         (equirectangular, FISHEYE624) first",
                            LENS_MODELS.join(", ")
                        ),
                    ))
                }
            };
        if lenses == Lenses::Refuse && !lens.is_pinhole() {
            let (at, what) = match given {
                Some((key, v)) => (key, format!("lens distortion {key} = {v}")),
                None => (
                    "camera_model",
                    format!("camera model {}", model.unwrap_or("?")),
                ),
            };
            return Err(FormatError::at(
                self.path,
                self.at(at),
                format!("{what}: {UNDISTORT_HINT}"),
            ));
        }
        Ok((keys_present || model.is_some()).then_some(lens))
    }
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// A matrix given as an array of rows of numbers.
fn matrix_rows(path: &Path, f: &str, v: &Value) -> Result<Vec<Vec<f64>>, FormatError> {
    let rows = v.as_array().ok_or_else(|| {
        FormatError::at(
            path,
            field(f),
            format!("expected an array of rows, found {}", kind(v)),
        )
    })?;
    rows.iter()
        .enumerate()
        .map(|(r, row)| {
            let row = row.as_array().ok_or_else(|| {
                FormatError::at(
                    path,
                    field(&format!("{f}[{r}]")),
                    "expected a row (array of numbers)",
                )
            })?;
            row.iter()
                .enumerate()
                .map(|(c, x)| {
                    x.as_f64().filter(|x| x.is_finite()).ok_or_else(|| {
                        FormatError::at(
                            path,
                            field(&format!("{f}[{r}][{c}]")),
                            format!("expected a finite number, found {}", kind(x)),
                        )
                    })
                })
                .collect()
        })
        .collect()
}

/// One frame of a transforms file: its image path, camera-to-world matrix and intrinsics (the
/// frame's own, else the top level's `top`, else the image's size and centre).
fn read_frame(
    path: &Path,
    dir: &Path,
    obj: &Map<String, Value>,
    prefix: &str,
    top: &Level,
    lenses: Lenses,
) -> Result<(Camera, Distortion), FormatError> {
    let file_path = frame_file_path(path, dir, obj, prefix)?;
    let c2w = frame_c2w(path, obj, prefix)?;
    let local = Level::read(path, obj, prefix, lenses)?;
    let (w, h) = frame_size(path, dir, &file_path, prefix, &local, top)?;
    let (fx, fy) = local.focal(w, h).or_else(|| top.focal(w, h)).ok_or_else(|| {
        FormatError::at(
            path,
            field(&join_field(prefix, "fl_x")),
            "no focal length: expected fl_x, intrinsic_matrix or camera_angle_x in the frame or at the top level",
        )
    })?;
    let (lcx, lcy) = local.principal();
    let (tcx, tcy) = top.principal();
    let cx = lcx.or(tcx).unwrap_or(0.5 * w as f64);
    let cy = lcy.or(tcy).unwrap_or(0.5 * h as f64);
    let camera = Camera {
        file_path,
        c2w,
        fx: fx as f32,
        fy: fy as f32,
        cx: cx as f32,
        cy: cy as f32,
        width: w,
        height: h,
    };
    if ![camera.fx, camera.fy, camera.cx, camera.cy]
        .iter()
        .all(|v| v.is_finite())
        || camera.fx <= 0.0
        || camera.fy <= 0.0
    {
        return Err(FormatError::at(
            path,
            field(prefix),
            "intrinsics out of f32 range or not positive",
        ));
    }
    let lens = local.lens.or(top.lens).unwrap_or(Distortion::None);
    Ok((camera, lens))
}

/// The frame's `file_path`, required non-empty, normalised.
fn frame_file_path(
    path: &Path,
    dir: &Path,
    obj: &Map<String, Value>,
    prefix: &str,
) -> Result<String, FormatError> {
    let fp_field = join_field(prefix, "file_path");
    let raw_path = match obj.get("file_path") {
        Some(Value::String(s)) if !s.trim().is_empty() => s.as_str(),
        Some(other) => {
            return Err(FormatError::at(
                path,
                field(&fp_field),
                format!("expected a non-empty string, found {}", kind(other)),
            ))
        }
        None => {
            return Err(FormatError::at(
                path,
                field(&fp_field),
                "missing (image path)",
            ))
        }
    };
    let rel = normalise_file_path(dir, raw_path);
    if leaves_directory(&rel) {
        return Err(FormatError::at(
            path,
            field(&fp_field),
            format!("`{raw_path}` {OUTSIDE_VIEWS}"),
        ));
    }
    Ok(rel)
}

/// What an image path outside the views directory is told.
pub(crate) const OUTSIDE_VIEWS: &str = "lies outside the views directory: the views' cache key \
    is the hash of that directory's files, so a photo elsewhere could change without anything \
    rerunning, and the stages name their per-view outputs after the path; copy (or link) the \
    photos into the views directory and give paths relative to it";

/// Whether a relative image path is absolute or climbs out of its directory (`..`).
pub(crate) fn leaves_directory(rel: &str) -> bool {
    Path::new(rel).components().any(|c| {
        !matches!(
            c,
            std::path::Component::Normal(_) | std::path::Component::CurDir
        )
    })
}

/// The frame's `transform_matrix`: 4 rows (or 3) of 4 numbers, a last row of `[0, 0, 0, 1]`,
/// invertible and within f32 range.
fn frame_c2w(path: &Path, obj: &Map<String, Value>, prefix: &str) -> Result<Mat4, FormatError> {
    let tm_field = join_field(prefix, "transform_matrix");
    let tm = obj.get("transform_matrix").ok_or_else(|| {
        FormatError::at(
            path,
            field(&tm_field),
            "missing (camera-to-world 4x4 matrix)",
        )
    })?;
    let rows = matrix_rows(path, &tm_field, tm)?;
    if !(rows.len() == 3 || rows.len() == 4) || rows.iter().any(|r| r.len() != 4) {
        return Err(FormatError::at(
            path,
            field(&tm_field),
            format!(
                "expected 4 rows (or 3) of 4 numbers, found {} rows of lengths {:?}",
                rows.len(),
                rows.iter().map(Vec::len).collect::<Vec<_>>()
            ),
        ));
    }
    if rows.len() == 4 {
        let last = &rows[3];
        let ok = (last[0].abs() + last[1].abs() + last[2].abs() + (last[3] - 1.0).abs()) < 1e-4;
        if !ok {
            return Err(FormatError::at(
                path,
                field(&format!("{tm_field}[3]")),
                format!("expected the last row [0, 0, 0, 1] of a rigid camera-to-world matrix, found {last:?}"),
            ));
        }
    }
    // The bottom row is kept as written (validated above) so that a round trip is exact.
    let bottom = |c: usize| match rows.get(3) {
        Some(last) => last[c] as f32,
        None => (c == 3) as u8 as f32,
    };
    let col = |c: usize| {
        Vec4::new(
            rows[0][c] as f32,
            rows[1][c] as f32,
            rows[2][c] as f32,
            bottom(c),
        )
    };
    let c2w = Mat4::from_cols(col(0), col(1), col(2), col(3));
    if c2w.determinant().abs() < 1e-12 || !c2w.is_finite() {
        return Err(FormatError::at(
            path,
            field(&tm_field),
            "matrix is singular or out of f32 range",
        ));
    }
    Ok(c2w)
}

/// The frame's image size: `w` / `h` of the frame or the top level, the image's own for what
/// neither gives.
fn frame_size(
    path: &Path,
    dir: &Path,
    file_path: &str,
    prefix: &str,
    local: &Level,
    top: &Level,
) -> Result<(u32, u32), FormatError> {
    Ok(match (local.w.or(top.w), local.h.or(top.h)) {
        (Some(w), Some(h)) => (w, h),
        (w, h) => {
            let img = dir.join(file_path);
            let (iw, ih) = super::images::image_size(&img).map_err(|e| {
                FormatError::at(
                    path,
                    field(&join_field(prefix, "w")),
                    format!("image size not given (w/h) and not readable from the image: {e}"),
                )
            })?;
            (w.unwrap_or(iw), h.unwrap_or(ih))
        }
    })
}

/// Normalises a frame's `file_path` (see the module doc).
fn normalise_file_path(dir: &Path, raw: &str) -> String {
    let mut p = raw.trim().replace('\\', "/");
    while let Some(rest) = p.strip_prefix("./") {
        p = rest.to_string();
    }
    let has_image_ext = Path::new(&p)
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
        .unwrap_or(false);
    if has_image_ext {
        return p;
    }
    for ext in IMAGE_EXTENSIONS {
        for e in [ext.to_string(), ext.to_ascii_uppercase()] {
            let candidate = format!("{p}.{e}");
            if dir.join(&candidate).is_file() {
                return candidate;
            }
        }
    }
    if dir.join(&p).is_file() {
        return p;
    }
    format!("{p}.png")
}

#[derive(Serialize)]
struct FileOut<'a> {
    #[serde(skip_serializing_if = "Option::is_none")]
    camera_angle_x: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    camera_angle_y: Option<f32>,
    #[serde(flatten)]
    intrinsics: Option<Intrinsics>,
    frames: Vec<FrameOut<'a>>,
}

#[derive(Serialize, Clone, Copy, PartialEq)]
struct Intrinsics {
    fl_x: f32,
    fl_y: f32,
    cx: f32,
    cy: f32,
    w: u32,
    h: u32,
}

#[derive(Serialize)]
struct FrameOut<'a> {
    file_path: &'a str,
    transform_matrix: [[f32; 4]; 4],
    #[serde(flatten)]
    intrinsics: Option<Intrinsics>,
}

fn intrinsics(c: &Camera) -> Intrinsics {
    Intrinsics {
        fl_x: c.fx,
        fl_y: c.fy,
        cx: c.cx,
        cy: c.cy,
        w: c.width,
        h: c.height,
    }
}

/// Writes one `transforms*.json` file (see the module doc for the layout).
pub fn write_transforms(path: impl AsRef<Path>, cameras: &[Camera]) -> Result<(), FormatError> {
    let path = path.as_ref();
    for (i, c) in cameras.iter().enumerate() {
        check_finite(
            path,
            &format!("camera {i} ({})", c.file_path),
            c.c2w
                .to_cols_array()
                .into_iter()
                .chain([c.fx, c.fy, c.cx, c.cy]),
        )?;
        if c.fx <= 0.0 || c.fy <= 0.0 || c.width == 0 || c.height == 0 {
            return Err(FormatError::invalid(
                path,
                format!(
                    "camera {i} ({}): focal lengths and image size must be positive",
                    c.file_path
                ),
            ));
        }
    }
    let shared = match cameras.first() {
        Some(first) if cameras.iter().all(|c| intrinsics(c) == intrinsics(first)) => {
            Some(intrinsics(first))
        }
        _ => None,
    };
    let frames = cameras
        .iter()
        .map(|c| {
            let mut m = [[0.0f32; 4]; 4];
            for (r, row) in m.iter_mut().enumerate() {
                for (k, v) in row.iter_mut().enumerate() {
                    *v = c.c2w.col(k)[r];
                }
            }
            FrameOut {
                file_path: &c.file_path,
                transform_matrix: m,
                intrinsics: if shared.is_some() {
                    None
                } else {
                    Some(intrinsics(c))
                },
            }
        })
        .collect();
    let out = FileOut {
        camera_angle_x: shared.map(|k| 2.0 * (0.5 * k.w as f32 / k.fl_x).atan()),
        camera_angle_y: shared.map(|k| 2.0 * (0.5 * k.h as f32 / k.fl_y).atan()),
        intrinsics: shared,
        frames,
    };
    let bytes = to_pretty_bytes(path, &out)?;
    write_bytes(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn data(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../tests/data/formats")
            .join(name)
    }

    /// Rows of every frame's `transform_matrix`, read straight from the JSON (not through our reader).
    fn raw_matrices(path: &Path) -> Vec<[[f64; 4]; 4]> {
        let v: Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
        v["frames"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| {
                let mut m = [[0.0; 4]; 4];
                for (r, row) in m.iter_mut().enumerate() {
                    for (c, x) in row.iter_mut().enumerate() {
                        *x = f["transform_matrix"][r][c].as_f64().unwrap();
                    }
                }
                m
            })
            .collect()
    }

    /// Independent projection in the OpenCV convention (x right, y down, z forward): the OpenGL
    /// camera axes flipped, `u = fx x / z + cx`, `v = fy y / z + cy`.
    fn project_cv(m: &[[f64; 4]; 4], k: [f64; 4], p: [f64; 3]) -> (f64, f64) {
        let d = [p[0] - m[0][3], p[1] - m[1][3], p[2] - m[2][3]];
        let axis = |c: usize| (0..3).map(|r| m[r][c] * d[r]).sum::<f64>();
        let (x, y, z) = (axis(0), -axis(1), -axis(2));
        (k[0] * x / z + k[2], k[1] * y / z + k[3])
    }

    #[test]
    fn blender_nerf_synthetic_reads() {
        let dir = data("nerf_synthetic");
        let set = read_views(&dir).unwrap();
        assert_eq!(set.train.len(), 3, "transforms_train.json");
        assert_eq!(
            set.test.len(),
            2,
            "transforms_test.json preferred over transforms_val.json"
        );
        assert_eq!(set.train[0].file_path, "train/r_0.png");
        assert_eq!(set.test[1].file_path, "test/r_1.png");
        let angle = 0.6911112070083618f64;
        let f = 0.5 * 8.0 / (0.5 * angle).tan();
        let mats = raw_matrices(&dir.join("transforms_train.json"));
        for (cam, m) in set.train.iter().zip(&mats) {
            assert_eq!((cam.width, cam.height), (8, 6), "size from the PNG header");
            assert!((cam.fx as f64 - f).abs() < 1e-4 && (cam.fy as f64 - f).abs() < 1e-4);
            assert_eq!((cam.cx, cam.cy), (4.0, 3.0));
            // The cameras look at the origin: it lands on the image centre, in front.
            let (uv, depth) = cam.project(Vec3::ZERO);
            assert!(
                (uv.x - 4.0).abs() < 1e-4 && (uv.y - 3.0).abs() < 1e-4,
                "{uv}"
            );
            assert!((depth - 4.031).abs() < 1e-4, "{depth}");
            // An off-centre point agrees with an independent OpenCV-convention projection.
            let p = [1.0, -0.8, 1.2];
            let (u, v) = project_cv(m, [f, f, 4.0, 3.0], p);
            let (uv, _) = cam.project(Vec3::new(1.0, -0.8, 1.2));
            assert!(
                (uv.x as f64 - u).abs() < 1e-3 && (uv.y as f64 - v).abs() < 1e-3,
                "{uv} vs {u},{v}"
            );
            assert!(
                (uv - glam::Vec2::new(4.0, 3.0)).length() > 1.0,
                "the test point must be off-centre: {uv}"
            );
            // The ray through that pixel passes through the point.
            let (o, d) = cam.ray(uv.x, uv.y);
            let q = Vec3::new(1.0, -0.8, 1.2) - o;
            assert!(q.cross(d).length() < 1e-4);
        }
        let view = read_view(&dir, &set.train[1]).unwrap();
        assert_eq!(view.rgb.channels, 3);
        let mask = view.mask.expect("alpha channel is the mask");
        assert_eq!(mask.data[0], 0.0); // (x + y) % 3 == 0 -> transparent
        assert_eq!(mask.data[1], 1.0);
    }

    #[test]
    fn instant_ngp_colmap_capture_reads() {
        // colmap2nerf.py copies COLMAP's OPENCV distortion into the file: refused, naming it.
        let e = read_views(data("ngp_capture")).unwrap_err();
        assert_eq!(e.position(), Some(&Position::Field("k1".into())), "{e}");
        assert!(e.to_string().contains("undistort"), "{e}");
        // The same capture undistorted (coefficients zeroed) reads.
        let tmp = tempfile::tempdir().unwrap();
        let mut v: Value = serde_json::from_slice(
            &std::fs::read(data("ngp_capture").join("transforms.json")).unwrap(),
        )
        .unwrap();
        for k in DISTORTION_KEYS {
            if let Some(x) = v.get_mut(k) {
                *x = serde_json::json!(0.0);
            }
        }
        std::fs::write(tmp.path().join("transforms.json"), v.to_string()).unwrap();
        let dir = tmp.path().to_path_buf();
        let set = read_views(&dir).unwrap();
        assert_eq!(set.train.len(), 4);
        assert!(set.test.is_empty());
        let c = &set.train[2];
        assert_eq!(c.file_path, "images/0003.jpg");
        assert_eq!((c.width, c.height), (1920, 1080));
        assert_eq!(
            (c.fx, c.fy),
            (1375.5210563891232f64 as f32, 1374.4929911283916f64 as f32)
        );
        assert_eq!(
            (c.cx, c.cy),
            (964.2156614587127f64 as f32, 541.1364584958453f64 as f32)
        );
        let mats = raw_matrices(&dir.join("transforms.json"));
        let k = [
            1375.5210563891232,
            1374.4929911283916,
            964.2156614587127,
            541.1364584958453,
        ];
        for (cam, m) in set.train.iter().zip(&mats) {
            let (uv, _) = cam.project(Vec3::new(0.05, -0.02, 0.1));
            assert!(
                (uv.x - cam.cx).abs() < 1e-2 && (uv.y - cam.cy).abs() < 1e-2,
                "{uv}"
            );
            let (u, v) = project_cv(m, k, [0.5, 0.4, -0.3]);
            let (uv, _) = cam.project(Vec3::new(0.5, 0.4, -0.3));
            assert!(
                (uv.x as f64 - u).abs() < 2e-2 && (uv.y as f64 - v).abs() < 2e-2,
                "{uv} vs {u},{v}"
            );
        }
    }

    fn camera(i: usize, fx: f32) -> Camera {
        let eye = Vec3::new(1.0 + i as f32, -2.0, 0.5 * i as f32 + 0.3);
        let c2w = Mat4::look_at_rh(eye, Vec3::ZERO, Vec3::Z).inverse();
        Camera {
            file_path: format!("train/r_{i:03}.png"),
            c2w,
            fx,
            fy: fx * 1.01,
            cx: 40.5,
            cy: 29.75,
            width: 80,
            height: 60,
        }
    }

    #[test]
    fn round_trip_shared_and_per_frame_intrinsics() {
        let dir = tempfile::tempdir().unwrap();
        let shared = CameraSet {
            train: (0..4).map(|i| camera(i, 71.3)).collect(),
            test: vec![camera(9, 71.3)],
        };
        write_views(dir.path(), &shared).unwrap();
        assert_eq!(read_views(dir.path()).unwrap(), shared);
        let text = std::fs::read_to_string(dir.path().join("transforms.json")).unwrap();
        assert!(text.contains("camera_angle_x") && text.ends_with("}\n"));
        let bytes = text.into_bytes();
        write_views(dir.path(), &read_views(dir.path()).unwrap()).unwrap();
        assert_eq!(
            std::fs::read(dir.path().join("transforms.json")).unwrap(),
            bytes
        );

        let mixed = CameraSet {
            train: (0..3).map(|i| camera(i, 50.0 + i as f32 / 3.0)).collect(),
            test: Vec::new(),
        };
        let dir2 = tempfile::tempdir().unwrap();
        write_views(dir2.path(), &mixed).unwrap();
        assert_eq!(read_views(dir2.path()).unwrap(), mixed);
        assert!(dir2.path().join("transforms_test.json").is_file());
    }

    #[test]
    fn neus2_intrinsic_matrix_and_per_frame_overrides() {
        let dir = tempfile::tempdir().unwrap();
        let text = r#"{"w": 64, "h": 48, "fl_x": 10, "frames": [
            {"file_path": "image/000.png", "intrinsic_matrix": [[60.5, 0, 31.25, 0], [0, 61.5, 23.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
             "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2]]},
            {"file_path": "image\\001.png", "w": 32, "camera_angle_x": 1.0, "cy": 7,
             "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]},
            {"file_path": "./image/002.png",
             "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]}]}"#;
        std::fs::write(dir.path().join("transforms.json"), text).unwrap();
        let set = read_views(dir.path()).unwrap();
        let c = &set.train;
        assert_eq!(
            (c[0].fx, c[0].fy, c[0].cx, c[0].cy),
            (60.5, 61.5, 31.25, 23.5)
        );
        assert_eq!((c[0].width, c[0].height), (64, 48));
        assert_eq!(c[1].file_path, "image/001.png");
        assert_eq!(c[1].width, 32);
        let f = (16.0 / 0.5f64.tan()) as f32;
        assert_eq!((c[1].fx, c[1].fy, c[1].cx, c[1].cy), (f, f, 16.0, 7.0));
        assert_eq!(
            (c[2].fx, c[2].fy, c[2].cx, c[2].cy),
            (10.0, 10.0, 32.0, 24.0)
        );
        assert_eq!(c[2].center(), Vec3::new(0.0, 0.0, 2.0));
    }

    #[test]
    #[allow(clippy::useless_format)]
    fn malformed_files_name_the_field() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("transforms.json");
        let frame_ok = r#"{"file_path": "a.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"#;
        let cases: Vec<(String, &str)> = vec![
            (
                format!(
                    r#"{{"fl_x": 5, "w": 4, "h": 4, "frames": [{frame_ok}, {{"file_path": "b.png"}}]}}"#
                ),
                "frames[1].transform_matrix",
            ),
            // Photos outside the views directory: absolute, or climbing out of it.
            (
                r#"{"fl_x": 5, "w": 4, "h": 4, "frames": [{"file_path": "/data/cap/a.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}"#.to_string(),
                "frames[0].file_path",
            ),
            (
                r#"{"fl_x": 5, "w": 4, "h": 4, "frames": [{"file_path": "./../images/a.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}"#.to_string(),
                "frames[0].file_path",
            ),
            (
                format!(
                    r#"{{"fl_x": 5, "w": 4, "h": 4, "frames": [{frame_ok}, {{"file_path": "b.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,1,1]]}}]}}"#
                ),
                "frames[1].transform_matrix[3]",
            ),
            (
                format!(
                    r#"{{"fl_x": 5, "w": 4, "h": 4, "frames": [{{"file_path": "b.png", "transform_matrix": [[1,0,0],[0,1,0],[0,0,1]]}}]}}"#
                ),
                "frames[0].transform_matrix",
            ),
            (
                format!(
                    r#"{{"fl_x": 5, "w": 4, "h": 4, "frames": [{{"file_path": "b.png", "transform_matrix": [[1,0,0,"x"],[0,1,0,0],[0,0,1,0]]}}]}}"#
                ),
                "frames[0].transform_matrix[0][3]",
            ),
            (
                format!(r#"{{"w": 4, "h": 4, "frames": [{frame_ok}]}}"#),
                "frames[0].fl_x",
            ),
            (
                format!(r#"{{"fl_x": -5, "w": 4, "h": 4, "frames": [{frame_ok}]}}"#),
                "fl_x",
            ),
            (
                format!(r#"{{"fl_x": 5, "w": 4.5, "h": 4, "frames": [{frame_ok}]}}"#),
                "w",
            ),
            (
                format!(r#"{{"fl_x": 5, "frames": [{frame_ok}]}}"#),
                "frames[0].w",
            ),
            (
                format!(r#"{{"fl_x": 5, "w": 4, "h": 4, "frames": [{{"transform_matrix": []}}]}}"#),
                "frames[0].file_path",
            ),
            (r#"{"fl_x": 5, "w": 4, "h": 4}"#.to_string(), "frames"),
            // nerfstudio's distortion and camera model: a pinhole only.
            (
                format!(r#"{{"fl_x": 5, "w": 4, "h": 4, "k1": 0.02, "frames": [{frame_ok}]}}"#),
                "k1",
            ),
            (
                format!(
                    r#"{{"fl_x": 5, "w": 4, "h": 4, "frames": [{{"file_path": "b.png", "p2": -1e-3, "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}}]}}"#
                ),
                "frames[0].p2",
            ),
            (
                format!(
                    r#"{{"fl_x": 5, "w": 4, "h": 4, "camera_model": "OPENCV_FISHEYE", "frames": [{frame_ok}]}}"#
                ),
                "camera_model",
            ),
        ];
        for (text, fieldname) in cases {
            std::fs::write(&p, &text).unwrap();
            let e = read_views(dir.path()).unwrap_err();
            assert_eq!(
                e.position(),
                Some(&Position::Field(fieldname.to_string())),
                "{text}: {e}"
            );
            assert!(e.to_string().contains("transforms.json"), "{e}");
        }
        // A file-level lens that every frame replaces with its own pinhole reads; one that a
        // frame takes is refused, naming the file's field.
        let own = |lens: &str| {
            format!(
                r#"{{"file_path": "a.png", {lens}"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}}"#
            )
        };
        let pinhole = own(r#""camera_model": "OPENCV", "k1": 0, "#);
        std::fs::write(
            &p,
            format!(
                r#"{{"fl_x": 5, "w": 4, "h": 4, "k1": 0.02, "frames": [{pinhole}, {pinhole}]}}"#
            ),
        )
        .unwrap();
        assert_eq!(read_views(dir.path()).unwrap().train.len(), 2);
        std::fs::write(
            &p,
            format!(
                r#"{{"fl_x": 5, "w": 4, "h": 4, "k1": 0.02, "frames": [{pinhole}, {}]}}"#,
                own("")
            ),
        )
        .unwrap();
        let e = read_views(dir.path()).unwrap_err();
        assert_eq!(e.position(), Some(&Position::Field("k1".into())), "{e}");
        // nerfstudio's own undistorted output (OPENCV, zero distortion) reads.
        std::fs::write(
            &p,
            format!(
                r#"{{"camera_model": "OPENCV", "fl_x": 5, "fl_y": 5, "cx": 2, "cy": 2, "w": 4, "h": 4, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": [{frame_ok}]}}"#
            ),
        )
        .unwrap();
        assert_eq!(read_transforms(&p).unwrap().len(), 1);
        // The lenses read_capture keeps: nerfstudio's OPENCV (k4 the r^8 term) at the top level,
        // a frame's own lens replacing it whole; a model fure does not know is refused by both.
        std::fs::write(dir.path().join("b.png"), b"").unwrap();
        std::fs::write(
            &p,
            r#"{"camera_model": "OPENCV", "fl_x": 5, "w": 4, "h": 4, "k1": -0.1, "k2": 0.02, "k3": 0.003, "k4": 0.0004, "p1": 0.001, "p2": -0.002, "frames": [
                {"file_path": "b.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]},
                {"file_path": "b.png", "camera_model": "OPENCV_FISHEYE", "k1": 0.05, "p1": 0, "p2": 0, "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}"#,
        )
        .unwrap();
        let cap = read_capture(dir.path()).unwrap();
        assert_eq!(
            cap.lenses,
            [
                Distortion::radial_tangential([-0.1, 0.02, 0.003, 0.0004], [0.001, -0.002]),
                Distortion::Fisheye {
                    k: [0.05, 0.0, 0.0, 0.0]
                },
            ]
        );
        for model in ["EQUIRECTANGULAR", "FISHEYE624"] {
            std::fs::write(
                &p,
                format!(r#"{{"camera_model": "{model}", "fl_x": 5, "w": 4, "h": 4, "frames": [{frame_ok}]}}"#),
            )
            .unwrap();
            let e = read_capture(dir.path()).unwrap_err();
            assert_eq!(
                e.position(),
                Some(&Position::Field("camera_model".into())),
                "{e}"
            );
        }
        // Syntax errors and truncation: line and column.
        std::fs::write(&p, "{\n  \"frames\": [\n    {\"file_path\": \"a.png\",\n").unwrap();
        let e = read_views(dir.path()).unwrap_err();
        assert!(
            matches!(e.position(), Some(Position::LineColumn { line: 4, .. })),
            "{e}"
        );
        // No camera file at all.
        std::fs::remove_file(&p).unwrap();
        let e = read_views(dir.path()).unwrap_err();
        assert!(e.to_string().contains("transforms.json"), "{e}");
    }

    #[test]
    fn masks_folder_for_rgb_images_and_missing_masks_named() {
        assert_eq!(
            mask_candidates("images/a/0001.jpg"),
            [
                "images/a/0001_mask.png",
                "masks/a/0001.png",
                "masks/a/0001.jpg.png"
            ]
        );
        assert_eq!(mask_candidates("train/r_0.png")[1], "masks/train/r_0.png");
        let dir = tempfile::tempdir().unwrap();
        let mut rgb = ImageF32::new(4, 3, 3);
        rgb.data
            .iter_mut()
            .enumerate()
            .for_each(|(i, v)| *v = (i % 5) as f32 / 4.0);
        super::super::images::write_png(dir.path().join("images/0001.png"), &rgb).unwrap();
        let cam = Camera {
            file_path: "images/0001.png".into(),
            width: 4,
            height: 3,
            ..camera(0, 10.0)
        };
        // RGB, no mask anywhere: no mask read, and the error names the image and the mask files.
        assert_eq!(read_view(dir.path(), &cam).unwrap().mask, None);
        let e = missing_mask(dir.path(), &cam).to_string();
        assert!(
            e.contains("images/0001.png")
                && e.contains("masks/0001.png")
                && e.contains("images/0001_mask.png")
                && e.contains("alpha"),
            "{e}"
        );
        // COLMAP's own naming is found, then the plain stem wins over it.
        let mut m = ImageF32::new(4, 3, 1);
        m.data[5] = 1.0;
        super::super::images::write_png(dir.path().join("masks/0001.png.png"), &m).unwrap();
        assert_eq!(
            mask_path(dir.path(), &cam),
            dir.path().join("masks/0001.png.png")
        );
        m.data[6] = 1.0;
        super::super::images::write_png(dir.path().join("masks/0001.png"), &m).unwrap();
        let v = read_view(dir.path(), &cam).unwrap();
        assert_eq!(v.mask.unwrap().data, m.data);
        // 8-bit PNG: within a level.
        assert!(v
            .rgb
            .data
            .iter()
            .zip(&rgb.data)
            .all(|(a, b)| (a - b).abs() <= 1.0 / 255.0));
    }

    #[test]
    fn soft_alpha_is_kept_beside_a_mask_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut rgba = ImageF32::new(4, 3, 4);
        for (i, px) in rgba.data.chunks_exact_mut(4).enumerate() {
            px[3] = ((i % 5) * 51) as f32 / 255.0; // exact in 8 bits
        }
        super::super::images::write_png(dir.path().join("r_0.png"), &rgba).unwrap();
        let cam = Camera {
            file_path: "r_0.png".into(),
            width: 4,
            height: 3,
            ..camera(0, 10.0)
        };
        let soft: Vec<f32> = rgba.data.chunks_exact(4).map(|p| p[3]).collect();
        let near = |a: &[f32]| a.iter().zip(&soft).all(|(x, y)| (x - y).abs() < 1e-6);
        // Without a mask file the alpha is both.
        let v = read_view(dir.path(), &cam).unwrap();
        assert!(near(&v.mask.unwrap().data) && near(&v.alpha.unwrap().data));
        // A (binary) mask file takes over the mask; the soft alpha is still there.
        let mut m = ImageF32::new(4, 3, 1);
        for (d, a) in m.data.iter_mut().zip(&soft) {
            *d = if *a >= 0.5 { 1.0 } else { 0.0 };
        }
        super::super::images::write_png(dir.path().join("r_0_mask.png"), &m).unwrap();
        let v = read_view(dir.path(), &cam).unwrap();
        assert_eq!(v.mask.unwrap().data, m.data);
        assert!(near(&v.alpha.unwrap().data));
    }

    #[test]
    fn paths_and_masks() {
        assert_eq!(mask_file_path("train/r_000.png"), "train/r_000_mask.png");
        assert_eq!(mask_file_path("a.b/c"), "a.b/c_mask.png");
        assert_eq!(fur_mask_file_path("train/r_000.png"), "train/r_000_fur.png");
        assert_eq!(fur_mask_file_path("images/0001.jpg"), "images/0001_fur.png");
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("im")).unwrap();
        std::fs::write(dir.path().join("im/x.JPG"), b"").unwrap();
        assert_eq!(normalise_file_path(dir.path(), "./im/x"), "im/x.JPG");
        assert_eq!(normalise_file_path(dir.path(), "im/y"), "im/y.png");
        assert_eq!(
            normalise_file_path(dir.path(), "im/frame.0001.jpeg"),
            "im/frame.0001.jpeg"
        );
    }
}
