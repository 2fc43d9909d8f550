//! Lens distortion as COLMAP and nerfstudio write it, and undoing it on an image.
//!
//! Every stage renders and projects through a pinhole ([`Camera`]). A capture calibrated with a
//! distorting model (COLMAP's default `SIMPLE_RADIAL`, `OPENCV`, a fisheye) says where the lens
//! moved each pinhole ray on the sensor: in normalised coordinates (`x = X / Z`, `y = Y / Z`,
//! OpenCV axes, +y down), [`Distortion::distort`] maps the pinhole's point to the distorted one,
//! and the pixel is `(fx x_d + cx, fy y_d + cy)`. [`undistorted`] resamples a photo onto the
//! pinhole camera with the same `fx, fy, cx, cy` and size, so the camera reads unchanged and only
//! the pixels move (as COLMAP's `image_undistorter` does, without its choice of a new focal
//! length: the frame keeps its size and centre; what the lens showed beyond the pinhole's frame
//! is dropped). Where the pinhole sees past the photo (the corners under a pincushion lens), the
//! photo's border goes on outward (clamp to edge), so a mask that the photo's frame cuts still
//! reaches the working frame's border and `outer_surface` keeps what lies beyond it (its rule
//! for frames that cut the object; an empty fill there would end such a mask short of the
//! border, and the hull would carve away what the photo's frame cut off). A mask inside the
//! photo stays inside: its border is background.
//!
//! The models, `r² = x² + y²`:
//! - **radial-tangential** (OpenCV; COLMAP `SIMPLE_RADIAL`, `RADIAL`, `OPENCV`, `FULL_OPENCV`;
//!   nerfstudio `OPENCV`): `x_d = x s + 2 p1 x y + p2 (r² + 2 x²)`,
//!   `y_d = y s + p1 (r² + 2 y²) + 2 p2 x y`, with the radial factor
//!   `s = (1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸) / (1 + k5 r² + k6 r⁴ + k7 r⁶)`: nerfstudio's fourth
//!   coefficient is the `r⁸` term, OpenCV's rational `k4 k5 k6` (COLMAP `FULL_OPENCV`) the
//!   denominator's;
//! - **fisheye** (equidistant; COLMAP `OPENCV_FISHEYE`, `SIMPLE_RADIAL_FISHEYE`,
//!   `RADIAL_FISHEYE`; nerfstudio `OPENCV_FISHEYE`): with `θ = atan(r)`,
//!   `θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)` and `(x_d, y_d) = (x, y) θ_d / r`.
//!
//! Pixel centres are at half-integers in both cameras, as COLMAP's are ([`Camera`]); samples are
//! Lanczos-3 ([`ImageF32::sample_lanczos3`]; its ringing clamped at 0, and coverage at 1), and
//! an image with alpha is resampled premultiplied, so a fringe keeps its colour.

use rayon::prelude::*;

use super::camera::Camera;
use super::image::ImageF32;

/// A lens' distortion (module doc for the formulas).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Distortion {
    /// A pinhole: nothing to undo.
    None,
    /// OpenCV's radial-tangential model.
    RadialTangential {
        /// `k1..k4`: the numerator's `r², r⁴, r⁶, r⁸` coefficients.
        radial: [f64; 4],
        /// The denominator's `r², r⁴, r⁶` coefficients (OpenCV's rational `k4 k5 k6`).
        rational: [f64; 3],
        /// `p1 p2`.
        tangential: [f64; 2],
    },
    /// The equidistant fisheye, `k1..k4` on the angle.
    Fisheye { k: [f64; 4] },
}

impl Distortion {
    /// The radial-tangential model with `k1..k4` and `p1 p2` (no rational terms).
    pub fn radial_tangential(radial: [f64; 4], tangential: [f64; 2]) -> Distortion {
        Distortion::RadialTangential {
            radial,
            rational: [0.0; 3],
            tangential,
        }
    }

    /// Whether the lens is a pinhole (every coefficient of a radial-tangential model zero; a
    /// fisheye never is).
    pub fn is_pinhole(&self) -> bool {
        match self {
            Distortion::None => true,
            Distortion::RadialTangential {
                radial,
                rational,
                tangential,
            } => radial
                .iter()
                .chain(rational)
                .chain(tangential)
                .all(|c| *c == 0.0),
            Distortion::Fisheye { .. } => false,
        }
    }

    /// Where the lens puts the pinhole's normalised image point `(x, y)` (OpenCV axes).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        match *self {
            Distortion::None => (x, y),
            Distortion::RadialTangential {
                radial: k,
                rational: d,
                tangential: [p1, p2],
            } => {
                let r2 = x * x + y * y;
                let num = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * (k[2] + r2 * k[3])));
                let den = 1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[2]));
                let s = num / den;
                (
                    x * s + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                    y * s + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
                )
            }
            Distortion::Fisheye { k } => {
                let r = (x * x + y * y).sqrt();
                if r < 1e-12 {
                    return (x, y);
                }
                let t = r.atan();
                let t2 = t * t;
                let td = t * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))));
                (x * td / r, y * td / r)
            }
        }
    }
}

/// `image`, seen by `camera` through `lens`, resampled onto the pinhole `camera` (module doc).
/// Alpha is the last channel of 2- and 4-channel images; a 1-channel image (a mask) is resampled
/// as it is.
pub fn undistorted(image: &ImageF32, camera: &Camera, lens: &Distortion) -> ImageF32 {
    let c = image.channels as usize;
    let alpha = c == 2 || c == 4;
    // Premultiplied, so that transparent neighbours lend no colour to a fringe.
    let premultiplied;
    let src = if alpha {
        let mut p = image.clone();
        for px in p.data.chunks_exact_mut(c) {
            let a = px[c - 1];
            for v in &mut px[..c - 1] {
                *v *= a;
            }
        }
        premultiplied = p;
        &premultiplied
    } else {
        image
    };
    let (fx, fy, cx, cy) = (
        camera.fx as f64,
        camera.fy as f64,
        camera.cx as f64,
        camera.cy as f64,
    );
    let mut out = ImageF32::new(image.width, image.height, image.channels);
    let row_len = (image.width * image.channels) as usize;
    out.data
        .par_chunks_mut(row_len)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, px) in row.chunks_exact_mut(c).enumerate() {
                let nx = (x as f64 + 0.5 - cx) / fx;
                let ny = (y as f64 + 0.5 - cy) / fy;
                let (dx, dy) = lens.distort(nx, ny);
                // Past the photo its border goes on (clamp to edge), as `outer_surface` reads
                // a frame that cuts the object.
                let u = (fx * dx + cx).clamp(0.0, image.width as f64);
                let v = (fy * dy + cy).clamp(0.0, image.height as f64);
                src.sample_lanczos3(u, v, px);
                // The kernel rings past a step: no negative light, no coverage beyond [0, 1].
                for v in px.iter_mut() {
                    *v = v.max(0.0);
                }
                if alpha || c == 1 {
                    px[c - 1] = px[c - 1].min(1.0);
                }
                if alpha {
                    let a = px[c - 1];
                    for v in &mut px[..c - 1] {
                        *v = if a > 1e-6 { *v / a } else { 0.0 };
                    }
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Mat4;

    #[test]
    fn the_models_match_their_formulas_at_known_points() {
        // COLMAP SIMPLE_RADIAL k = 0.1 at (0.5, 0): 0.5 (1 + 0.1 * 0.25).
        let d = Distortion::radial_tangential([0.1, 0.0, 0.0, 0.0], [0.0; 2]);
        let (x, y) = d.distort(0.5, 0.0);
        assert!((x - 0.5125).abs() < 1e-12 && y == 0.0);
        // Tangential terms alone at (0.2, 0.1), p1 = 0.01, p2 = -0.02: r² = 0.05.
        let d = Distortion::radial_tangential([0.0; 4], [0.01, -0.02]);
        let (x, y) = d.distort(0.2, 0.1);
        assert!((x - (0.2 + 2.0 * 0.01 * 0.02 - 0.02 * (0.05 + 0.08))).abs() < 1e-12);
        assert!((y - (0.1 + 0.01 * (0.05 + 0.02) - 2.0 * 0.02 * 0.02)).abs() < 1e-12);
        // The rational denominator: s = (1 + 0.1 r²) / (1 + 0.1 r²) = 1.
        let d = Distortion::RadialTangential {
            radial: [0.1, 0.0, 0.0, 0.0],
            rational: [0.1, 0.0, 0.0],
            tangential: [0.0; 2],
        };
        let (x, _) = d.distort(0.7, 0.0);
        assert!((x - 0.7).abs() < 1e-12);
        // The equidistant fisheye without coefficients at 45 degrees: r_d = pi / 4.
        let d = Distortion::Fisheye { k: [0.0; 4] };
        let (x, y) = d.distort(0.6, 0.8);
        let rd = (x * x + y * y).sqrt();
        assert!((rd - std::f64::consts::FRAC_PI_4).abs() < 1e-12, "{rd}");
        assert!((x / y - 0.75).abs() < 1e-12);
        assert!(!d.is_pinhole());
        assert!(Distortion::radial_tangential([0.0; 4], [0.0; 2]).is_pinhole());
    }

    /// A smooth pattern over the pinhole's normalised image plane.
    fn pattern(x: f64, y: f64) -> f32 {
        (0.5 + 0.4 * (20.0 * x).sin() * (17.0 * y + 0.3).cos()) as f32
    }

    /// The distorted photo of [`pattern`]: each pixel's normalised point found by inverting the
    /// model numerically (Newton on the radius, written here from the formula, not with the
    /// module's code).
    fn distorted_photo(cam: &Camera, k1: f64, k2: f64) -> ImageF32 {
        let mut im = ImageF32::new(cam.width, cam.height, 1);
        for v in 0..cam.height {
            for u in 0..cam.width {
                let xd = (u as f64 + 0.5 - cam.cx as f64) / cam.fx as f64;
                let yd = (v as f64 + 0.5 - cam.cy as f64) / cam.fy as f64;
                let rd = (xd * xd + yd * yd).sqrt();
                // r (1 + k1 r² + k2 r⁴) = rd.
                let mut r = rd;
                for _ in 0..30 {
                    let f = r * (1.0 + k1 * r * r + k2 * r.powi(4)) - rd;
                    let df = 1.0 + 3.0 * k1 * r * r + 5.0 * k2 * r.powi(4);
                    r -= f / df;
                }
                let s = if rd > 0.0 { r / rd } else { 1.0 };
                im.pixel_mut(u, v)[0] = pattern(xd * s, yd * s);
            }
        }
        im
    }

    #[test]
    fn an_undistorted_photo_shows_what_the_pinhole_sees() {
        let cam = Camera {
            file_path: "a.png".into(),
            c2w: Mat4::IDENTITY,
            fx: 120.0,
            fy: 125.0,
            cx: 61.5,
            cy: 58.25,
            width: 128,
            height: 112,
        };
        let (k1, k2) = (-0.18, 0.03);
        let photo = distorted_photo(&cam, k1, k2);
        let lens = Distortion::radial_tangential([k1, k2, 0.0, 0.0], [0.0; 2]);
        let fixed = undistorted(&photo, &cam, &lens);
        // Against the pattern at each pinhole pixel, away from the frame's edge.
        let err = |im: &ImageF32| {
            let mut worst = 0.0f32;
            for v in 8..cam.height - 8 {
                for u in 8..cam.width - 8 {
                    let x = (u as f64 + 0.5 - cam.cx as f64) / cam.fx as f64;
                    let y = (v as f64 + 0.5 - cam.cy as f64) / cam.fy as f64;
                    worst = worst.max((im.pixel(u, v)[0] - pattern(x, y)).abs());
                }
            }
            worst
        };
        let (after, before) = (err(&fixed), err(&photo));
        eprintln!("worst error: undistorted {after}, distorted {before}");
        assert!(after < 0.03, "undistorted: worst error {after}");
        // The control: the photo taken for a pinhole's is far off.
        assert!(before > 0.2, "distorted: worst error {before}");
        // Barrel distortion: the pinhole's frame lies inside the photo, so nothing is empty.
        assert!(fixed.data.iter().all(|v| *v > 0.05));
    }

    /// A 64 px pinhole camera, focal length 40 px, principal point in the middle.
    fn square_camera() -> Camera {
        Camera {
            file_path: "a.png".into(),
            c2w: Mat4::IDENTITY,
            fx: 40.0,
            fy: 40.0,
            cx: 32.0,
            cy: 32.0,
            width: 64,
            height: 64,
        }
    }

    #[test]
    fn where_the_pinhole_sees_past_the_photo_its_border_goes_on_and_alpha_keeps_colour() {
        let cam = square_camera();
        // A red photo, opaque in its left half, transparent (and green underneath) on the right.
        let mut im = ImageF32::new(64, 64, 4);
        for y in 0..64 {
            for x in 0..64 {
                let px = if x < 32 {
                    [1.0, 0.0, 0.0, 1.0]
                } else {
                    [0.0, 1.0, 0.0, 0.0]
                };
                im.pixel_mut(x, y).copy_from_slice(&px);
            }
        }
        // Pincushion: the corners of the pinhole frame fall outside the photo.
        let lens = Distortion::radial_tangential([0.3, 0.0, 0.0, 0.0], [0.0; 2]);
        let out = undistorted(&im, &cam, &lens);
        // Past the photo's corners its corner pixels go on: opaque red on the left, empty on
        // the right.
        assert_eq!(out.pixel(0, 0), &[1.0, 0.0, 0.0, 1.0]);
        assert_eq!(out.pixel(63, 63), &[0.0, 0.0, 0.0, 0.0]);
        // The fringe between the halves is red with partial alpha, never green.
        for x in 28..36 {
            let p = out.pixel(x, 32);
            assert!(p[1] == 0.0, "green leaked at {x}: {p:?}");
            if p[3] > 0.0 {
                assert!((p[0] - 1.0).abs() < 1e-3, "{p:?}");
            }
        }
    }

    #[test]
    fn a_mask_the_photos_frame_cuts_still_reaches_the_working_frames_border() {
        let cam = square_camera();
        // An object cut by the photo's left border (rows 24-39), and one inside the photo.
        let mut mask = ImageF32::new(64, 64, 1);
        for y in 24..40 {
            for x in 0..12 {
                mask.pixel_mut(x, y)[0] = 1.0;
            }
            for x in 44..56 {
                mask.pixel_mut(x, y)[0] = 1.0;
            }
        }
        // Pincushion: every pixel of the working frame's border lies past the photo's.
        let lens = Distortion::radial_tangential([0.3, 0.0, 0.0, 0.0], [0.0; 2]);
        let (nx, _) = lens.distort(-32.0 / 40.0, 0.0);
        assert!(40.0 * nx + 32.0 < 0.0);
        let out = undistorted(&mask, &cam, &lens);
        // The cut object reaches the working frame's left border, as it reached the photo's.
        assert!(out.pixel(0, 31)[0] > 0.99 && out.pixel(0, 32)[0] > 0.99);
        // Nothing else reaches any border: the photo's border is background elsewhere.
        for i in 0..64 {
            for (x, y) in [(63, i), (i, 0), (i, 63)] {
                assert!(
                    out.pixel(x, y)[0] < 1e-3,
                    "({x}, {y}): {:?}",
                    out.pixel(x, y)
                );
            }
            if !(20..44).contains(&i) {
                assert!(out.pixel(0, i)[0] < 1e-3, "(0, {i})");
            }
        }
    }
}
