//! Pinhole cameras in the NeRF / instant-ngp convention.
//!
//! `c2w` is camera-to-world with OpenGL axes: the camera looks down its -z
//! axis, +y is up, +x is right. Pixel (u, v) has u to the right and v down,
//! pixel centres at half-integers; a camera-space point (x, y, z), z < 0,
//! projects to u = cx + fx * x / -z, v = cy - fy * y / -z.

use glam::{Mat4, Vec2, Vec3};
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
/// the cameras of their distance to the centre of `outer`'s bounding box over
/// their focal length in pixels. Radii given in pixels scale with it, so they
/// mean the same in any unit and at any resolution.
pub fn pixel_footprint(cameras: &[Camera], outer: &crate::data::mesh::Mesh) -> f32 {
    let (lo, hi) = outer.bounds();
    let centre = 0.5 * (lo + hi);
    let mut f: Vec<f32> = cameras
        .iter()
        .map(|c| (c.center() - centre).length() / c.fx.abs().max(1e-12))
        .filter(|x| x.is_finite())
        .collect();
    if f.is_empty() {
        return 0.0;
    }
    f.sort_by(f32::total_cmp);
    f[f.len() / 2]
}
