//! The renderer benchmarks' scene (`render.rs`, `gpu.rs`): a ball of short
//! strands seen by one square camera.

use fure_stages::data::camera::Camera;
use fure_stages::render::{strands_to_gaussians, Gaussians, Mat4, Vec3};

use crate::common::Rng;

pub const SEGS_PER_STRAND: usize = 8;

/// `segments` Gaussians: strands of `SEGS_PER_STRAND` segments on the unit sphere.
pub fn fur_ball(segments: usize, seed: u64) -> Gaussians {
    let mut rng = Rng(seed);
    let strands = segments / SEGS_PER_STRAND;
    let mut points = Vec::with_capacity(strands * (SEGS_PER_STRAND + 1));
    let mut starts = vec![0u32];
    let mut widths = Vec::with_capacity(strands);
    let mut colors = Vec::with_capacity(strands);
    for _ in 0..strands {
        // Uniform direction on the sphere.
        let z = 2.0 * rng.next() - 1.0;
        let phi = std::f32::consts::TAU * rng.next();
        let r = (1.0 - z * z).max(0.0).sqrt();
        let n = Vec3::new(r * phi.cos(), r * phi.sin(), z);
        let lean = Vec3::new(rng.next() - 0.5, rng.next() - 0.5, rng.next() - 0.5);
        let len = 0.12 + 0.1 * rng.next();
        let mut p = n;
        let mut d = (n + 0.8 * lean).normalize();
        let step = len / SEGS_PER_STRAND as f32;
        for _ in 0..=SEGS_PER_STRAND {
            points.push(p);
            p += d * step;
            d = (d - Vec3::new(0.0, 0.15, 0.0)).normalize();
        }
        starts.push(points.len() as u32);
        widths.push(0.004);
        let t = rng.next();
        colors.push([0.6 + 0.3 * t, 0.4 + 0.2 * t, 0.2]);
    }
    strands_to_gaussians(&points, &starts, &widths, &colors, true).expect("valid strands")
}

/// A `size` x `size` camera looking at the ball.
pub fn camera(size: u32) -> Camera {
    let w2c = Mat4::look_at_rh(Vec3::new(0.0, 0.6, 3.2), Vec3::ZERO, Vec3::Y);
    Camera {
        file_path: String::new(),
        c2w: w2c.inverse(),
        fx: size as f32 * 1.1,
        fy: size as f32 * 1.1,
        cx: size as f32 * 0.5,
        cy: size as f32 * 0.5,
        width: size,
        height: size,
    }
}
