//! COLMAP sparse models (`cameras` + `images`, text or binary) as a views directory.
//!
//! A COLMAP views directory is what `colmap mapper` (or `colmap image_undistorter`, whose `dense/`
//! folder has the same layout) leaves behind:
//!
//! ```text
//! views/
//!   sparse/0/cameras.bin  images.bin  (points3D.*: not read)   or sparse/cameras.* directly
//!   images/<name>            the photos, `<name>` as written in images.*
//!   masks/<name stem>.png    optional foreground masks, white = object (also `masks/<name>.png`)
//! ```
//!
//! [`find_sparse`] picks `sparse/0/`, else `sparse/`; in each, binary files win over text ones
//! when both exist (COLMAP writes binary by default, and its doubles are exact). Text files
//! follow COLMAP's `cameras.txt` / `images.txt` (`#` comments; two lines per image, the second,
//! the 2D points, skipped); binary files COLMAP's little-endian layout (`read_write_model.py`).
//!
//! **Convention.** COLMAP stores world-to-camera poses (`x_cam = R(q) x_world + t`, quaternion
//! `qw qx qy qz`) with OpenCV camera axes (+x right, +y down, +z forward); [`Camera`] is
//! camera-to-world with OpenGL axes (+y up, looking down -z). So `c2w = [R^T | -R^T t]` with its
//! y and z columns negated. COLMAP's pixel centres are at half-integers, as ours: `cx`, `cy`
//! carry over unchanged.
//!
//! **Camera models.** `SIMPLE_PINHOLE` and `PINHOLE` are pinholes. `SIMPLE_RADIAL` (COLMAP's
//! default), `RADIAL`, `OPENCV`, `FULL_OPENCV` and the fisheyes `OPENCV_FISHEYE`,
//! `SIMPLE_RADIAL_FISHEYE`, `RADIAL_FISHEYE` are read with their lens
//! ([`crate::data::lens::Distortion`]) under [`Lenses::Keep`], which the `working_views` stage
//! uses to undistort the photos; every other reader ([`Lenses::Refuse`]) takes a lens with every
//! coefficient zero for a pinhole and refuses any other with an error naming the camera, its
//! model and coefficients, and what to do. `FOV` and the thin-prism models are refused in both:
//! undistort them with `colmap image_undistorter --image_path images --input_path sparse/0
//! --output_path dense` and point `views` at `dense/` (it writes `PINHOLE` cameras).
//!
//! **Held-out views.** Images are sorted by name; when there are at least [`HOLDOUT_EVERY`]
//! images, every [`HOLDOUT_EVERY`]-th one from the first (index `i % 8 == 0`, the LLFF /
//! Mip-NeRF 360 convention) is held out as a test view, the rest are training views. Fewer
//! images are all training views.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{DMat3, DQuat, DVec3, Mat4};

use super::{read_bytes, write_bytes, FormatError, Position};
use crate::data::camera::{Camera, CameraSet};
use crate::data::lens::Distortion;

/// One in this many images (by sorted name, from the first) is held out for testing.
pub const HOLDOUT_EVERY: usize = 8;

/// COLMAP's camera models: (id, name, parameter count).
const MODELS: [(i32, &str, usize); 12] = [
    (0, "SIMPLE_PINHOLE", 3),
    (1, "PINHOLE", 4),
    (2, "SIMPLE_RADIAL", 4),
    (3, "RADIAL", 5),
    (4, "OPENCV", 8),
    (5, "OPENCV_FISHEYE", 8),
    (6, "FULL_OPENCV", 12),
    (7, "FOV", 5),
    (8, "SIMPLE_RADIAL_FISHEYE", 4),
    (9, "RADIAL_FISHEYE", 5),
    (10, "THIN_PRISM_FISHEYE", 12),
    (11, "RAD_TAN_THIN_PRISM_FISHEYE", 16),
];

/// A camera of `cameras.txt` / `cameras.bin`.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    pub id: u32,
    pub model: String,
    pub width: u64,
    pub height: u64,
    pub params: Vec<f64>,
}

/// A registered image of `images.txt` / `images.bin` (its 2D points are not kept).
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImage {
    pub id: u32,
    /// World-to-camera rotation, `qw qx qy qz`.
    pub q: [f64; 4],
    /// World-to-camera translation.
    pub t: [f64; 3],
    pub camera_id: u32,
    pub name: String,
}

/// A sparse model's cameras and images.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ColmapModel {
    pub cameras: Vec<ColmapCamera>,
    pub images: Vec<ColmapImage>,
}

fn model_by_name(name: &str) -> Option<(i32, &'static str, usize)> {
    MODELS.iter().copied().find(|m| m.1 == name)
}

fn model_by_id(id: i32) -> Option<(i32, &'static str, usize)> {
    MODELS.iter().copied().find(|m| m.0 == id)
}

/// The sparse model folder of a COLMAP views directory: `sparse/0/`, else `sparse/`, when it
/// holds `cameras.bin` or `cameras.txt`.
pub fn find_sparse(dir: &Path) -> Option<PathBuf> {
    [dir.join("sparse").join("0"), dir.join("sparse")]
        .into_iter()
        .find(|d| d.join("cameras.bin").is_file() || d.join("cameras.txt").is_file())
}

/// Reads `cameras` and `images` from a sparse model folder (binary files win over text).
pub fn read_model(sparse: &Path) -> Result<ColmapModel, FormatError> {
    let pick = |stem: &str| -> Result<PathBuf, FormatError> {
        let bin = sparse.join(format!("{stem}.bin"));
        let txt = sparse.join(format!("{stem}.txt"));
        if bin.is_file() {
            Ok(bin)
        } else if txt.is_file() {
            Ok(txt)
        } else {
            Err(FormatError::invalid(
                sparse,
                format!(
                    "COLMAP model without {stem}: expected {stem}.bin or {stem}.txt in this folder"
                ),
            ))
        }
    };
    let cams = pick("cameras")?;
    let imgs = pick("images")?;
    let is_bin = |p: &Path| p.extension().is_some_and(|e| e == "bin");
    let cameras = if is_bin(&cams) {
        read_cameras_bin(&cams)?
    } else {
        read_cameras_txt(&cams)?
    };
    let images = if is_bin(&imgs) {
        read_images_bin(&imgs)?
    } else {
        read_images_txt(&imgs)?
    };
    Ok(ColmapModel { cameras, images })
}

fn parse<T: std::str::FromStr>(
    path: &Path,
    line: usize,
    column: usize,
    token: &str,
    what: &str,
) -> Result<T, FormatError> {
    token.parse().map_err(|_| {
        FormatError::at(
            path,
            Position::LineColumn { line, column },
            format!("expected {what}, found `{token}`"),
        )
    })
}

/// A finite number (NaN and infinities are refused where they are read, not downstream).
fn number(path: &Path, line: usize, column: usize, token: &str) -> Result<f64, FormatError> {
    let v: f64 = parse(path, line, column, token, "a number")?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(FormatError::at(
            path,
            Position::LineColumn { line, column },
            format!("expected a finite number, found `{token}`"),
        ))
    }
}

/// Whitespace-separated tokens of a line with their 1-based columns.
fn tokens(line: &str) -> Vec<(usize, &str)> {
    let mut out = Vec::new();
    let mut start = None;
    for (i, c) in line.char_indices() {
        match (c.is_whitespace(), start) {
            (false, None) => start = Some(i),
            (true, Some(s)) => {
                out.push((s + 1, &line[s..i]));
                start = None;
            }
            _ => {}
        }
    }
    if let Some(s) = start {
        out.push((s + 1, &line[s..]));
    }
    out
}

fn text(path: &Path) -> Result<String, FormatError> {
    String::from_utf8(read_bytes(path)?).map_err(|e| {
        FormatError::at(
            path,
            Position::Byte(e.utf8_error().valid_up_to() as u64),
            "not UTF-8 text",
        )
    })
}

/// Reads `cameras.txt`: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]` per line.
pub fn read_cameras_txt(path: &Path) -> Result<Vec<ColmapCamera>, FormatError> {
    let text = text(path)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let ln = i + 1;
        let t = line.trim_start();
        if t.is_empty() || t.starts_with('#') {
            continue;
        }
        let tok = tokens(line);
        if tok.len() < 4 {
            return Err(FormatError::at(
                path,
                Position::Line(ln),
                "expected `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`",
            ));
        }
        let id = parse(path, ln, tok[0].0, tok[0].1, "a camera id (integer)")?;
        let (_, name, n) = model_by_name(tok[1].1).ok_or_else(|| {
            FormatError::at(
                path,
                Position::LineColumn {
                    line: ln,
                    column: tok[1].0,
                },
                format!("unknown camera model `{}`", tok[1].1),
            )
        })?;
        let width = parse(path, ln, tok[2].0, tok[2].1, "the image width (integer)")?;
        let height = parse(path, ln, tok[3].0, tok[3].1, "the image height (integer)")?;
        if tok.len() != 4 + n {
            return Err(FormatError::at(
                path,
                Position::Line(ln),
                format!(
                    "camera model {name} has {n} parameters, found {}",
                    tok.len() - 4
                ),
            ));
        }
        let params = tok[4..]
            .iter()
            .map(|(c, s)| number(path, ln, *c, s))
            .collect::<Result<Vec<_>, _>>()?;
        out.push(ColmapCamera {
            id,
            model: name.to_string(),
            width,
            height,
            params,
        });
    }
    Ok(out)
}

/// Reads `images.txt`: `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`, then a line of 2D points.
pub fn read_images_txt(path: &Path) -> Result<Vec<ColmapImage>, FormatError> {
    let text = text(path)?;
    let lines: Vec<&str> = text.lines().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let line = lines[i];
        let ln = i + 1;
        let t = line.trim_start();
        if t.is_empty() || t.starts_with('#') {
            i += 1;
            continue;
        }
        let tok = tokens(line);
        if tok.len() < 10 {
            return Err(FormatError::at(
                path,
                Position::Line(ln),
                "expected `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`",
            ));
        }
        let id = parse(path, ln, tok[0].0, tok[0].1, "an image id (integer)")?;
        let mut v = [0.0f64; 7];
        for (k, x) in v.iter_mut().enumerate() {
            *x = number(path, ln, tok[k + 1].0, tok[k + 1].1)?;
        }
        let camera_id = parse(path, ln, tok[8].0, tok[8].1, "a camera id (integer)")?;
        // The name is the rest of the line (COLMAP names rarely hold spaces, but may).
        let name = line[tok[9].0 - 1..].trim_end().to_string();
        out.push(ColmapImage {
            id,
            q: [v[0], v[1], v[2], v[3]],
            t: [v[4], v[5], v[6]],
            camera_id,
            name,
        });
        // The next line lists the image's 2D points (possibly empty): not needed.
        i += 2;
    }
    Ok(out)
}

/// A little-endian cursor over a binary model file that reports where it ran out.
struct Bin<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    at: usize,
}

impl Bin<'_> {
    /// An error unless every byte was read (`what` names the last record kind).
    fn finish(&self, what: &str) -> Result<(), FormatError> {
        if self.at == self.bytes.len() {
            return Ok(());
        }
        Err(FormatError::at(
            self.path,
            Position::Byte(self.at as u64),
            format!("trailing bytes after the last {what}"),
        ))
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&[u8], FormatError> {
        if self.bytes.len() - self.at < n {
            return Err(FormatError::at(
                self.path,
                Position::Byte(self.at as u64),
                format!("file ends inside {what}: expected {n} more bytes"),
            ));
        }
        let s = &self.bytes[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }
    fn u64(&mut self, what: &str) -> Result<u64, FormatError> {
        Ok(u64::from_le_bytes(self.take(8, what)?.try_into().unwrap()))
    }
    fn i32(&mut self, what: &str) -> Result<i32, FormatError> {
        Ok(i32::from_le_bytes(self.take(4, what)?.try_into().unwrap()))
    }
    fn f64(&mut self, what: &str) -> Result<f64, FormatError> {
        let at = self.at;
        let v = f64::from_le_bytes(self.take(8, what)?.try_into().unwrap());
        if !v.is_finite() {
            return Err(FormatError::at(
                self.path,
                Position::Byte(at as u64),
                format!("expected a finite number in {what}, found {v}"),
            ));
        }
        Ok(v)
    }
    /// A count of records of at least `min_bytes` each, checked against the bytes left.
    fn count(&mut self, what: &str, min_bytes: usize) -> Result<usize, FormatError> {
        let at = self.at;
        let n = self.u64(what)?;
        let left = (self.bytes.len() - self.at) as u64;
        if n.saturating_mul(min_bytes as u64) > left {
            return Err(FormatError::at(
                self.path,
                Position::Byte(at as u64),
                format!("{what} = {n} does not fit in the {left} bytes left"),
            ));
        }
        Ok(n as usize)
    }
}

/// Reads `cameras.bin`.
pub fn read_cameras_bin(path: &Path) -> Result<Vec<ColmapCamera>, FormatError> {
    let bytes = read_bytes(path)?;
    let mut b = Bin {
        path,
        bytes: &bytes,
        at: 0,
    };
    let n = b.count("the number of cameras", 24)?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let id = b.i32("a camera id")?;
        let at = b.at;
        let model_id = b.i32("a camera model id")?;
        let (_, name, np) = model_by_id(model_id).ok_or_else(|| {
            FormatError::at(
                path,
                Position::Byte(at as u64),
                format!("camera {id}: unknown camera model id {model_id}"),
            )
        })?;
        let width = b.u64("an image width")?;
        let height = b.u64("an image height")?;
        let params = (0..np)
            .map(|_| b.f64("camera parameters"))
            .collect::<Result<Vec<_>, _>>()?;
        out.push(ColmapCamera {
            id: id as u32,
            model: name.to_string(),
            width,
            height,
            params,
        });
    }
    b.finish("camera")?;
    Ok(out)
}

/// Reads `images.bin`.
pub fn read_images_bin(path: &Path) -> Result<Vec<ColmapImage>, FormatError> {
    let bytes = read_bytes(path)?;
    let mut b = Bin {
        path,
        bytes: &bytes,
        at: 0,
    };
    let n = b.count("the number of images", 4 + 7 * 8 + 4 + 1 + 8)?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let id = b.i32("an image id")? as u32;
        let mut v = [0.0f64; 7];
        for x in v.iter_mut() {
            *x = b.f64("an image pose")?;
        }
        let camera_id = b.i32("a camera id")? as u32;
        let at = b.at;
        let end = bytes[at..].iter().position(|&c| c == 0).ok_or_else(|| {
            FormatError::at(
                path,
                Position::Byte(at as u64),
                "file ends inside an image name (no terminating 0 byte)",
            )
        })?;
        let name = String::from_utf8(bytes[at..at + end].to_vec()).map_err(|_| {
            FormatError::at(path, Position::Byte(at as u64), "image name is not UTF-8")
        })?;
        b.at = at + end + 1;
        let points = b.count("the number of 2D points", 24)?;
        b.take(points * 24, "2D points")?;
        out.push(ColmapImage {
            id,
            q: [v[0], v[1], v[2], v[3]],
            t: [v[4], v[5], v[6]],
            camera_id,
            name,
        });
    }
    b.finish("image")?;
    Ok(out)
}

/// Writes `cameras.txt` and `images.txt` (no 2D points) into `dir`.
pub fn write_model_txt(dir: &Path, model: &ColmapModel) -> Result<(), FormatError> {
    let mut c = String::from("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    for cam in &model.cameras {
        c.push_str(&format!(
            "{} {} {} {}",
            cam.id, cam.model, cam.width, cam.height
        ));
        for p in &cam.params {
            c.push_str(&format!(" {p}"));
        }
        c.push('\n');
    }
    write_bytes(&dir.join("cameras.txt"), c.as_bytes())?;
    let mut s = String::from("# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n");
    for im in &model.images {
        let [qw, qx, qy, qz] = im.q;
        let [tx, ty, tz] = im.t;
        s.push_str(&format!(
            "{} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {} {}\n\n",
            im.id, im.camera_id, im.name
        ));
    }
    write_bytes(&dir.join("images.txt"), s.as_bytes())
}

/// Writes `cameras.bin` and `images.bin` (no 2D points) into `dir`.
pub fn write_model_bin(dir: &Path, model: &ColmapModel) -> Result<(), FormatError> {
    let path = dir.join("cameras.bin");
    let mut c = (model.cameras.len() as u64).to_le_bytes().to_vec();
    for cam in &model.cameras {
        let (id, _, _) = model_by_name(&cam.model)
            .filter(|m| m.2 == cam.params.len())
            .ok_or_else(|| {
                FormatError::invalid(
                    &path,
                    format!(
                        "camera {}: model {} with {} parameters",
                        cam.id,
                        cam.model,
                        cam.params.len()
                    ),
                )
            })?;
        c.extend((cam.id as i32).to_le_bytes());
        c.extend(id.to_le_bytes());
        c.extend(cam.width.to_le_bytes());
        c.extend(cam.height.to_le_bytes());
        for p in &cam.params {
            c.extend(p.to_le_bytes());
        }
    }
    write_bytes(&path, &c)?;
    let mut s = (model.images.len() as u64).to_le_bytes().to_vec();
    for im in &model.images {
        s.extend((im.id as i32).to_le_bytes());
        for v in im.q.iter().chain(&im.t) {
            s.extend(v.to_le_bytes());
        }
        s.extend((im.camera_id as i32).to_le_bytes());
        s.extend(im.name.as_bytes());
        s.push(0);
        s.extend(0u64.to_le_bytes());
    }
    write_bytes(&dir.join("images.bin"), &s)
}

/// Whether a reader keeps a distorting camera's lens or refuses the camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Lenses {
    /// An error naming the camera and what to do: for every stage that projects through the
    /// views' cameras as pinholes.
    Refuse,
    /// Kept beside the pinhole intrinsics: for the stage that undoes it (`working_views`).
    Keep,
}

/// What a distorting camera's error says to do.
pub const UNDISTORT_HINT: &str = "fure's stages see through pinhole cameras: read the capture through a `working_views` stage, which undistorts the photos (pipelines/capture.toml does), or undistort them first (`colmap image_undistorter --image_path images --input_path sparse/0 --output_path dense`, then use `dense/` as the views directory)";

/// A camera's intrinsics (fx, fy, cx, cy) and lens ([`crate::data::lens`]); under
/// [`Lenses::Refuse`] a camera that distorts is an error naming it.
fn intrinsics(
    cam: &ColmapCamera,
    path: &Path,
    lenses: Lenses,
) -> Result<([f64; 4], Distortion), FormatError> {
    let p = &cam.params;
    let rt =
        |radial: [f64; 4], tangential: [f64; 2]| Distortion::radial_tangential(radial, tangential);
    let fisheye = |k: [f64; 4]| Distortion::Fisheye { k };
    let (k, lens) = match cam.model.as_str() {
        "SIMPLE_PINHOLE" => ([p[0], p[0], p[1], p[2]], Distortion::None),
        "PINHOLE" => ([p[0], p[1], p[2], p[3]], Distortion::None),
        "SIMPLE_RADIAL" => ([p[0], p[0], p[1], p[2]], rt([p[3], 0.0, 0.0, 0.0], [0.0; 2])),
        "RADIAL" => ([p[0], p[0], p[1], p[2]], rt([p[3], p[4], 0.0, 0.0], [0.0; 2])),
        "OPENCV" => ([p[0], p[1], p[2], p[3]], rt([p[4], p[5], 0.0, 0.0], [p[6], p[7]])),
        "FULL_OPENCV" => (
            [p[0], p[1], p[2], p[3]],
            Distortion::RadialTangential {
                radial: [p[4], p[5], p[8], 0.0],
                rational: [p[9], p[10], p[11]],
                tangential: [p[6], p[7]],
            },
        ),
        "OPENCV_FISHEYE" => ([p[0], p[1], p[2], p[3]], fisheye([p[4], p[5], p[6], p[7]])),
        "SIMPLE_RADIAL_FISHEYE" => ([p[0], p[0], p[1], p[2]], fisheye([p[3], 0.0, 0.0, 0.0])),
        "RADIAL_FISHEYE" => ([p[0], p[0], p[1], p[2]], fisheye([p[3], p[4], 0.0, 0.0])),
        other => {
            return Err(FormatError::invalid(
                path,
                format!(
                    "camera {} has model {other}, which fure does not model: undistort the images first (`colmap image_undistorter --image_path images --input_path sparse/0 --output_path dense`, then use `dense/` as the views directory)",
                    cam.id
                ),
            ))
        }
    };
    // The parameters after the focal lengths and the principal point.
    let one_focal = matches!(
        cam.model.as_str(),
        "SIMPLE_PINHOLE" | "SIMPLE_RADIAL" | "RADIAL" | "SIMPLE_RADIAL_FISHEYE" | "RADIAL_FISHEYE"
    );
    let coefficients = &p[if one_focal { 3 } else { 4 }..];
    if !coefficients.iter().all(|c| c.is_finite()) {
        return Err(FormatError::invalid(
            path,
            format!(
                "camera {} ({}): expected finite distortion coefficients, found {:?}",
                cam.id, cam.model, coefficients
            ),
        ));
    }
    if lenses == Lenses::Refuse && !lens.is_pinhole() {
        return Err(FormatError::invalid(
            path,
            format!(
                "camera {} ({}) has lens distortion {:?}: {UNDISTORT_HINT}",
                cam.id, cam.model, coefficients
            ),
        ));
    }
    // Sizes beyond u32 are no image (and would not fit a Camera).
    let size_ok = |v: u64| v > 0 && v <= u32::MAX as u64;
    if k.iter().any(|v| !v.is_finite())
        || k[0] <= 0.0
        || k[1] <= 0.0
        || !size_ok(cam.width)
        || !size_ok(cam.height)
    {
        return Err(FormatError::invalid(
            path,
            format!("camera {} ({}): expected positive focal lengths and image size, found {:?}, {} x {}", cam.id, cam.model, cam.params, cam.width, cam.height),
        ));
    }
    Ok((k, lens))
}

/// COLMAP's world-to-camera pose (OpenCV axes) as our camera-to-world matrix (OpenGL axes).
pub fn c2w_from_colmap(q: [f64; 4], t: [f64; 3]) -> Mat4 {
    let r = DMat3::from_quat(DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize());
    let rt = r.transpose();
    let centre = -(rt * DVec3::from(t));
    // Columns of R^T are the camera axes in the world; OpenGL's y and z are OpenCV's negated.
    let cols = [rt.x_axis, -rt.y_axis, -rt.z_axis];
    glam::DMat4::from_cols(
        cols[0].extend(0.0),
        cols[1].extend(0.0),
        cols[2].extend(0.0),
        centre.extend(1.0),
    )
    .as_mat4()
}

/// Our camera-to-world matrix as COLMAP's (quaternion `qw qx qy qz`, translation); for writers
/// and tests.
pub fn colmap_from_c2w(c2w: &Mat4) -> ([f64; 4], [f64; 3]) {
    let c = c2w.as_dmat4();
    let rt = DMat3::from_cols(
        c.x_axis.truncate(),
        -c.y_axis.truncate(),
        -c.z_axis.truncate(),
    );
    let r = rt.transpose();
    let q = DQuat::from_mat3(&r).normalize();
    let t = -(r * c.w_axis.truncate());
    ([q.w, q.x, q.y, q.z], t.to_array())
}

/// The views of a COLMAP views directory `dir` (see the module doc): images under `images/`,
/// sorted by name, every [`HOLDOUT_EVERY`]-th held out; with each camera's lens (all
/// [`Distortion::None`] under [`Lenses::Refuse`]), training views' then held-out views'.
pub fn read_colmap_views(
    dir: &Path,
    sparse: &Path,
    lenses: Lenses,
) -> Result<(CameraSet, Vec<Distortion>), FormatError> {
    let model = read_model(sparse)?;
    let images_file = ["images.bin", "images.txt"]
        .iter()
        .map(|n| sparse.join(n))
        .find(|p| p.is_file())
        .unwrap_or_else(|| sparse.to_path_buf());
    let cameras_file = ["cameras.bin", "cameras.txt"]
        .iter()
        .map(|n| sparse.join(n))
        .find(|p| p.is_file())
        .unwrap_or_else(|| sparse.to_path_buf());
    let cameras = lensed_model_cameras(&model, &cameras_file, &images_file, lenses)?;
    let mut set = CameraSet::default();
    let (mut train_lenses, mut test_lenses) = (Vec::new(), Vec::new());
    let holdout = cameras.len() >= HOLDOUT_EVERY;
    for (i, (camera, lens)) in cameras.into_iter().enumerate() {
        if !dir.join(&camera.file_path).is_file() {
            return Err(FormatError::invalid(
                &dir.join(&camera.file_path),
                format!(
                    "missing image: {} lists image `{}`, expected it under images/",
                    images_file.display(),
                    &camera.file_path["images/".len()..]
                ),
            ));
        }
        if holdout && i % HOLDOUT_EVERY == 0 {
            set.test.push(camera);
            test_lenses.push(lens);
        } else {
            set.train.push(camera);
            train_lenses.push(lens);
        }
    }
    train_lenses.extend(test_lenses);
    Ok((set, train_lenses))
}

/// A model's images as pinhole cameras ([`Lenses::Refuse`]; see [`lensed_model_cameras`]).
pub fn model_cameras(
    model: &ColmapModel,
    cameras_file: &Path,
    images_file: &Path,
) -> Result<Vec<Camera>, FormatError> {
    Ok(
        lensed_model_cameras(model, cameras_file, images_file, Lenses::Refuse)?
            .into_iter()
            .map(|(c, _)| c)
            .collect(),
    )
}

/// A model's images as cameras (`file_path` = `images/<name>`), sorted by name, each with its
/// camera's lens; the files are named in errors.
pub fn lensed_model_cameras(
    model: &ColmapModel,
    cameras_file: &Path,
    images_file: &Path,
    lenses: Lenses,
) -> Result<Vec<(Camera, Distortion)>, FormatError> {
    let (cameras_file, images_file) = (cameras_file.to_path_buf(), images_file.to_path_buf());
    let mut by_id: BTreeMap<u32, (&ColmapCamera, ([f64; 4], Distortion))> = BTreeMap::new();
    for cam in &model.cameras {
        if by_id
            .insert(cam.id, (cam, intrinsics(cam, &cameras_file, lenses)?))
            .is_some()
        {
            return Err(FormatError::invalid(
                &cameras_file,
                format!("camera id {} appears twice", cam.id),
            ));
        }
    }
    let mut images: Vec<&ColmapImage> = model.images.iter().collect();
    images.sort_by(|a, b| a.name.cmp(&b.name));
    if let Some(w) = images.windows(2).find(|w| w[0].name == w[1].name) {
        return Err(FormatError::invalid(
            &images_file,
            format!("image name `{}` appears twice", w[0].name),
        ));
    }
    let mut out = Vec::with_capacity(images.len());
    for im in images {
        let (cam, (k, lens)) = by_id.get(&im.camera_id).ok_or_else(|| {
            FormatError::invalid(
                &images_file,
                format!(
                    "image {} (`{}`) refers to camera {}, which cameras.* does not list",
                    im.id, im.name, im.camera_id
                ),
            )
        })?;
        if im.q.iter().chain(&im.t).any(|v| !v.is_finite()) || im.q.iter().all(|v| *v == 0.0) {
            return Err(FormatError::invalid(
                &images_file,
                format!(
                    "image {} (`{}`): expected a finite pose with a non-zero quaternion",
                    im.id, im.name
                ),
            ));
        }
        let name = im.name.replace('\\', "/");
        if super::cameras::leaves_directory(&name) {
            return Err(FormatError::invalid(
                &images_file,
                format!(
                    "image {} is named `{}`, which {}",
                    im.id,
                    im.name,
                    super::cameras::OUTSIDE_VIEWS
                ),
            ));
        }
        let camera = Camera {
            file_path: format!("images/{name}"),
            c2w: c2w_from_colmap(im.q, im.t),
            fx: k[0] as f32,
            fy: k[1] as f32,
            cx: k[2] as f32,
            cy: k[3] as f32,
            width: cam.width as u32,
            height: cam.height as u32,
        };
        // f64 values beyond f32's range, or a quaternion too small to normalise, end here.
        if !camera.c2w.is_finite()
            || ![camera.fx, camera.fy, camera.cx, camera.cy]
                .iter()
                .all(|v| v.is_finite())
        {
            return Err(FormatError::invalid(
                &images_file,
                format!(
                    "image {} (`{}`) with camera {}: the pose or intrinsics are out of range",
                    im.id, im.name, im.camera_id
                ),
            ));
        }
        out.push((camera, *lens));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// Cameras on a ring looking at the origin, one per model (both intrinsics forms).
    fn known() -> (ColmapModel, Vec<Camera>) {
        let mut model = ColmapModel::default();
        model.cameras.push(ColmapCamera {
            id: 1,
            model: "PINHOLE".into(),
            width: 64,
            height: 48,
            params: vec![70.5, 71.25, 31.75, 24.5],
        });
        model.cameras.push(ColmapCamera {
            id: 2,
            model: "SIMPLE_PINHOLE".into(),
            width: 40,
            height: 30,
            params: vec![50.0, 20.0, 15.0],
        });
        model.cameras.push(ColmapCamera {
            id: 3,
            model: "OPENCV".into(),
            width: 64,
            height: 48,
            params: vec![60.0, 61.0, 32.0, 24.0, 0.0, 0.0, 0.0, 0.0],
        });
        let mut cams = Vec::new();
        for i in 0..9u32 {
            let a = i as f32 * 0.7;
            let eye = Vec3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.8 + 0.1 * i as f32);
            // Our cameras: OpenGL axes, looking at a point near the origin, z up.
            let c2w = Mat4::look_at_rh(eye, Vec3::new(0.1, -0.2, 0.3), Vec3::Z).inverse();
            let (q, t) = colmap_from_c2w(&c2w);
            let camera_id = 1 + i % 3;
            let name = format!("img_{i:02}.png");
            model.images.push(ColmapImage {
                id: 10 + i,
                q,
                t,
                camera_id,
                name: name.clone(),
            });
            let c = &model.cameras[(camera_id - 1) as usize];
            let p = &c.params;
            let (fx, fy, cx, cy) = match c.model.as_str() {
                "SIMPLE_PINHOLE" => (p[0], p[0], p[1], p[2]),
                _ => (p[0], p[1], p[2], p[3]),
            };
            cams.push(Camera {
                file_path: format!("images/{name}"),
                c2w,
                fx: fx as f32,
                fy: fy as f32,
                cx: cx as f32,
                cy: cy as f32,
                width: c.width as u32,
                height: c.height as u32,
            });
        }
        (model, cams)
    }

    /// Limits of the real model's agreement: a sparse reconstruction of rendered fur from few SIFT
    /// matches is noisy (measured: 13 of 15 images within 5 degrees, centres within 8% of their
    /// spread, 17 px on 512 px images).
    const CENTRE_TOLERANCE: f64 = 0.1;
    const PX_TOLERANCE: f32 = 25.0;

    /// Independent projection the COLMAP way: x_cam = R x + t (OpenCV axes), u = fx x/z + cx.
    fn project_colmap(im: &ColmapImage, k: [f64; 4], p: [f64; 3]) -> (f64, f64) {
        let [w, x, y, z] = im.q;
        let n = (w * w + x * x + y * y + z * z).sqrt();
        let (w, x, y, z) = (w / n, x / n, y / n, z / n);
        let r = [
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ],
            [
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ],
            [
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ];
        let c: Vec<f64> = (0..3)
            .map(|i| (0..3).map(|j| r[i][j] * p[j]).sum::<f64>() + im.t[i])
            .collect();
        (k[0] * c[0] / c[2] + k[2], k[1] * c[1] / c[2] + k[3])
    }

    fn views_dir(model: &ColmapModel, bin: bool, nested: bool) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        let sparse = if nested {
            dir.path().join("sparse/0")
        } else {
            dir.path().join("sparse")
        };
        std::fs::create_dir_all(&sparse).unwrap();
        if bin {
            write_model_bin(&sparse, model).unwrap();
        } else {
            write_model_txt(&sparse, model).unwrap();
        }
        std::fs::create_dir_all(dir.path().join("images")).unwrap();
        for im in &model.images {
            std::fs::write(dir.path().join("images").join(&im.name), b"").unwrap();
        }
        dir
    }

    #[test]
    fn text_and_binary_models_round_trip_poses_and_intrinsics() {
        let (model, cams) = known();
        for (bin, nested) in [(false, true), (true, true), (true, false)] {
            let dir = views_dir(&model, bin, nested);
            let sparse = find_sparse(dir.path()).unwrap();
            assert_eq!(sparse.ends_with("0"), nested);
            let back = read_model(&sparse).unwrap();
            assert_eq!(back.cameras, model.cameras, "bin {bin}");
            assert_eq!(back.images, model.images, "bin {bin}");
            // Through the views reader: 9 images, sorted by name, every 8th held out (0 and 8).
            let set = super::super::cameras::read_views(dir.path()).unwrap();
            assert_eq!(
                set.test
                    .iter()
                    .map(|c| c.file_path.as_str())
                    .collect::<Vec<_>>(),
                ["images/img_00.png", "images/img_08.png"]
            );
            assert_eq!(set.train.len(), 7);
            for cam in set.train.iter().chain(&set.test) {
                let i: usize = cam.file_path[11..13].parse().unwrap();
                let want = &cams[i];
                assert_eq!(
                    (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height),
                    (want.fx, want.fy, want.cx, want.cy, want.width, want.height)
                );
                assert!(
                    cam.c2w.abs_diff_eq(want.c2w, 1e-5),
                    "{i}: {:?} vs {:?}",
                    cam.c2w,
                    want.c2w
                );
                let im = &model.images[i];
                let k = [
                    want.fx as f64,
                    want.fy as f64,
                    want.cx as f64,
                    want.cy as f64,
                ];
                for p in [[0.1, -0.2, 0.3], [0.5, 0.4, -0.3], [-0.6, 0.2, 0.9]] {
                    let (u, v) = project_colmap(im, k, p);
                    let (uv, depth) = cam.project(Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32));
                    assert!(depth > 0.0);
                    assert!(
                        (uv.x as f64 - u).abs() < 1e-3 && (uv.y as f64 - v).abs() < 1e-3,
                        "{i}: {uv} vs {u},{v}"
                    );
                }
                // The look-at point projects near the principal point, so the test is not vacuous
                // only off it: the third point lands away from it.
                let (uv, _) = cam.project(Vec3::new(-0.6, 0.2, 0.9));
                assert!((uv - glam::Vec2::new(cam.cx, cam.cy)).length() > 2.0);
            }
        }
    }

    /// How a model's cameras agree with the cameras they were made from, up to a similarity:
    /// (images whose frame rotation agrees with the consensus within 5 degrees, the worst centre
    /// residual of those over the centres' mean spread, their worst reprojection error in pixels
    /// of a point near the animal).
    fn agreement(pairs: &[(Camera, Camera)]) -> (usize, f64, f32) {
        let rot = |m: &Mat4| DMat3::from_mat4(m.as_dmat4());
        // Frame rotation per image, R_gt = S R_colmap; the consensus is the medoid.
        let s: Vec<DQuat> = pairs
            .iter()
            .map(|(c, g)| DQuat::from_mat3(&(rot(&g.c2w) * rot(&c.c2w).transpose())))
            .collect();
        let cost = |a: &DQuat| s.iter().map(|b| a.angle_between(*b)).sum::<f64>();
        let s0 = *s.iter().min_by(|a, b| cost(a).total_cmp(&cost(b))).unwrap();
        let inl: Vec<usize> = (0..s.len())
            .filter(|&i| s[i].angle_between(s0).to_degrees() < 5.0)
            .collect();
        let r = DMat3::from_quat(s0);
        // Scale and translation by least squares given the rotation.
        let n = inl.len() as f64;
        let cc: Vec<DVec3> = inl
            .iter()
            .map(|&i| pairs[i].0.center().as_dvec3())
            .collect();
        let cg: Vec<DVec3> = inl
            .iter()
            .map(|&i| pairs[i].1.center().as_dvec3())
            .collect();
        let (mc, mg) = (cc.iter().sum::<DVec3>() / n, cg.iter().sum::<DVec3>() / n);
        let scale = cc
            .iter()
            .zip(&cg)
            .map(|(c, g)| (*g - mg).dot(r * (*c - mc)))
            .sum::<f64>()
            / cc.iter().map(|c| (*c - mc).length_squared()).sum::<f64>();
        let spread = cg.iter().map(|g| (*g - mg).length()).sum::<f64>() / n;
        let centre = cc
            .iter()
            .zip(&cg)
            .map(|(c, g)| (r * (*c - mc) * scale + mg - *g).length() / spread)
            .fold(0.0, f64::max);
        // A point near the animal (the cameras look at the origin) through both cameras.
        let p_gt = DVec3::new(0.05, -0.03, 0.1) * spread;
        let p_c = r.transpose() * ((p_gt - mg) / scale) + mc;
        let px = inl
            .iter()
            .map(|&i| {
                let (a, _) = pairs[i].0.project(p_c.as_vec3());
                let (b, _) = pairs[i].1.project(p_gt.as_vec3());
                (a - b).length()
            })
            .fold(0.0, f32::max);
        (inl.len(), centre, px)
    }

    /// A real COLMAP 3.8 model of synthetic tiger views (tests/data/colmap/README.md), in text and
    /// in binary, agrees with the renderer's cameras up to one similarity: the images give one
    /// frame rotation, the centres map onto each other, and a point lands on the same pixel
    /// through both cameras. Without the OpenCV -> OpenGL axis flip they would not.
    #[test]
    fn real_colmap_output_matches_the_cameras_it_was_made_from() {
        let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/data/colmap");
        let gt = super::super::cameras::read_transforms(data.join("transforms.json")).unwrap();
        let tmp = tempfile::tempdir().unwrap();
        for ext in ["txt", "bin"] {
            // One format at a time (binary files win when both are present).
            let dir = tmp.path().join(ext);
            std::fs::create_dir_all(&dir).unwrap();
            for f in ["cameras", "images"] {
                std::fs::copy(
                    data.join(format!("sparse/0/{f}.{ext}")),
                    dir.join(format!("{f}.{ext}")),
                )
                .unwrap();
            }
            let model = read_model(&dir).unwrap();
            let cams = model_cameras(&model, &dir.join("cameras"), &dir.join("images")).unwrap();
            let pairs: Vec<(Camera, Camera)> = cams
                .iter()
                .map(|c| {
                    let g = gt
                        .iter()
                        .find(|g| g.file_path == format!("train/{}", &c.file_path[7..]))
                        .unwrap();
                    assert_eq!((c.fx, c.cx, c.width), (g.fx, g.cx, g.width));
                    (c.clone(), g.clone())
                })
                .collect();
            let (inliers, centre, px) = agreement(&pairs);
            eprintln!(
                "{ext}: {} images, {inliers} agree, centre residual {centre}, {px} px",
                pairs.len()
            );
            assert!(
                inliers * 10 >= pairs.len() * 8,
                "{ext}: {inliers} of {} images agree",
                pairs.len()
            );
            assert!(
                centre < CENTRE_TOLERANCE && px < PX_TOLERANCE,
                "{ext}: centre {centre}, {px} px"
            );
            // The control: OpenCV axes taken for OpenGL ones.
            let flip = Mat4::from_scale(Vec3::new(1.0, -1.0, -1.0));
            let wrong: Vec<(Camera, Camera)> = pairs
                .iter()
                .map(|(c, g)| {
                    (
                        Camera {
                            c2w: c.c2w * flip,
                            ..c.clone()
                        },
                        g.clone(),
                    )
                })
                .collect();
            let (bad, _, _) = agreement(&wrong);
            eprintln!("{ext}: without the axis flip {bad} agree");
            assert!(
                bad * 2 < pairs.len(),
                "{ext}: the control agrees on {bad} images"
            );
        }
    }

    #[test]
    fn distorting_lenses_are_refused_by_pinhole_readers_and_kept_for_working_views() {
        use super::super::cameras::{read_capture, read_views};
        let (mut model, _) = known();
        model.cameras[2].params[4] = -0.05;
        let dir = views_dir(&model, false, true);
        let e = read_views(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains("camera 3 (OPENCV)")
                && e.contains("distortion")
                && e.contains("working_views")
                && e.contains("image_undistorter")
                && e.contains("cameras.txt"),
            "{e}"
        );
        // Kept: the images of camera 3 carry its lens, the others are pinholes.
        let cap = read_capture(dir.path()).unwrap();
        let frames: Vec<&Camera> = cap.views.train.iter().chain(&cap.views.test).collect();
        assert_eq!(frames.len(), cap.lenses.len());
        let on_3 = |c: &Camera| {
            let im = model
                .images
                .iter()
                .find(|i| c.file_path.ends_with(&i.name))
                .unwrap();
            im.camera_id == 3
        };
        assert!(frames.iter().any(|c| on_3(c)));
        for (c, lens) in frames.iter().zip(&cap.lenses) {
            let expected = if on_3(c) {
                Distortion::radial_tangential([-0.05, 0.0, 0.0, 0.0], [0.0; 2])
            } else {
                Distortion::None
            };
            assert_eq!(*lens, expected, "{}", c.file_path);
        }
        // A fisheye is never a pinhole, whatever its coefficients; COLMAP's order of OPENCV_FISHEYE
        // parameters is fx fy cx cy k1 k2 k3 k4.
        model.cameras[2] = ColmapCamera {
            id: 3,
            model: "OPENCV_FISHEYE".into(),
            width: 64,
            height: 48,
            params: vec![60.0, 61.0, 32.0, 24.0, 0.01, 0.0, 0.0, 0.003],
        };
        let dir = views_dir(&model, true, true);
        let e = read_views(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains("camera 3 (OPENCV_FISHEYE)") && e.contains("cameras.bin"),
            "{e}"
        );
        let cap = read_capture(dir.path()).unwrap();
        assert!(cap.lenses.contains(&Distortion::Fisheye {
            k: [0.01, 0.0, 0.0, 0.003]
        }));
        // FULL_OPENCV: fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6, k4-k6 the rational denominator.
        model.cameras[2].model = "FULL_OPENCV".into();
        model.cameras[2].params = vec![
            60.0, 61.0, 32.0, 24.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0,
        ];
        let dir = views_dir(&model, false, true);
        assert!(read_capture(dir.path())
            .unwrap()
            .lenses
            .contains(&Distortion::RadialTangential {
                radial: [1.0, 2.0, 5.0, 0.0],
                rational: [6.0, 7.0, 8.0],
                tangential: [3.0, 4.0],
            }));
        // FOV is refused by both readers.
        model.cameras[2].model = "FOV".into();
        model.cameras[2].params = vec![60.0, 61.0, 32.0, 24.0, 0.9];
        let dir = views_dir(&model, false, true);
        let e = read_capture(dir.path()).unwrap_err().to_string();
        assert!(e.contains("camera 3 has model FOV"), "{e}");
        // SIMPLE_RADIAL with k = 0 is a pinhole.
        model.cameras[2] = ColmapCamera {
            id: 3,
            model: "SIMPLE_RADIAL".into(),
            width: 64,
            height: 48,
            params: vec![60.0, 32.0, 24.0, 0.0],
        };
        let dir = views_dir(&model, true, true);
        read_views(dir.path()).unwrap();
    }

    #[test]
    fn image_names_outside_the_views_directory_are_refused() {
        let (model, _) = known();
        let dir = views_dir(&model, false, true);
        let txt = dir.path().join("sparse/0/images.txt");
        let text = std::fs::read_to_string(&txt).unwrap();
        let name = &model.images[1].name;
        std::fs::write(&txt, text.replace(name.as_str(), "../elsewhere/0001.jpg")).unwrap();
        let e = super::super::cameras::read_views(dir.path())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("images.txt")
                && e.contains("../elsewhere/0001.jpg")
                && e.contains("outside the views directory"),
            "{e}"
        );
    }

    #[test]
    fn malformed_models_name_file_and_position() {
        let (model, _) = known();
        let dir = views_dir(&model, false, true);
        let sparse = dir.path().join("sparse/0");
        std::fs::write(
            sparse.join("cameras.txt"),
            "# c\n1 PINHOLE 64 48 70 71 32\n",
        )
        .unwrap();
        let e = read_model(&sparse).unwrap_err();
        assert_eq!(e.position(), Some(&Position::Line(2)), "{e}");
        assert!(
            e.to_string().contains("PINHOLE has 4 parameters, found 3"),
            "{e}"
        );
        std::fs::write(sparse.join("cameras.txt"), "1 PINHOL 64 48 70 71 32 24\n").unwrap();
        let e = read_model(&sparse).unwrap_err();
        assert_eq!(
            e.position(),
            Some(&Position::LineColumn { line: 1, column: 3 }),
            "{e}"
        );
        std::fs::write(sparse.join("cameras.txt"), "1 PINHOLE 64 4x8 70 71 32 24\n").unwrap();
        let e = read_model(&sparse).unwrap_err();
        assert_eq!(
            e.position(),
            Some(&Position::LineColumn {
                line: 1,
                column: 14
            }),
            "{e}"
        );
        std::fs::write(sparse.join("cameras.txt"), "1 PINHOLE 64 48 70 71 32 24\n").unwrap();
        std::fs::write(
            sparse.join("images.txt"),
            "1 1 0 0 0 0 0 1 7 img_00.png\n\n",
        )
        .unwrap();
        let e = super::super::cameras::read_views(dir.path())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("refers to camera 7") && e.contains("images.txt"),
            "{e}"
        );
        std::fs::write(
            sparse.join("images.txt"),
            "1 1 0 0 0 0 0 1 1 nothere.png\n\n",
        )
        .unwrap();
        let e = super::super::cameras::read_views(dir.path())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("missing image") && e.contains("nothere.png"),
            "{e}"
        );
        // Binary: truncated files name the byte where they end.
        let bdir = views_dir(&model, true, true);
        let cams = bdir.path().join("sparse/0/cameras.bin");
        let bytes = std::fs::read(&cams).unwrap();
        std::fs::write(&cams, &bytes[..bytes.len() - 3]).unwrap();
        let e = read_model(&bdir.path().join("sparse/0")).unwrap_err();
        assert!(
            matches!(e.position(), Some(Position::Byte(_)))
                && e.to_string().contains("cameras.bin"),
            "{e}"
        );
        std::fs::write(&cams, [255u8; 8]).unwrap();
        let e = read_model(&bdir.path().join("sparse/0")).unwrap_err();
        assert!(e.to_string().contains("does not fit"), "{e}");
    }
}
