//! The `synthetic_scene` stage: a furry animal with ground-truth strands and rendered views.
//!
//! Pipeline of the stage (each step in its own module):
//! 1. [`presets`]: a species (tiger, fox, cat, panda, bison) as a parametric quadruped in
//!    centimetres, with per-part fur and a colour pattern; `parts.<name>.<key>` overrides.
//! 2. [`body`]: the implicit body (smooth union of ellipsoids and round cones) in scene units,
//!    `1 unit = s_cm` cm with `s_cm = nose-to-rump length / 2` (the body is about 2 units long,
//!    as a reconstruction would normalise it; the scene records `s_cm` and the two eye centres
//!    so a metric-scale step has what a real capture would give it), and its skin mesh (surface
//!    nets) with per-vertex part labels.
//! 3. [`fur`]: roots, growth, clumping, colours.
//! 4. [`bvh`] + [`trace`]: a ray tracer of skin triangles and strand tubes with Kajiya-Kay
//!    shading, written for this stage only (it shares no code with `crate::render`).
//!
//! [`blender`] is the stage `blender_scene`: steps 1-2 as here, then Blender's own hair and
//! Cycles' views in place of steps 3-4 (the same parameters and outputs).
//!
//! What the stage chooses and why (written to `report.json` and the run log):
//! - Framing: cameras on a sphere around the centre of the skin's bounding box, at the distance
//!   where the skin's bounding sphere about that centre, grown by the longest fur, fills a 40
//!   degree field of view. Training views lie on a Fibonacci spiral over elevations -30..70
//!   degrees; held-out views on rings at -12, 8, 28 and 52 degrees, azimuths offset from the
//!   spiral. Square images, `fl_x = fl_y`, principal point at the centre.
//! - Pixel footprint `p` = width of a pixel at the camera distance (scene units). Everything
//!   that sets the cost of the scene follows from it ("model no more than the scene needs"):
//!   the skin mesh grid spacing is `p` of a provisional framing (from the primitives' boxes,
//!   slightly looser; at most 0.03 units); the base root density is
//!   `strands_per_px2 / p_cm^2` (default 1.5 strands per pixel of skin, times each part's
//!   relative `density`), which gives a few thousand strands at the quick size and tens of
//!   thousands at 256 px; segments are about `seg_px` pixels long (default 1, at least 2 per
//!   strand, 6 for curly fur); strands are tubes `width_px` pixels wide (default 0.7) at the
//!   root, tapering to 30 % at the tip. Real fur has thousands of strands per cm^2 of a few
//!   hundredths of a millimetre; like any reconstruction test at low resolution we use fewer,
//!   thicker strands, as many as it takes for the fur to read as a coat at this resolution.
//!   The `density_per_cm2` in `scene.json` is that of the GT strands as generated.
//! - Images: RGBA PNG (sRGB colour, straight alpha = coverage of the supersamples), object mask
//!   `NNN_mask.png` (alpha >= 0.5, then dilated or eroded by `mask_dilate_px` with a disc),
//!   fur mask `NNN_fur.png` (at least half the samples hit a strand first; not dilated),
//!   depth `NNN_depth.exr` (view-axis depth of the covered samples, their mean; 0 = nothing).
//! - Stability knobs: `noise_sigma` adds N(0, sigma) to the RGB of covered pixels (seeded per
//!   view); `jitter_deg` / `jitter_cm` perturb the *written* cameras (rotation about a random
//!   axis by an angle ~ N(0, jitter_deg) about the camera centre, translation with per-axis
//!   std `jitter_cm / sqrt(3)`), never the rendering.
//! - `scene.json`: `s_cm`, `eyes`, `eye_separation_cm` (the species value, which equals the
//!   distance of the GT eye centres), and per part `fur`, `mean_length_cm` (mean arc length of
//!   the part's GT strands), `density_per_cm2` (strands / skin area of the part, areas split by
//!   vertex labels), `mean_thickness_cm` (mean over the part's strands of the height of the
//!   strand's highest point above its root's tangent plane: the fur-layer thickness a shell
//!   fitted around the fur would see).
//! - Ground truth and what is not: `skin.obj`, `strands.hair`, `regrown.hair` and the per-part
//!   statistics of `scene.json` are ground truth and may only reach `gt_*` ports (metrics).
//!   `labels.obj` (the skin's part groups, the stand-in for the mesh a user labels by hand) and
//!   `scene.json`'s `eyes` / `eye_separation_cm` (what a user clicks and looks up) are the
//!   capture's own data. `regrown.hair` is the same animal grown again with
//!   [`regrow_seed`]`(seed)`: scored against `strands.hair` it gives the scene's ceiling, what
//!   any reconstruction could reach when everything but the seed's draws is right.
//! - Overrides: `[stages.NAME.parts.<part>]` with `length_cm` (mean strand length),
//!   `length_jitter` (lengths uniform in `mean * [1 - j, 1 + j]`), `density` (relative to the
//!   footprint-derived base density), `density_per_cm2` (absolute, replaces the footprint rule
//!   for that part), `direction` (`[x, y, z]` in the animal frame: +x tail to nose, +y up, +z the
//!   animal's left; replaces the flow field on that part's primitives), `lift_deg`, `curl`,
//!   `clump`, `gravity` and `color` (linear RGB). Non-fur parts (eyes, nose, pads; the bison's
//!   horns and hooves) take only `color`. Unknown parts or keys fail in `validate` with the list
//!   of what is allowed; settings that would grow more than [`MAX_STRANDS`] strands fail too.
//! - Determinism: every random stream is a seeded ChaCha8 (or a SplitMix64 hash of the seed for
//!   per-pixel jitter); parallel loops collect in index order. The only non-deterministic bytes
//!   are the timings under `seconds` in `report.json`.

pub mod blender;
pub mod body;
pub mod bvh;
pub mod fur;
pub mod presets;
pub mod trace;

use std::time::Instant;

use fure_stage_api::{
    ensure_finite, ParamSpec, ParamType, Params, PortSpec, Stage, StageContext, StageError,
};
use glam::{Mat4, Quat, Vec3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde_json::json;

use crate::data::camera::{Camera, CameraSet};
use crate::data::image::ImageF32;
use crate::data::mesh::Mesh;
use crate::data::scene::{PartInfo, SceneInfo};
use crate::formats;
use body::Body;
use fur::{gauss, mix, FurConfig};
use presets::{Preset, Shape, PRESETS};
use trace::Scene;

/// Most GT strands the stage will grow (memory and render time guard).
pub const MAX_STRANDS: usize = 3_000_000;

/// Half the field of view (degrees).
const HALF_FOV_DEG: f32 = 20.0;

/// The `synthetic_scene` stage.
pub struct SyntheticSceneStage;

/// Sizes: (views, test views, resolution, supersample).
fn size_defaults(size: &str) -> (usize, usize, u32, u32) {
    match size {
        "quick" => (8, 2, 96, 2),
        _ => (36, 8, 256, 3),
    }
}

/// Everything the stage computed, for tests and the benchmark.
pub struct Generated {
    pub preset: Preset,
    pub s_cm: f32,
    pub mesh: Mesh,
    pub fur: fur::Fur,
    /// The same animal regrown with another seed ([`regrow_seed`]): the ceiling a reconstruction
    /// can be scored against, since it differs from `fur` only in what the seed decides.
    pub regrown: fur::Fur,
    pub cameras: CameraSet,
    pub scene: Scene,
    pub pixel_units: f32,
    /// Skin grid spacing (scene units).
    pub cell: f32,
    pub supersample: u32,
}

/// Resolved settings.
#[derive(Debug, Clone)]
pub struct Settings {
    pub preset: String,
    pub size: String,
    pub seed: u64,
    pub views: usize,
    pub test_views: usize,
    pub resolution: u32,
    pub supersample: u32,
    pub strands_per_px2: f32,
    pub width_px: f32,
    pub seg_px: f32,
    pub noise_sigma: f32,
    pub jitter_deg: f32,
    pub jitter_cm: f32,
    pub mask_dilate_px: i64,
    pub parts: std::collections::BTreeMap<String, fure_stage_api::Value>,
    /// `Some` when Blender grows and renders the fur ([`blender`]).
    pub blender: Option<blender::BlenderSettings>,
}

fure_stage_api::stage_params! {
    /// The `synthetic_scene` stage's parameters (unset sizes follow `size`).
    pub struct SyntheticSceneParams {
        /// species preset
        preset: String = string("tiger").choices(PRESETS),
        /// quick (tests, seconds) or default
        size: String = string("default").choices(&["quick", "default"]),
        /// random seed of fur, jitter and noise
        seed: u64 = int(0).min(0.0),
        /// training views (quick 8, default 36)
        views: Option<usize> = optional(ParamType::Int).range(1.0, 1000.0),
        /// held-out views (quick 2, default 8)
        test_views: Option<usize> = optional(ParamType::Int).range(0.0, 1000.0),
        /// square image size in pixels (quick 96, default 256)
        resolution: Option<usize> = optional(ParamType::Int).range(16.0, 4096.0),
        /// samples per pixel side (quick 2, default 3; kind blender_scene takes blender_samples instead)
        supersample: Option<usize> = optional(ParamType::Int).range(1.0, 8.0),
        /// GT roots per pixel-footprint area of skin (base density)
        strands_per_px2: f32 = float(1.5).range(0.01, 50.0),
        /// strand tube width at the root, in pixels
        width_px: f32 = float(0.7).range(0.05, 8.0),
        /// target segment length, in pixels
        seg_px: f32 = float(1.0).range(0.25, 20.0),
        /// std of Gaussian noise added to image RGB
        noise_sigma: f32 = float(0.0).range(0.0, 1.0),
        /// std of the rotation applied to written cameras (degrees)
        jitter_deg: f32 = float(0.0).range(0.0, 45.0),
        /// RMS translation applied to written cameras (cm)
        jitter_cm: f32 = float(0.0).range(0.0, 1000.0),
        /// dilate (> 0) or erode (< 0) the object masks by this radius
        mask_dilate_px: i64 = int(0).range(-50.0, 50.0),
        /// per-part overrides: parts.<part> = { length_cm, length_jitter, density, density_per_cm2, direction, lift_deg, curl, clump, gravity, color }
        parts: std::collections::BTreeMap<String, fure_stage_api::Value> = table(),
        /// kind blender_scene: how far the hair rises along the normal against lying toward the tail and the ground (0.15 flat, about 11 degrees; 0.6 about 40; default 0.3)
        blender_rise: Option<f32> = optional(ParamType::Float).range(0.0, 4.0),
        /// kind blender_scene: hair length in cm (default: the mean length of the preset's own fur)
        blender_length_cm: Option<f32> = optional(ParamType::Float).range(0.01, 1000.0),
        /// kind blender_scene: Cycles samples per pixel (default 16)
        blender_samples: Option<usize> = optional(ParamType::Int).range(1.0, 4096.0),
    }
}

impl Settings {
    pub fn from_params(p: &Params) -> Result<Settings, StageError> {
        Settings::from_params_of(p, false)
    }

    /// The settings of kind `synthetic_scene` (`blender` false) or `blender_scene` (true).
    pub fn from_params_of(p: &Params, blender: bool) -> Result<Settings, StageError> {
        let p = SyntheticSceneParams::from_params(p)?;
        let (v, tv, res, ss) = size_defaults(&p.size);
        let blender = blender_settings(&p, blender)?;
        Ok(Settings {
            preset: p.preset,
            seed: p.seed,
            views: p.views.unwrap_or(v),
            test_views: p.test_views.unwrap_or(tv),
            resolution: p.resolution.unwrap_or(res as usize) as u32,
            supersample: p.supersample.unwrap_or(ss as usize) as u32,
            strands_per_px2: p.strands_per_px2,
            width_px: p.width_px,
            seg_px: p.seg_px,
            noise_sigma: p.noise_sigma,
            jitter_deg: p.jitter_deg,
            jitter_cm: p.jitter_cm,
            mask_dilate_px: p.mask_dilate_px,
            parts: p.parts,
            size: p.size,
            blender,
        })
    }

    /// The default settings of a size (for tests and the benchmark).
    pub fn new(preset: &str, size: &str) -> Settings {
        let (views, test_views, resolution, supersample) = size_defaults(size);
        Settings {
            preset: preset.to_string(),
            size: size.to_string(),
            seed: 0,
            views,
            test_views,
            resolution,
            supersample,
            strands_per_px2: 1.5,
            width_px: 0.7,
            seg_px: 1.0,
            noise_sigma: 0.0,
            jitter_deg: 0.0,
            jitter_cm: 0.0,
            mask_dilate_px: 0,
            parts: Default::default(),
            blender: None,
        }
    }
}

/// The Blender renderer's settings for kind `blender_scene` (`blender`), `None` for
/// `synthetic_scene`; the options that only one kind reads fail on the other.
fn blender_settings(
    p: &SyntheticSceneParams,
    blender: bool,
) -> Result<Option<blender::BlenderSettings>, StageError> {
    if !blender {
        for (name, set) in [
            ("blender_rise", p.blender_rise.is_some()),
            ("blender_length_cm", p.blender_length_cm.is_some()),
            ("blender_samples", p.blender_samples.is_some()),
        ] {
            if set {
                return Err(StageError::param(
                    name,
                    "is read only by kind `blender_scene`",
                ));
            }
        }
        return Ok(None);
    }
    for (name, set) in [
        ("seg_px", p.seg_px != 1.0),
        ("noise_sigma", p.noise_sigma != 0.0),
        ("jitter_deg", p.jitter_deg != 0.0),
        ("jitter_cm", p.jitter_cm != 0.0),
        ("mask_dilate_px", p.mask_dilate_px != 0),
    ] {
        if set {
            return Err(StageError::param(
                name,
                "is not read by kind `blender_scene` (Blender grows the hair and Cycles renders the views); remove it",
            ));
        }
    }
    if p.seed >= blender::MAX_SEED {
        return Err(StageError::param(
            "seed",
            format!(
                "must be below {} for kind `blender_scene` (Blender's particle seed is a 32-bit int), found {}",
                blender::MAX_SEED,
                p.seed
            ),
        ));
    }
    Ok(Some(blender::BlenderSettings {
        rise: p.blender_rise.unwrap_or(blender::DEFAULT_RISE),
        length_cm: p.blender_length_cm,
        samples: p.blender_samples.unwrap_or(blender::DEFAULT_SAMPLES),
    }))
}

/// Tight axis-aligned bounds of the preset's primitives (scene units).
fn body_bounds(body: &Body) -> (Vec3, Vec3) {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for p in &body.prims {
        let (a, b) = match &p.shape {
            Shape::RoundCone { a, b, ra, rb } => (
                (*a - Vec3::splat(*ra)).min(*b - Vec3::splat(*rb)),
                (*a + Vec3::splat(*ra)).max(*b + Vec3::splat(*rb)),
            ),
            Shape::Ellipsoid { c, r, rot } => {
                let m = glam::Mat3::from_quat(*rot);
                let e = Vec3::new(
                    m.row(0).abs().dot(*r),
                    m.row(1).abs().dot(*r),
                    m.row(2).abs().dot(*r),
                );
                (*c - e, *c + e)
            }
        };
        lo = lo.min(a);
        hi = hi.max(b);
    }
    (lo, hi)
}

fn look_at(eye: Vec3, target: Vec3) -> Mat4 {
    Mat4::look_at_rh(eye, target, Vec3::Y).inverse()
}

/// Builds the whole scene (geometry, fur, cameras, tracer) without rendering or writing.
pub fn generate(st: &Settings) -> Result<Generated, StageError> {
    let mut preset = presets::preset(&st.preset)?;
    presets::apply_overrides(&mut preset, &st.parts)?;
    let s_cm = preset.body_length_cm / 2.0;
    let body = Body::from_preset(&preset, s_cm);
    let max_len = longest_fur(&preset, s_cm);
    let half = HALF_FOV_DEG.to_radians();
    let res = st.resolution;
    let (mesh, cell) = skin_mesh(&body, max_len, half, res)?;
    let framing = Framing::around_skin(&mesh, max_len, half, res);
    let pixel_units = framing.pixel_units;
    let pixel_cm = pixel_units * s_cm;
    let cfg = FurConfig {
        s_cm,
        base_density_per_cm2: st.strands_per_px2 / (pixel_cm * pixel_cm),
        seg_len: st.seg_px * pixel_units,
        width: st.width_px * pixel_units,
        seed: st.seed,
    };
    check_strand_budget(&preset, &mesh, &cfg)?;
    let fur = fur::grow(&preset, &body, &mesh, &cfg);
    let regrown = fur::grow(
        &preset,
        &body,
        &mesh,
        &FurConfig {
            seed: regrow_seed(st.seed),
            ..cfg.clone()
        },
    );
    ensure_finite(
        "GT strands",
        fur.strands.points.iter().flat_map(|p| p.to_array()),
    )?;
    let cameras = framing.cameras(st, half);
    // Tracer.
    let shiny = shiny_vertices(&preset, &mesh);
    let colors = fur::skin_colors(&preset, &mesh, s_cm, st.seed);
    let scene = Scene::new(&mesh, colors, shiny, &fur.strands);
    Ok(Generated {
        preset,
        s_cm,
        mesh,
        fur,
        regrown,
        cameras,
        scene,
        pixel_units,
        cell,
        supersample: st.supersample,
    })
}

/// The longest strand any fur part can grow (scene units).
fn longest_fur(preset: &Preset, s_cm: f32) -> f32 {
    preset
        .parts
        .iter()
        .map(|(_, f)| f.length_cm * (1.0 + f.length_jitter))
        .fold(0.0, f32::max)
        / s_cm
}

/// The skin mesh and its grid spacing, the pixel footprint of a provisional framing (from the
/// primitives' bounds plus the longest fur `max_len`), at most 0.03 units; fails when the mesh
/// is not finite or empty.
fn skin_mesh(body: &Body, max_len: f32, half: f32, res: u32) -> Result<(Mesh, f32), StageError> {
    let (lo, hi) = body_bounds(body);
    let r0 = (hi - lo).length() * 0.5 + max_len;
    let cell = (2.0 * r0 / half.sin() * half.tan() / res as f32).min(0.03);
    let mesh = body.mesh(cell);
    ensure_finite(
        "skin mesh",
        mesh.positions.iter().flat_map(|p| p.to_array()),
    )?;
    if mesh.triangles.is_empty() {
        return Err(StageError::failed("the skin mesh came out empty"));
    }
    Ok((mesh, cell))
}

/// Refuses settings that would grow more than [`MAX_STRANDS`] strands, naming the part that
/// would grow the most.
fn check_strand_budget(preset: &Preset, mesh: &Mesh, cfg: &FurConfig) -> Result<(), StageError> {
    let areas = fur::part_areas_cm2(mesh, cfg.s_cm);
    let mut expected = 0.0f64;
    let mut biggest = ("", 0.0f64);
    for ((name, fp), area) in preset.parts.iter().zip(&areas) {
        if fp.fur {
            let d = fp
                .density_per_cm2
                .unwrap_or(cfg.base_density_per_cm2 * fp.density) as f64;
            expected += d * area;
            if d * area > biggest.1 {
                biggest = (name, d * area);
            }
        }
    }
    if expected > MAX_STRANDS as f64 {
        return Err(StageError::param(
            format!("parts.{}", biggest.0),
            format!(
                "these settings would grow about {expected:.0} GT strands (most on `{}`), more than the \
                 limit of {MAX_STRANDS}; lower the densities, `strands_per_px2` or `resolution`",
                biggest.0
            ),
        ));
    }
    Ok(())
}

/// The final framing: cameras look at the centre of the skin's bounding box from the distance
/// where the skin's bounding sphere about it, grown by the longest fur, fills the field of view.
struct Framing {
    centre: Vec3,
    dist: f32,
    /// Width of a pixel at the camera distance (scene units).
    pixel_units: f32,
    res: u32,
}

impl Framing {
    /// The framing of `mesh` with fur up to `max_len` long, half field of view `half` (radians)
    /// and square images of `res` pixels.
    fn around_skin(mesh: &Mesh, max_len: f32, half: f32, res: u32) -> Framing {
        let (mlo, mhi) = mesh.bounds();
        let centre = (mlo + mhi) * 0.5;
        let radius = mesh
            .positions
            .iter()
            .map(|p| (*p - centre).length())
            .fold(0.0, f32::max)
            + max_len;
        let dist = radius / half.sin();
        let pixel_units = 2.0 * dist * half.tan() / res as f32;
        Framing {
            centre,
            dist,
            pixel_units,
            res,
        }
    }

    /// Training views on a Fibonacci spiral over elevations -30..70 degrees and held-out views
    /// on four elevation rings, azimuths offset from the spiral.
    fn cameras(&self, st: &Settings, half: f32) -> CameraSet {
        let res = self.res;
        let f = 0.5 * res as f32 / half.tan();
        let mk = |i: usize, el: f32, az: f32, dir: &str| -> Camera {
            let eye = self.centre
                + self.dist * Vec3::new(el.cos() * az.cos(), el.sin(), el.cos() * az.sin());
            Camera {
                file_path: format!("{dir}/{i:03}.png"),
                c2w: look_at(eye, self.centre),
                fx: f,
                fy: f,
                cx: 0.5 * res as f32,
                cy: 0.5 * res as f32,
                width: res,
                height: res,
            }
        };
        let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
        let (z0, z1) = ((-30f32).to_radians().sin(), 70f32.to_radians().sin());
        let train: Vec<Camera> = (0..st.views)
            .map(|i| {
                let z = z0 + (z1 - z0) * (i as f32 + 0.5) / st.views as f32;
                mk(i, z.asin(), i as f32 * golden, "train")
            })
            .collect();
        let rings = [-12f32, 8.0, 28.0, 52.0];
        let test: Vec<Camera> = (0..st.test_views)
            .map(|i| {
                let az = (i as f32 + 0.5) * std::f32::consts::TAU / st.test_views as f32 + 0.35;
                mk(i, rings[i % 4].to_radians(), az, "test")
            })
            .collect();
        CameraSet { train, test }
    }
}

/// Per skin vertex, whether the tracer shades it as a shiny part (eyes and nose).
fn shiny_vertices(preset: &Preset, mesh: &Mesh) -> Vec<bool> {
    mesh.part
        .iter()
        .map(|&p| {
            preset
                .parts
                .get(p as usize)
                .map(|(n, _)| *n == "eyes" || *n == "nose")
                .unwrap_or(false)
        })
        .collect()
}

/// The written camera: `c` perturbed by the pose-jitter knobs (deterministic per view).
fn jittered(c: &Camera, st: &Settings, s_cm: f32, view: u64) -> Camera {
    if st.jitter_deg <= 0.0 && st.jitter_cm <= 0.0 {
        return c.clone();
    }
    let mut rng = ChaCha8Rng::seed_from_u64(mix(st.seed ^ 0x00a1_77e7 ^ mix(view)));
    let axis = Vec3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng))
        .try_normalize()
        .unwrap_or(Vec3::Y);
    let ang = st.jitter_deg.to_radians() * gauss(&mut rng);
    let sd = st.jitter_cm / s_cm / 3f32.sqrt();
    let dt = Vec3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * sd;
    let mut out = c.clone();
    out.c2w =
        Mat4::from_translation(dt) * c.c2w * Mat4::from_quat(Quat::from_axis_angle(axis, ang));
    out
}

/// Binary mask from `src` (>= 0.5), dilated (r > 0) or eroded (r < 0) by a disc of radius |r|.
fn morph_mask(src: &ImageF32, ch: usize, r: i64) -> ImageF32 {
    let (w, h) = (src.width as i64, src.height as i64);
    let c = src.channels as usize;
    let on: Vec<bool> = (0..(w * h) as usize)
        .map(|i| src.data[i * c + ch] >= 0.5)
        .collect();
    let mut out = ImageF32::new(src.width, src.height, 1);
    let rr = r.abs();
    for y in 0..h {
        for x in 0..w {
            let v = if r == 0 {
                on[(y * w + x) as usize]
            } else {
                let dil = r > 0;
                let mut acc = !dil;
                'n: for dy in -rr..=rr {
                    for dx in -rr..=rr {
                        if dx * dx + dy * dy > rr * rr {
                            continue;
                        }
                        let (xx, yy) = (x + dx, y + dy);
                        let s =
                            xx >= 0 && yy >= 0 && xx < w && yy < h && on[(yy * w + xx) as usize];
                        if dil && s {
                            acc = true;
                            break 'n;
                        }
                        if !dil && !s {
                            acc = false;
                            break 'n;
                        }
                    }
                }
                acc
            };
            out.data[(y * w + x) as usize] = if v { 1.0 } else { 0.0 };
        }
    }
    out
}

/// Renders and writes every view into `dir`; returns the number of primary rays.
fn render_views(
    g: &Generated,
    st: &Settings,
    dir: &std::path::Path,
    progress: &dyn fure_stage_api::Progress,
) -> Result<(u64, CameraSet), StageError> {
    let mut rays = 0u64;
    let mut written = CameraSet::default();
    let all: Vec<(bool, usize, &Camera)> = g
        .cameras
        .train
        .iter()
        .enumerate()
        .map(|(i, c)| (false, i, c))
        .chain(g.cameras.test.iter().enumerate().map(|(i, c)| (true, i, c)))
        .collect();
    progress.set_total(all.len() as u64);
    for (k, (is_test, _i, cam)) in all.into_iter().enumerate() {
        progress.check_interrupted()?;
        progress.message(&format!("rendering {}", cam.file_path));
        let mut frame = g.scene.render(cam, st.supersample, st.seed, k as u64);
        rays += cam.width as u64 * cam.height as u64 * (st.supersample as u64).pow(2);
        if st.noise_sigma > 0.0 {
            let mut rng =
                ChaCha8Rng::seed_from_u64(mix(st.seed ^ 0x7015e_u64 ^ mix(k as u64 + 17)));
            for px in frame.rgba.data.chunks_mut(4) {
                if px[3] > 0.0 {
                    for v in &mut px[..3] {
                        *v = (*v + st.noise_sigma * gauss(&mut rng)).clamp(0.0, 1.0);
                    }
                }
            }
        }
        ensure_finite("rendered image", frame.rgba.data.iter().copied())?;
        ensure_finite("rendered depth", frame.depth.data.iter().copied())?;
        let base = cam.file_path.trim_end_matches(".png");
        formats::images::write_png(dir.join(&cam.file_path), &frame.rgba)?;
        formats::images::write_png(
            dir.join(format!("{base}_mask.png")),
            &morph_mask(&frame.rgba, 3, st.mask_dilate_px),
        )?;
        formats::images::write_png(
            dir.join(format!("{base}_fur.png")),
            &morph_mask(&frame.fur, 0, 0),
        )?;
        formats::images::write_exr(dir.join(format!("{base}_depth.exr")), &frame.depth)?;
        let wc = jittered(cam, st, g.s_cm, k as u64);
        if is_test {
            written.test.push(wc);
        } else {
            written.train.push(wc);
        }
        progress.advance(1);
    }
    Ok((rays, written))
}

/// The GT scene description.
pub fn scene_info(g: &Generated) -> SceneInfo {
    scene_info_of(g, &g.fur.stats)
}

/// The scene description of `g`'s body with per-part fur statistics `stats` (this stage's fur,
/// or the hair another renderer grew on the same skin); a bare part's length and thickness are 0.
pub fn scene_info_of(
    g: &Generated,
    stats: &std::collections::BTreeMap<String, fur::PartStats>,
) -> SceneInfo {
    let mut parts = std::collections::BTreeMap::new();
    for (name, fp) in &g.preset.parts {
        let st = stats.get(*name).cloned().unwrap_or_default();
        let n = st.strands.max(1) as f64;
        parts.insert(
            name.to_string(),
            PartInfo {
                fur: fp.fur,
                mean_length_cm: Some(if fp.fur {
                    (st.sum_length_cm / n) as f32
                } else {
                    0.0
                }),
                density_per_cm2: Some(st.density_per_cm2),
                mean_thickness_cm: Some(if fp.fur {
                    (st.sum_height_cm / n) as f32
                } else {
                    0.0
                }),
            },
        );
    }
    SceneInfo {
        s_cm: Some(g.s_cm),
        eyes: [g.preset.eyes_cm[0] / g.s_cm, g.preset.eyes_cm[1] / g.s_cm],
        eye_separation_cm: Some(g.preset.eye_separation_cm()),
        parts,
    }
}

impl Stage for SyntheticSceneStage {
    fn kind(&self) -> &'static str {
        "synthetic_scene"
    }
    fn version(&self) -> u32 {
        3
    }
    fn doc(&self) -> &'static str {
        "A synthetic furry animal (tiger, fox, lynx, sheepdog, poodle, cat, panda, bison, wolf): implicit body -> labelled skin \
         mesh, ground-truth strands, and ray-traced RGBA / mask / fur-mask / depth views on a sphere \
         (training and held-out) with transforms.json; scene.json holds s_cm, the eyes and per-part \
         GT fur statistics. Per-part overrides in `parts.<name>`."
    }
    fn params(&self) -> Vec<ParamSpec> {
        SyntheticSceneParams::specs()
    }
    fn inputs(&self, _params: &Params) -> Vec<PortSpec> {
        Vec::new()
    }
    fn outputs(&self, _params: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::dir("views", "transforms.json, transforms_test.json, train/ and test/ images, masks, fur masks, depth"),
            PortSpec::file("skin", "obj", "GT skin mesh, one group per part"),
            PortSpec::file("labels", "obj", "the labelled mesh a user would provide (the skin's part groups); not ground truth for the metrics"),
            PortSpec::file("strands", "hair", "GT strands (Cem Yuksel .hair)"),
            PortSpec::file("regrown", "hair", "GT: the same animal regrown with another seed, for the per-scene ceiling of the strand metrics"),
            PortSpec::file("strands_ply", "ply", "GT strands as PLY polylines with part labels"),
            PortSpec::file("scene", "json", "scene.json: s_cm, eyes, per-part GT fur statistics"),
            PortSpec::file("report", "json", "what the stage chose: strands, segments, resolution, rays, seconds"),
        ]
    }
    fn validate(&self, params: &Params) -> Result<(), StageError> {
        let st = Settings::from_params(params)?;
        let p = presets::preset(&st.preset)?;
        presets::validate_overrides(&p, &st.parts)
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let st = Settings::from_params(ctx.params)?;
        run_settings(&st, ctx)
    }
}

/// The seed of the regrown animal (`regrown.hair`): far from any seed a sweep would use.
pub fn regrow_seed(seed: u64) -> u64 {
    seed ^ 0x5eed_0000_0001_0000
}

/// Generates, renders and writes everything for `st` into the context's outputs.
pub fn run_settings(st: &Settings, ctx: &StageContext<'_>) -> Result<(), StageError> {
    let t0 = Instant::now();
    ctx.progress.message("building body and fur");
    let g = generate(st)?;
    let t_build = t0.elapsed().as_secs_f64();
    let views_dir = ctx.output("views")?;
    let t1 = Instant::now();
    let (rays, written) = render_views(&g, st, views_dir, ctx.progress)?;
    let t_render = t1.elapsed().as_secs_f64();
    formats::cameras::write_views(views_dir, &written)?;
    formats::obj::write_obj(ctx.output("skin")?, &g.mesh)?;
    // The labelled mesh a user would draw by hand (module doc, "Ground truth"): the skin's part
    // groups, written as its own file so the GT skin can change without touching the labels.
    formats::obj::write_obj(ctx.output("labels")?, &g.mesh)?;
    formats::hair::write_hair(ctx.output("strands")?, &g.fur.strands)?;
    formats::hair::write_hair(ctx.output("regrown")?, &g.regrown.strands)?;
    formats::ply::write_ply_strands(ctx.output("strands_ply")?, &g.fur.strands)?;
    formats::json::write_json(ctx.output("scene")?, &scene_info(&g))?;
    let n = g.fur.strands.len();
    let segs = g.fur.strands.segment_count();
    let pixel_cm = g.pixel_units * g.s_cm;
    let lines = [
        format!(
            "preset {} ({}), s_cm {:.2} cm per unit, resolution {} px, pixel {:.3} cm",
            st.preset, st.size, g.s_cm, st.resolution, pixel_cm
        ),
        format!(
            "skin mesh: {} vertices, {} triangles (grid {:.4} units)",
            g.mesh.positions.len(),
            g.mesh.triangles.len(),
            g.cell
        ),
        format!(
            "GT strands {n}, segments {segs} ({:.2} per strand), width {:.3} cm",
            segs as f64 / n.max(1) as f64,
            st.width_px * pixel_cm
        ),
        format!(
            "rendered {} views, {rays} rays in {t_render:.2} s ({:.2} Mrays/s)",
            written.train.len() + written.test.len(),
            rays as f64 / t_render.max(1e-9) / 1e6
        ),
    ];
    for l in &lines {
        ctx.progress.note(l);
    }
    let report = json!({
        "preset": st.preset,
        "size": st.size,
        "seed": st.seed,
        "s_cm": g.s_cm,
        "resolution": st.resolution,
        "supersample": st.supersample,
        "views": written.train.len(),
        "test_views": written.test.len(),
        "fov_deg": 2.0 * HALF_FOV_DEG,
        "pixel_cm": pixel_cm,
        "skin": { "vertices": g.mesh.positions.len(), "triangles": g.mesh.triangles.len(), "grid_units": g.cell },
        "strands": n,
        "segments": segs,
        "segments_per_strand": segs as f64 / n.max(1) as f64,
        "strand_width_cm": st.width_px * pixel_cm,
        "base_density_per_cm2": st.strands_per_px2 / (pixel_cm * pixel_cm),
        "rays": rays,
        "why": {
            "strands": format!("{} roots per pixel footprint ({:.3} cm)^2 of skin, times each part's relative density", st.strands_per_px2, pixel_cm),
            "segments": format!("segments about {} px ({:.3} cm) long, at least 2 per strand (6 when curly)", st.seg_px, st.seg_px * pixel_cm),
            "width": format!("tubes {} px wide so the fur reads as a coat at {} px", st.width_px, st.resolution),
            "skin": "surface-nets grid spacing = one pixel footprint of a provisional, looser framing (at most 0.03 units)",
        },
        "notes": lines,
        "seconds": { "build": t_build, "render": t_render, "total": t0.elapsed().as_secs_f64(), "rays_per_second": rays as f64 / t_render.max(1e-9) },
    });
    formats::json::write_json(ctx.output("report")?, &report)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use fure_stage_api::{NoProgress, Value};
    use std::collections::BTreeMap;
    use std::path::Path;

    const FILES: [(&str, &str); 8] = [
        ("views", "views"),
        ("skin", "skin.obj"),
        ("labels", "labels.obj"),
        ("strands", "strands.hair"),
        ("regrown", "regrown.hair"),
        ("strands_ply", "strands_ply.ply"),
        ("scene", "scene.json"),
        ("report", "report.json"),
    ];

    fn run_to(dir: &Path, st: &Settings) -> Result<(), StageError> {
        let outputs: BTreeMap<String, std::path::PathBuf> = FILES
            .iter()
            .map(|(p, f)| (p.to_string(), dir.join(f)))
            .collect();
        std::fs::create_dir_all(dir.join("views")).unwrap();
        let params = Params::default();
        let ctx = StageContext {
            name: "scene",
            params: &params,
            inputs: BTreeMap::new(),
            outputs,
            progress: &NoProgress,
        };
        run_settings(st, &ctx)
    }

    fn params_with(extra: &[(&str, Value)]) -> Params {
        let mut p = Params::default();
        for s in SyntheticSceneStage.params() {
            if let Some(d) = s.default {
                p.0.insert(s.name.to_string(), d);
            }
        }
        for (k, v) in extra {
            p.0.insert(k.to_string(), v.clone());
        }
        p
    }

    #[test]
    fn each_renderer_refuses_the_options_only_the_other_reads() {
        use blender::BlenderSceneStage;
        let err = |stage: &dyn Stage, extra: &[(&str, Value)]| {
            stage
                .validate(&params_with(extra))
                .err()
                .map(|e| e.to_string())
        };
        let ours = err(&SyntheticSceneStage, &[("blender_rise", Value::Float(0.6))]).unwrap();
        assert!(
            ours.contains("blender_rise") && ours.contains("blender_scene"),
            "{ours}"
        );
        let theirs = err(&BlenderSceneStage, &[("noise_sigma", Value::Float(0.1))]).unwrap();
        assert!(
            theirs.contains("noise_sigma") && theirs.contains("remove it"),
            "{theirs}"
        );
        let seed = err(&BlenderSceneStage, &[("seed", Value::Int(1 << 40))]).unwrap();
        assert!(seed.contains("32-bit"), "{seed}");
        // The shared parameters, `supersample` included (unused by Blender), and Blender's own.
        assert_eq!(
            err(
                &BlenderSceneStage,
                &[
                    ("supersample", Value::Int(3)),
                    ("blender_rise", Value::Float(0.6))
                ]
            ),
            None
        );
        let st =
            Settings::from_params_of(&params_with(&[("blender_samples", Value::Int(4))]), true)
                .unwrap();
        assert_eq!(
            st.blender,
            Some(blender::BlenderSettings {
                rise: blender::DEFAULT_RISE,
                length_cm: None,
                samples: 4
            })
        );
        assert_eq!(
            Settings::from_params(&params_with(&[])).unwrap().blender,
            None
        );
    }

    /// All files under `dir` (relative path -> bytes), sorted.
    fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
        let mut out = BTreeMap::new();
        let mut stack = vec![dir.to_path_buf()];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(&d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    stack.push(p);
                } else {
                    out.insert(
                        p.strip_prefix(dir).unwrap().to_string_lossy().to_string(),
                        std::fs::read(&p).unwrap(),
                    );
                }
            }
        }
        out
    }

    fn tiny(seed: u64) -> Settings {
        let mut st = Settings::new("cat", "quick");
        st.seed = seed;
        st.views = 2;
        st.test_views = 1;
        st.resolution = 40;
        st.supersample = 1;
        st
    }

    #[test]
    fn quick_tiger_runs_and_writes_all_outputs() {
        let p = params_with(&[("size", Value::Str("quick".into()))]);
        SyntheticSceneStage.validate(&p).unwrap();
        let st = Settings::from_params(&p).unwrap();
        assert_eq!((st.views, st.test_views, st.resolution), (8, 2, 96));
        let dir = tempfile::tempdir().unwrap();
        run_to(dir.path(), &st).unwrap();
        let views = dir.path().join("views");
        let cams = formats::cameras::read_views(&views).unwrap();
        assert_eq!((cams.train.len(), cams.test.len()), (8, 2));
        for c in cams.train.iter().chain(&cams.test) {
            let base = c.file_path.trim_end_matches(".png");
            for f in [
                c.file_path.clone(),
                format!("{base}_mask.png"),
                format!("{base}_fur.png"),
                format!("{base}_depth.exr"),
            ] {
                assert!(views.join(&f).is_file(), "missing {f}");
            }
            // The animal is in view but does not fill it.
            let img = formats::images::read_png(views.join(&c.file_path)).unwrap();
            assert_eq!(img.channels, 4);
            let cov = img.data.chunks(4).filter(|p| p[3] > 0.5).count() as f32 / (96.0 * 96.0);
            assert!(cov > 0.03 && cov < 0.8, "{}: coverage {cov}", c.file_path);
            let fur = formats::images::read_png(views.join(format!("{base}_fur.png"))).unwrap();
            let nfur = fur.data.iter().filter(|v| **v > 0.5).count() as f32 / (96.0 * 96.0);
            assert!(
                nfur > 0.5 * cov,
                "{}: fur {nfur} of coverage {cov}",
                c.file_path
            );
        }
        let scene: SceneInfo = formats::json::read_json(dir.path().join("scene.json")).unwrap();
        let sep = (scene.eyes[0] - scene.eyes[1]).length() * scene.s_cm.unwrap();
        assert!((sep - scene.eye_separation_cm.unwrap()).abs() < 1e-3 * sep);
        let preset = presets::preset("tiger").unwrap();
        for (name, fp) in &preset.parts {
            let info = &scene.parts[*name];
            assert_eq!(info.fur, fp.fur, "{name}");
            if !fp.fur {
                assert_eq!(info.density_per_cm2, Some(0.0), "{name} has roots");
            } else {
                assert!(info.mean_thickness_cm.unwrap() > 0.0);
            }
        }
        let t = &scene.parts["torso"];
        let want = preset.parts[preset.part_index("torso").unwrap()]
            .1
            .length_cm;
        assert!(
            (t.mean_length_cm.unwrap() / want - 1.0).abs() < 0.03,
            "{:?} vs {want}",
            t.mean_length_cm
        );
        let strands = formats::hair::read_hair(dir.path().join("strands.hair")).unwrap();
        assert!(
            strands.len() > 1000 && strands.len() < 20000,
            "{} strands",
            strands.len()
        );
        let skin = formats::obj::read_obj(dir.path().join("skin.obj")).unwrap();
        assert!(skin.part_names.iter().any(|n| n == "pads"));
        let report: serde_json::Value =
            formats::json::read_json(dir.path().join("report.json")).unwrap();
        assert_eq!(report["strands"].as_u64(), Some(strands.len() as u64));
    }

    #[test]
    fn same_seed_same_bytes_and_stability_knobs() {
        let (a, b, c, d, e) = (
            tempfile::tempdir().unwrap(),
            tempfile::tempdir().unwrap(),
            tempfile::tempdir().unwrap(),
            tempfile::tempdir().unwrap(),
            tempfile::tempdir().unwrap(),
        );
        run_to(a.path(), &tiny(3)).unwrap();
        run_to(b.path(), &tiny(3)).unwrap();
        let (fa, fb) = (files(a.path()), files(b.path()));
        assert_eq!(fa.keys().collect::<Vec<_>>(), fb.keys().collect::<Vec<_>>());
        for (k, v) in &fa {
            if k != "report.json" {
                assert!(v == &fb[k], "{k} differs between identical runs");
            }
        }
        // Jitter changes the written cameras, not the images.
        let mut j = tiny(3);
        j.jitter_deg = 1.0;
        j.jitter_cm = 2.0;
        run_to(c.path(), &j).unwrap();
        let fc = files(c.path());
        assert_ne!(fa["views/transforms.json"], fc["views/transforms.json"]);
        assert_eq!(fa["views/train/000.png"], fc["views/train/000.png"]);
        let ca = formats::cameras::read_views(a.path().join("views")).unwrap();
        let cc = formats::cameras::read_views(c.path().join("views")).unwrap();
        let moved = (ca.train[0].center() - cc.train[0].center()).length() * 23.0;
        assert!(moved > 0.01 && moved < 20.0, "camera moved {moved} cm");
        // Noise changes the images; mask erosion shrinks the masks.
        let mut n = tiny(3);
        n.noise_sigma = 0.05;
        n.mask_dilate_px = -1;
        run_to(d.path(), &n).unwrap();
        let fd = files(d.path());
        assert_ne!(fa["views/train/000.png"], fd["views/train/000.png"]);
        let m0 = formats::images::read_png(a.path().join("views/train/000_mask.png")).unwrap();
        let m1 = formats::images::read_png(d.path().join("views/train/000_mask.png")).unwrap();
        let s0: f32 = m0.data.iter().sum();
        let s1: f32 = m1.data.iter().sum();
        assert!(s1 < s0 && s1 > 0.0, "eroded mask {s1} vs {s0}");
        assert!(m1.data.iter().zip(&m0.data).all(|(x, y)| x <= y));
        // Another seed grows other fur.
        run_to(e.path(), &tiny(4)).unwrap();
        assert_ne!(fa["strands.hair"], files(e.path())["strands.hair"]);
    }

    #[test]
    fn every_preset_matches_its_part_lengths() {
        for name in PRESETS {
            let mut st = Settings::new(name, "quick");
            st.resolution = 64;
            let g = generate(&st).unwrap();
            let info = scene_info(&g);
            for (part, fp) in &g.preset.parts {
                let s = &g.fur.stats[*part];
                if !fp.fur {
                    assert_eq!(s.strands, 0, "{name}/{part}");
                } else if s.strands >= 150 {
                    let m = info.parts[*part].mean_length_cm.unwrap();
                    assert!(
                        (m / fp.length_cm - 1.0).abs() < 0.04,
                        "{name}/{part}: {m} vs {}",
                        fp.length_cm
                    );
                }
            }
            // Strand-weighted mean length near the paper's table (Artemis, cm).
            let table = [
                ("tiger", 3.70f64),
                ("panda", 5.22),
                ("fox", 3.80),
                ("cat", 1.60),
            ];
            if let Some((_, want)) = table.iter().find(|(n, _)| n == name) {
                let s = &g.fur.strands;
                let mean = (0..s.len()).map(|k| s.length(k) as f64).sum::<f64>() / s.len() as f64
                    * g.s_cm as f64;
                assert!(
                    (mean / want - 1.0).abs() < 0.08,
                    "{name}: mean strand length {mean:.2} cm vs {want}"
                );
            }
        }
    }

    #[test]
    fn overrides_apply_and_bad_names_error() {
        let mut st = Settings::new("fox", "quick");
        st.resolution = 64;
        let mut torso = BTreeMap::new();
        torso.insert("length_cm".to_string(), Value::Float(7.0));
        torso.insert("density".to_string(), Value::Float(2.0));
        st.parts.insert("torso".to_string(), Value::Table(torso));
        let g = generate(&st).unwrap();
        let base = generate(&Settings {
            parts: BTreeMap::new(),
            ..st.clone()
        })
        .unwrap();
        let info = scene_info(&g);
        assert!((info.parts["torso"].mean_length_cm.unwrap() / 7.0 - 1.0).abs() < 0.04);
        let (d1, d0) = (
            info.parts["torso"].density_per_cm2.unwrap(),
            scene_info(&base).parts["torso"].density_per_cm2.unwrap(),
        );
        assert!((d1 / d0 - 2.0).abs() < 0.2, "density {d1} vs {d0}");
        // Absurd densities are refused before anything is grown.
        let mut dense = BTreeMap::new();
        dense.insert("density_per_cm2".to_string(), Value::Float(900.0));
        let mut st2 = Settings::new("bison", "quick");
        st2.resolution = 32;
        st2.parts.insert("torso".to_string(), Value::Table(dense));
        let e = generate(&st2).err().expect("too many strands").to_string();
        assert!(e.contains("parts.torso") && e.contains("limit"), "{e}");
        // Unknown part names and keys are rejected by validate, naming what is allowed.
        let mut bad = BTreeMap::new();
        bad.insert("wing".to_string(), Value::Table(BTreeMap::new()));
        let e = SyntheticSceneStage
            .validate(&params_with(&[("parts", Value::Table(bad))]))
            .unwrap_err()
            .to_string();
        assert!(e.contains("wing") && e.contains("tail"), "{e}");
    }
}
