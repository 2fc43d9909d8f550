//! Differentiable 3D Gaussian splatting on the CPU (the reference renderer).
//!
//! Both the Frosting fit and strand learning optimise through this module.
//! Everything here is pure mathematics on in-memory data; the only file I/O is
//! in [`debug`]. A GPU backend is meant to mirror these formulas one to one.
//!
//! # Pipeline
//!
//! 1. **Gaussians** ([`Gaussians`]): per Gaussian a mean, three scales (the
//!    standard deviations along the local axes, world units, *activated*: no
//!    exp), a rotation quaternion (need not be normalised; it is normalised
//!    inside and the gradient is taken w.r.t. the raw quaternion), an opacity
//!    in [0, 1] (activated: no sigmoid), spherical-harmonics colour of degree
//!    0 or 1 (3DGS convention: `colour = 0.5 + C0 sh0 + C1 (-y sh1 + z sh2 -
//!    x sh3)` with `(x, y, z)` the unit vector from the camera centre to the
//!    mean, clamped below at 0) and a fur flag. Optimisers that prefer log
//!    scales or logit opacities chain the returned gradients themselves.
//! 2. **Strand mode** ([`strands_to_gaussians`]): every polyline segment
//!    `a -> b` becomes one Gaussian with mean `(a + b) / 2`, scales
//!    `(|b - a| / 2, w, w)` where `w = THIN_SIGMA_PER_WIDTH * width`, opacity
//!    [`STRAND_OPACITY`], degree-0 colour equal to the strand colour, and the
//!    rotation taking +x onto the segment direction (`[1 + x.d, x cross d]`
//!    normalised; the anti-parallel case d = -x is a half turn about +z; a
//!    zero-length segment gets the identity). [`strands_backward`] maps
//!    Gaussian gradients back to points, widths and colours *through the 3D
//!    covariance* `Sigma = |d|^2/4 dhat dhat^T + w^2 (I - dhat dhat^T)`, which
//!    does not depend on the (arbitrary) twist about the segment, so the
//!    anti-parallel case needs no special gradient; for segments shorter than
//!    [`MIN_SEGMENT`] the direction term is dropped (no NaN at zero length).
//! 3. **Projection** ([`project`]): EWA. Camera-space `t = W p + t_w`, depth
//!    `z = -t.z` (OpenGL axes, camera looks down -z), pixel
//!    `u = cx + fx t.x / z`, `v = cy - fy t.y / z` (v down, pixel centres at
//!    half-integers, as in `camera.rs`). Jacobian
//!    `J = [[fx/z, 0, fx rx/z], [0, -fy/z, -fy ry/z]]` with `rx = t.x / z`,
//!    `ry = t.y / z` clamped to the view frustum widened by 15 % of the image
//!    on each side (3DGS's `1.3 tan(fov/2)`; the clamped coordinate gets no
//!    gradient through J). `Sigma2 = J W Sigma3 W^T J^T + low_pass I` with
//!    `low_pass = 0.3` pixel^2. Gaussians with `z < near` are culled (this
//!    covers everything behind the camera).
//! 4. **Tiles** ([`raster`]): the support of a Gaussian is the ellipse
//!    `d^T Sigma2^-1 d <= k^2`, `k^2 = min(extent_sigmas^2, 2 ln(opacity /
//!    alpha_min))` (exactly where its alpha can reach `alpha_min`). Visible
//!    splats are sorted globally by (depth, index) -- a total order, so ties
//!    cannot make the result depend on the sort algorithm or thread count --
//!    then binned into 16x16 tiles with a stable counting sort, so every
//!    tile list is depth-sorted. Only tiles the ellipse
//!    actually touches are listed (per band of 16 rows, the union of the
//!    exact row intervals, not just the bounding box).
//! 5. **Compositing**: per tile (one rayon task each, fixed work), the
//!    tile's splats are gathered into a local array, then processed front to
//!    back; for each only the pixels inside its ellipse are visited (row
//!    intervals solved from the conic). `alpha = min(alpha_max, o
//!    exp(-0.5 d^T Sigma2^-1 d))`, skipped below `alpha_min`; a pixel stops
//!    when its transmittance would drop below `transmittance_min` (that
//!    Gaussian is not blended, as in 3DGS). Where alpha is clamped the
//!    gradient w.r.t. opacity and shape is zero (as in 3DGS).
//!
//! # Outputs ([`RenderOutput`])
//!
//! Every output is an alpha-blended per-Gaussian feature
//! `out = sum_i f_i alpha_i T_i (+ T_final bg for RGB)`:
//! - `rgb` (3 channels): SH colour over the background.
//! - `alpha` (1): `1 - T_final` (the silhouette; the feature is 1).
//! - `depth` (1): blended view depth `z` *not* divided by alpha (divide by
//!   alpha yourself for an expected depth of the covered part).
//! - `orientation` (2): the blended doubled-angle vector of the projected
//!   Gaussian's long axis, `((a - c), 2 b) / (a + c)` for `Sigma2 = [[a, b],
//!   [b, c]]` (pixel units). For a 2D covariance with eigenvalues l1 >= l2 and
//!   major axis at angle phi this equals `(l1 - l2) / (l1 + l2) (cos 2 phi,
//!   sin 2 phi)`: pi-periodic (strands drawn in opposite directions do not
//!   cancel), weighted by elongation (round blobs carry no orientation), and
//!   smooth everywhere (no normalisation singularity). The angle is
//!   [`orientation_from_feature`].
//! - `fur` (1): the blended fur flag (0 or 1 per Gaussian).
//!
//! # Orientation convention (shared with the Gabor maps)
//!
//! An image-space direction `(du, dv)` in pixel coordinates (u right, **v
//! down**) has orientation `theta = atan2(dv, du) mod pi` in `[0, pi)`
//! ([`orientation_angle`]). So theta = 0 is horizontal, and theta = pi/4 is a
//! line going right *and down* on screen.
//!
//! # Backward
//!
//! [`backward`] is the hand-written adjoint of all of the above (compositing
//! back to front with transmittance recovered by division, then the
//! projection). Determinism: each tile writes the gradient of each of its
//! (tile, Gaussian) instances into its own slot; slots are then summed per
//! Gaussian in tile order, and the per-Gaussian projection adjoint is
//! independent per Gaussian. Results are bit-identical for any thread count.
//! The finite-difference tests use [`RenderSettings::smooth`] (no alpha cut,
//! no early termination, 7-sigma support) so the rendered function is smooth.
//!
//! Also here: [`losses`] (L1 + D-SSIM, silhouette, orientation, fur mask, each
//! with its gradient) and [`adam`] (Adam with per-group learning rates).
//!
//! # Usage
//!
//! ```ignore
//! let g = strands_to_gaussians(&s.points, &s.starts, &s.width, &s.color, true)?;
//! let (out, state) = render(&g, &camera, &RenderSettings::default())?;
//! let (loss, d_rgb) = losses::l1_dssim(&out.rgb, &target, None, 0.2)?;
//! let dl = OutputGrads { rgb: Some(d_rgb), ..Default::default() };
//! let grads = backward(&g, &camera, &RenderSettings::default(), &state, &dl)?;
//! let sg = strands_backward(&s.points, &s.starts, &s.width, &grads)?; // d/dpoints
//! ```
//!
//! # Choices where the paper and issue are vague
//!
//! - Thin strand sigma = `0.5 x width` ([`THIN_SIGMA_PER_WIDTH`]); strand
//!   opacity 1 ([`STRAND_OPACITY`]; with the 0.99 clamp the centre of an
//!   opaque strand has no opacity/shape gradient, its edges do).
//! - Parameters are taken activated (sigmas, opacity in [0, 1]); SH colours
//!   use the 3DGS constants and the 0.5 offset, clamped at 0.
//! - Depth is blended, not normalised; orientation is the doubled-angle
//!   covariance feature described above (the Gaussian Haircut code projects
//!   the 3D direction and normalises after blending; the covariance form gives
//!   the same angle for a thin strand and has no singularity).
//! - Everything is f32; the finite-difference tests evaluate losses in f64.
//! - [`render`] and [`backward`] return `Result` (bad lengths, NaN inputs,
//!   bad cameras or settings are errors naming the array and index).

// `!(x > y)` is deliberate: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod adam;
pub mod debug;
pub mod device;
pub mod gaussians;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod losses;
pub mod project;
pub mod raster;

pub use adam::Adam;
pub use gaussians::{
    strands_backward, strands_to_gaussians, GaussianGrads, Gaussians, StrandGrads, MIN_SEGMENT,
    STRAND_OPACITY, THIN_SIGMA_PER_WIDTH,
};
pub use raster::{backward, blend_sums, render, OutputGrads, RenderOutput, RenderState};

/// The vector types of this API, re-exported for users without a glam dependency.
pub use glam::{Mat3, Mat4, Quat, Vec2, Vec3};

/// Spherical-harmonics band-0 constant.
pub const SH_C0: f32 = 0.282_094_8;
/// Spherical-harmonics band-1 constant.
pub const SH_C1: f32 = 0.488_602_5;
/// Tile edge in pixels.
pub const TILE: u32 = 16;

/// Errors from the renderer: malformed inputs, never numerical trouble (that
/// is culled or clamped).
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// Two arrays that must have one entry per item disagree.
    #[error("{what}: expected {expected} entries, found {found}")]
    Length {
        what: &'static str,
        expected: usize,
        found: usize,
    },
    /// An input value is NaN or infinite.
    #[error("{what}[{index}] is not finite")]
    NonFinite { what: &'static str, index: usize },
    /// The camera cannot be rendered from.
    #[error("camera: {0}")]
    Camera(String),
    /// A setting is out of range.
    #[error("render settings: {0}")]
    Settings(String),
    /// An image has the wrong size or channel count.
    #[error("{what}: expected a {width}x{height} image with {channels} channel(s), found {found}")]
    Image {
        what: &'static str,
        width: u32,
        height: u32,
        channels: u32,
        found: String,
    },
    /// Strand topology is inconsistent.
    #[error("strands: {0}")]
    Strands(String),
    /// The GPU path failed (no adapter, device lost, too large a scene).
    #[error("gpu: {0}")]
    Gpu(String),
}

impl From<RenderError> for fure_stage_api::StageError {
    fn from(e: RenderError) -> Self {
        fure_stage_api::StageError::failed(e)
    }
}

/// How to render. [`RenderSettings::default`] is the usual 3DGS
/// configuration; [`RenderSettings::smooth`] makes the image a smooth function
/// of the parameters (for finite-difference tests).
#[derive(Debug, Clone, PartialEq)]
pub struct RenderSettings {
    /// RGB behind everything.
    pub background: Vec3,
    /// 0 or 1.
    pub sh_degree: u32,
    /// Gaussians whose mean is nearer than this (view depth) are culled.
    pub near: f32,
    /// Contributions with alpha below this are skipped (1/255 in 3DGS; 0 = no cut).
    pub alpha_min: f32,
    /// Alpha is clamped to this (0.99 in 3DGS).
    pub alpha_max: f32,
    /// A pixel stops when its transmittance would drop below this (1e-4; 0 = never).
    pub transmittance_min: f32,
    /// Upper bound of the support radius in standard deviations.
    pub extent_sigmas: f32,
    /// Screen-space low-pass added to the 2D covariance diagonal (pixels^2).
    pub low_pass: f32,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            background: Vec3::ZERO,
            sh_degree: 0,
            near: 0.01,
            alpha_min: 1.0 / 255.0,
            alpha_max: 0.99,
            transmittance_min: 1e-4,
            extent_sigmas: 4.0,
            low_pass: 0.3,
        }
    }
}

impl RenderSettings {
    /// The smooth test configuration: no alpha cut, no early termination and a
    /// 7-sigma support (the cut tail is below 3e-11 of the peak).
    pub fn smooth() -> Self {
        RenderSettings {
            alpha_min: 0.0,
            transmittance_min: 0.0,
            extent_sigmas: 7.0,
            ..Default::default()
        }
    }

    pub(crate) fn validate(&self) -> Result<(), RenderError> {
        let bad = |m: &str| Err(RenderError::Settings(m.to_string()));
        if !self.background.is_finite() {
            return bad("background is not finite");
        }
        if self.sh_degree > 1 {
            return bad("sh_degree must be 0 or 1");
        }
        if !(self.near.is_finite() && self.near > 0.0) {
            return bad("near must be > 0");
        }
        if !(self.alpha_min >= 0.0 && self.alpha_min < 1.0) {
            return bad("alpha_min must be in [0, 1)");
        }
        if !(self.alpha_max > 0.0 && self.alpha_max < 1.0) {
            return bad("alpha_max must be in (0, 1) (1 would make the backward divide by zero)");
        }
        if !(self.transmittance_min >= 0.0 && self.transmittance_min < 1.0) {
            return bad("transmittance_min must be in [0, 1)");
        }
        if !(self.extent_sigmas.is_finite() && self.extent_sigmas > 0.0) {
            return bad("extent_sigmas must be > 0");
        }
        if !(self.low_pass.is_finite() && self.low_pass > 0.0) {
            return bad("low_pass must be > 0");
        }
        Ok(())
    }
}

/// Orientation of the image-space direction `(du, dv)` (pixels, v down):
/// `atan2(dv, du) mod pi`, in `[0, pi)`. The Gabor orientation maps use the
/// same definition.
pub fn orientation_angle(du: f32, dv: f32) -> f32 {
    let a = dv.atan2(du).rem_euclid(std::f32::consts::PI);
    if a >= std::f32::consts::PI {
        0.0
    } else {
        a
    }
}

/// The orientation angle (see [`orientation_angle`]) encoded by a blended
/// orientation feature `(ox, oy) = m (cos 2 theta, sin 2 theta)`. Returns 0
/// for the zero vector.
pub fn orientation_from_feature(ox: f32, oy: f32) -> f32 {
    if ox == 0.0 && oy == 0.0 {
        return 0.0;
    }
    let a = (0.5 * oy.atan2(ox)).rem_euclid(std::f32::consts::PI);
    if a >= std::f32::consts::PI {
        0.0
    } else {
        a
    }
}

#[cfg(test)]
pub(crate) mod tests;
