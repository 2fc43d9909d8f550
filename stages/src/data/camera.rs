//! Pinhole cameras in the NeRF / instant-ngp convention.
//!
//! `c2w` is camera-to-world with OpenGL axes: the camera looks down its -z
//! axis, +y is up, +x is right. Pixel (u, v) has u to the right and v down,
//! pixel centres at half-integers; a camera-space point (x, y, z), z < 0,
//! projects to u = cx + fx * x / -z, v = cy - fy * y / -z.
//!
//! Also what the cameras' pixels are at the subject: each camera's footprint
//! there, which views resolve it ([`resolving_views`]: a capture may mix
//! cameras and distances), and the one footprint every stage sizes by
//! ([`pixel_footprint`]).

use glam::{DMat3, DVec3, Mat4, Vec2, Vec3};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Image path relative to the directory of `transforms.json` (as written there).
    pub file_path: String,
    pub c2w: Mat4,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    pub fn w2c(&self) -> Mat4 {
        self.c2w.inverse()
    }
    /// Camera centre in world space.
    pub fn center(&self) -> Vec3 {
        self.c2w.w_axis.truncate()
    }
    /// Projects a world point; returns pixel coordinates and depth (distance along the view axis, > 0 in front).
    pub fn project(&self, p: Vec3) -> (Vec2, f32) {
        let c = self.w2c().transform_point3(p);
        let depth = -c.z;
        let u = self.cx + self.fx * c.x / depth;
        let v = self.cy - self.fy * c.y / depth;
        (Vec2::new(u, v), depth)
    }
    /// World-space ray (origin, unit direction) through pixel coordinates (u, v).
    pub fn ray(&self, u: f32, v: f32) -> (Vec3, Vec3) {
        let d_cam = Vec3::new((u - self.cx) / self.fx, -(v - self.cy) / self.fy, -1.0);
        let d = self.c2w.transform_vector3(d_cam).normalize();
        (self.center(), d)
    }
}

/// The cameras of a capture: training views and held-out test views.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraSet {
    pub train: Vec<Camera>,
    pub test: Vec<Camera>,
}

/// The views' pixel footprint at the subject, in scene units: the median over
/// the resolving cameras ([`resolving_views`]) of their distance to the centre
/// of `outer`'s bounding box over their focal length in pixels. Radii given in
/// pixels scale with it, so they mean the same in any unit and at any
/// resolution.
pub fn pixel_footprint(cameras: &[Camera], outer: &crate::data::mesh::Mesh) -> f32 {
    let (lo, hi) = outer.bounds();
    let centre = 0.5 * (lo + hi);
    let f: Vec<f64> = cameras
        .iter()
        .map(|c| ((c.center() - centre).length() / c.fx.abs().max(1e-12)) as f64)
        .collect();
    resolving_footprint(&f).unwrap_or(0.0) as f32
}

/// How much coarser than the sharper views a view's pixel may be and still
/// count as resolving the subject: 1.5, above the spread of a hand-held orbit
/// whose distance varies by a few tens of percent (the benchmark's rigs are
/// orbits at one distance: 1.0), below a second camera at half the
/// resolution (2).
pub const RESOLVING_RATIO: f64 = 1.5;

/// Which views resolve the subject, from each view's pixel footprint there
/// (scene units per pixel; a value that is not finite and positive says
/// nothing and counts as resolving). A view resolves it when its footprint is
/// at most [`RESOLVING_RATIO`] times the coarsest footprint of the sharpest
/// quarter of the views.
///
/// Why: a capture that mixes cameras, or photographs from two distances,
/// holds views in which a pixel covers twice the fur. What such a view shows
/// of the coat is its colour pattern, not the fur's texture, and its
/// orientation map reads the pattern (a tiger's stripes run across the fur);
/// sized by the median view, the model is also sized by the coarse half. The
/// sharpest quarter rather than the sharpest view, so that a few close-ups of
/// a head do not set the rest of the animal aside.
pub fn resolving_views(footprints: &[f64]) -> Vec<bool> {
    footprint_ratios(footprints)
        .into_iter()
        .map(resolves)
        .collect()
}

/// Whether a view whose footprint is `ratio` times the sharpest quarter's
/// resolves the subject (a ratio that is not a number says nothing: it does).
pub fn resolves(ratio: f64) -> bool {
    !(ratio > RESOLVING_RATIO)
}

/// Each footprint over the coarsest of the sharpest quarter's
/// ([`sharpest_quarter_footprint`]); not a number where either says nothing.
pub fn footprint_ratios(footprints: &[f64]) -> Vec<f64> {
    let reference = sharpest_quarter_footprint(footprints).unwrap_or(f64::NAN);
    footprints
        .iter()
        .map(|&f| {
            if usable_footprint(f) {
                f / reference
            } else {
                f64::NAN
            }
        })
        .collect()
}

/// The coarsest footprint of the sharpest quarter of the views (rounded up),
/// [`resolving_views`]' reference; `None` without a usable footprint.
pub fn sharpest_quarter_footprint(footprints: &[f64]) -> Option<f64> {
    let mut sorted: Vec<f64> = footprints
        .iter()
        .copied()
        .filter(|f| usable_footprint(*f))
        .collect();
    sorted.sort_by(f64::total_cmp);
    (!sorted.is_empty()).then(|| sorted[sorted.len().div_ceil(4) - 1])
}

fn usable_footprint(f: f64) -> bool {
    f.is_finite() && f > 0.0
}

/// [`resolving_views`] for cameras, from their footprints where their optical axes meet
/// ([`axes_centre`]); every camera resolves when the axes do not meet.
pub fn resolving_cameras(cameras: &[Camera]) -> Vec<bool> {
    camera_footprint_ratios(cameras)
        .into_iter()
        .map(resolves)
        .collect()
}

/// [`footprint_ratios`] of cameras where their optical axes meet; not a number
/// for every camera when the axes do not meet.
pub fn camera_footprint_ratios(cameras: &[Camera]) -> Vec<f64> {
    match axes_centre(cameras) {
        Some(centre) => footprint_ratios(&footprints_at(cameras, centre)),
        None => vec![f64::NAN; cameras.len()],
    }
}

/// The median footprint over the resolving views (the upper middle for an
/// even count); `None` without a usable footprint.
pub fn resolving_footprint(footprints: &[f64]) -> Option<f64> {
    let keep = resolving_views(footprints);
    let mut f: Vec<f64> = footprints
        .iter()
        .zip(keep)
        .filter(|(f, k)| *k && usable_footprint(**f))
        .map(|(f, _)| *f)
        .collect();
    f.sort_by(f64::total_cmp);
    f.get(f.len() / 2).copied()
}

/// Each camera's pixel footprint at `p`: the depth of `p` along the camera's
/// axis over its focal length in pixels (not finite where `fx` is not positive).
pub fn footprints_at(cameras: &[Camera], p: DVec3) -> Vec<f64> {
    cameras
        .iter()
        .map(|c| {
            let local = c.w2c().as_dmat4().transform_point3(p);
            if c.fx > 0.0 {
                (-local.z).abs() / c.fx as f64
            } else {
                f64::NAN
            }
        })
        .collect()
}

/// The point closest in least squares to the cameras' optical axes: where an
/// orbit looks. `None` with fewer than two cameras or axes that do not meet
/// (all parallel).
pub fn axes_centre(cameras: &[Camera]) -> Option<DVec3> {
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for c in cameras {
        let o = c.center().as_dvec3();
        let d = (-c.c2w.z_axis.truncate()).as_dvec3().normalize_or_zero();
        if d == DVec3::ZERO {
            continue;
        }
        // (I - d d^T) projects onto the plane orthogonal to the axis.
        let m = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += m;
        b += m * o;
    }
    let n = cameras.len();
    if n < 2 || a.determinant().abs() < 1e-9 * (n as f64).powi(3) {
        return None;
    }
    Some(a.inverse() * b).filter(|x| x.is_finite())
}

/// Test support: a camera at `eye` looking at the origin, `size` pixels square with a
/// 40-degree field, its photo `name`.
#[cfg(test)]
pub(crate) fn looking_at_origin(eye: Vec3, size: u32, name: String) -> Camera {
    let f = size as f32 / (2.0 * 20f32.to_radians().tan());
    Camera {
        file_path: name,
        c2w: Mat4::look_at_rh(eye, Vec3::ZERO, Vec3::Y).inverse(),
        fx: f,
        fy: f,
        cx: size as f32 / 2.0,
        cy: size as f32 / 2.0,
        width: size,
        height: size,
    }
}

/// Test support: `n` cameras around the origin, camera `i` at `distance(i)` with
/// `size(i)` pixels, its photo `{i}.png`.
#[cfg(test)]
pub(crate) fn orbit(
    n: usize,
    distance: impl Fn(usize) -> f32,
    size: impl Fn(usize) -> u32,
) -> Vec<Camera> {
    (0..n)
        .map(|i| {
            let a = i as f32 / n as f32 * std::f32::consts::TAU;
            let eye = Vec3::new(a.cos(), 0.3, a.sin()).normalize() * distance(i);
            looking_at_origin(eye, size(i), format!("{i}.png"))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_axes_of_an_orbit_meet_where_it_looks() {
        let cams = orbit(8, |i| 3.0 + i as f32 * 0.2, |_| 64);
        let c = axes_centre(&cams).unwrap();
        assert!(c.length() < 1e-5, "{c}");
        // One camera, or axes that are all parallel, give no centre.
        assert!(axes_centre(&cams[..1]).is_none());
        let parallel: Vec<Camera> = (0..4)
            .map(|i| {
                let mut c = looking_at_origin(Vec3::new(0.0, 0.0, 5.0), 64, "p.png".into());
                c.c2w = Mat4::from_translation(Vec3::new(i as f32, 0.0, 5.0));
                c
            })
            .collect();
        assert!(axes_centre(&parallel).is_none());
    }

    #[test]
    fn views_much_coarser_than_the_sharpest_quarter_do_not_resolve_the_subject() {
        let at = |cams: &[Camera]| footprints_at(cams, DVec3::ZERO);
        // An orbit whose distance varies by 1.3x: every view resolves the subject, and the
        // footprint is the plain median.
        let varied = orbit(12, |i| 3.0 * (1.0 + 0.3 * i as f32 / 11.0), |_| 256);
        let f = at(&varied);
        assert!(resolving_views(&f).iter().all(|r| *r));
        let mut sorted = f.clone();
        sorted.sort_by(f64::total_cmp);
        assert_eq!(resolving_footprint(&f), Some(sorted[6]));
        // Every other camera at half the resolution: those are set aside, and the
        // footprint is the sharp half's.
        let mixed = orbit(12, |_| 3.0, |i| if i % 2 == 0 { 256 } else { 128 });
        let f = at(&mixed);
        let keep = resolving_views(&f);
        assert_eq!(keep, (0..12).map(|i| i % 2 == 0).collect::<Vec<_>>());
        assert!((resolving_footprint(&f).unwrap() - f[0]).abs() < 1e-9 * f[0]);
        // A sharp quarter still leads; fewer sharp views than a quarter (two close-ups)
        // set nothing aside.
        let quarter = orbit(12, |_| 3.0, |i| if i % 4 == 0 { 256 } else { 128 });
        assert_eq!(
            resolving_views(&at(&quarter))
                .iter()
                .filter(|r| **r)
                .count(),
            3
        );
        let closeups = orbit(12, |i| if i < 2 { 1.0 } else { 3.0 }, |_| 256);
        assert!(resolving_views(&at(&closeups)).iter().all(|r| *r));
        // A footprint that says nothing (a camera without a focal length) is kept.
        let mut odd = f.clone();
        odd[1] = f64::NAN;
        assert!(resolving_views(&odd)[1]);
        assert_eq!(resolving_footprint(&[f64::NAN]), None);
    }
}
