//! Finite-difference and behaviour tests of the renderer.

use glam::{Mat4, Quat, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;
use crate::camera::Camera;
use crate::image::ImageF32;

pub(crate) fn test_camera(size: u32, eye: Vec3, target: Vec3) -> Camera {
    // look_at_rh gives the w2c of a camera looking down -z (OpenGL).
    let w2c = Mat4::look_at_rh(eye, target, Vec3::Y);
    Camera {
        file_path: String::new(),
        c2w: w2c.inverse(),
        fx: size as f32 * 1.2,
        fy: size as f32 * 1.2,
        cx: size as f32 * 0.5,
        cy: size as f32 * 0.5,
        width: size,
        height: size,
    }
}

fn random_gaussians(rng: &mut ChaCha8Rng, n: usize) -> Gaussians {
    let mut g = Gaussians::default();
    for _ in 0..n {
        let mean = Vec3::new(
            rng.gen_range(-0.6..0.6),
            rng.gen_range(-0.6..0.6),
            rng.gen_range(-0.6..0.6),
        );
        let scale = Vec3::new(
            rng.gen_range(0.08..0.3),
            rng.gen_range(0.03..0.2),
            rng.gen_range(0.03..0.2),
        );
        let rot = Quat::from_xyzw(
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
        ) * 1.3;
        let op = rng.gen_range(0.3..0.9);
        let mut sh = [Vec3::ZERO; 4];
        for c in sh.iter_mut() {
            *c = Vec3::new(
                rng.gen_range(-0.5..0.5),
                rng.gen_range(-0.5..0.5),
                rng.gen_range(-0.5..0.5),
            );
        }
        g.means.push(mean);
        g.scales.push(scale);
        g.rotations.push(rot);
        g.opacities.push(op);
        g.sh.push(sh);
        g.fur.push(rng.gen_bool(0.5));
    }
    g
}

fn random_image(rng: &mut ChaCha8Rng, w: u32, h: u32, c: u32, amp: f32) -> ImageF32 {
    let mut im = ImageF32::new(w, h, c);
    for v in im.data.iter_mut() {
        *v = rng.gen_range(-amp..amp);
    }
    im
}

/// A scalar loss that is linear in every output, and its output gradients.
struct LinearLoss {
    dl: OutputGrads,
}

impl LinearLoss {
    fn new(rng: &mut ChaCha8Rng, w: u32, h: u32) -> Self {
        LinearLoss {
            dl: OutputGrads {
                rgb: Some(random_image(rng, w, h, 3, 1.0)),
                alpha: Some(random_image(rng, w, h, 1, 1.0)),
                depth: Some(random_image(rng, w, h, 1, 0.3)),
                orientation: Some(random_image(rng, w, h, 2, 1.0)),
                fur: Some(random_image(rng, w, h, 1, 1.0)),
            },
        }
    }
    fn eval(&self, o: &RenderOutput) -> f64 {
        let dot = |a: &ImageF32, b: &Option<ImageF32>| -> f64 {
            a.data
                .iter()
                .zip(&b.as_ref().unwrap().data)
                .map(|(x, y)| *x as f64 * *y as f64)
                .sum()
        };
        dot(&o.rgb, &self.dl.rgb)
            + dot(&o.alpha, &self.dl.alpha)
            + dot(&o.depth, &self.dl.depth)
            + dot(&o.orientation, &self.dl.orientation)
            + dot(&o.fur, &self.dl.fur)
    }
}

/// Compares analytic and central-difference gradients; returns the worst
/// relative error (w.r.t. max(|analytic|, |fd|, floor)).
fn compare(name: &str, pairs: &[(f64, f64)], floor: f64) -> f64 {
    let mut worst = 0.0f64;
    for (i, &(a, fd)) in pairs.iter().enumerate() {
        let err = (a - fd).abs() / a.abs().max(fd.abs()).max(floor);
        if err > worst {
            worst = err;
        }
        assert!(
            err < 0.03,
            "{name}[{i}]: analytic {a:.6e} vs finite difference {fd:.6e} (rel err {err:.3})"
        );
    }
    let amax = pairs.iter().map(|p| p.0.abs()).fold(0.0, f64::max);
    eprintln!(
        "{name}: {} values, max |grad| {amax:.3e}, worst rel err {worst:.2e}",
        pairs.len()
    );
    worst
}

fn fd_scene(sh_degree: u32, bg: Vec3) -> (Gaussians, Camera, RenderSettings, LinearLoss) {
    let mut rng = ChaCha8Rng::seed_from_u64(7 + sh_degree as u64);
    let g = random_gaussians(&mut rng, 5);
    let cam = test_camera(32, Vec3::new(0.4, 0.3, 4.0), Vec3::ZERO);
    let mut s = RenderSettings::smooth();
    s.sh_degree = sh_degree;
    s.background = bg;
    let loss = LinearLoss::new(&mut rng, 32, 32);
    (g, cam, s, loss)
}

#[test]
fn gaussian_gradients_match_finite_differences() {
    for degree in [0u32, 1] {
        let (g, cam, s, loss) = fd_scene(degree, Vec3::new(0.2, 0.5, 0.9));
        let (_, st) = render(&g, &cam, &s).unwrap();
        let gr = backward(&g, &cam, &s, &st, &loss.dl).unwrap();
        let f = |gg: &Gaussians| loss.eval(&render(gg, &cam, &s).unwrap().0);
        let h = 1e-3f32;
        let mut means = Vec::new();
        let mut scales = Vec::new();
        let mut rots = Vec::new();
        let mut ops = Vec::new();
        let mut shs = Vec::new();
        for i in 0..g.len() {
            for k in 0..3 {
                let mut a = g.clone();
                let mut b = g.clone();
                a.means[i][k] += h;
                b.means[i][k] -= h;
                means.push((gr.means[i][k] as f64, (f(&a) - f(&b)) / (2.0 * h as f64)));
                let mut a = g.clone();
                let mut b = g.clone();
                a.scales[i][k] += h;
                b.scales[i][k] -= h;
                scales.push((gr.scales[i][k] as f64, (f(&a) - f(&b)) / (2.0 * h as f64)));
            }
            for k in 0..4 {
                let mut a = g.clone();
                let mut b = g.clone();
                let mut qa = a.rotations[i].to_array();
                let mut qb = b.rotations[i].to_array();
                qa[k] += h;
                qb[k] -= h;
                a.rotations[i] = Quat::from_array(qa);
                b.rotations[i] = Quat::from_array(qb);
                let an = gr.rotations[i].to_array()[k] as f64;
                rots.push((an, (f(&a) - f(&b)) / (2.0 * h as f64)));
            }
            let mut a = g.clone();
            let mut b = g.clone();
            a.opacities[i] += h;
            b.opacities[i] -= h;
            ops.push((gr.opacities[i] as f64, (f(&a) - f(&b)) / (2.0 * h as f64)));
            for band in 0..(if degree == 1 { 4 } else { 1 }) {
                for k in 0..3 {
                    let mut a = g.clone();
                    let mut b = g.clone();
                    a.sh[i][band][k] += h;
                    b.sh[i][band][k] -= h;
                    shs.push((gr.sh[i][band][k] as f64, (f(&a) - f(&b)) / (2.0 * h as f64)));
                }
            }
        }
        // The floor is a small fraction of the typical gradient size, so a
        // missing term or a wrong sign fails while f32 noise in near-zero
        // entries does not.
        let scale_of =
            |v: &[(f64, f64)]| v.iter().map(|p| p.1.abs()).fold(0.0, f64::max) * 2e-3 + 1e-4;
        compare("means", &means, scale_of(&means));
        compare("scales", &scales, scale_of(&scales));
        compare("rotations", &rots, scale_of(&rots));
        compare("opacities", &ops, scale_of(&ops));
        compare("sh", &shs, scale_of(&shs));
        // The gradients are not trivially zero.
        assert!(means.iter().any(|p| p.0.abs() > 1e-2));
        assert!(rots.iter().any(|p| p.0.abs() > 1e-2));
    }
}

#[test]
fn strand_gradients_match_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    // Three strands of 4, 3 and 2 points; one has a zero-length segment and
    // one an exactly anti-parallel (-x) segment.
    let mut points = Vec::new();
    let mut starts = vec![0u32];
    for s in 0..3 {
        let n = 4 - s;
        let mut p = Vec3::new(
            rng.gen_range(-0.5..0.5),
            rng.gen_range(-0.5..0.5),
            rng.gen_range(-0.3..0.3),
        );
        for k in 0..n {
            points.push(p);
            let step = if s == 1 && k == 0 {
                Vec3::new(-0.3, 0.0, 0.0)
            } else {
                Vec3::new(
                    rng.gen_range(-0.3..0.3),
                    rng.gen_range(-0.3..0.3),
                    rng.gen_range(-0.3..0.3),
                )
            };
            p += step;
        }
        starts.push(points.len() as u32);
    }
    let zero_seg = points[5];
    points.push(zero_seg); // strand 3: a zero-length segment
    points.push(zero_seg);
    starts.push(points.len() as u32);
    let widths = vec![0.06, 0.1, 0.04, 0.08];
    let colors = vec![
        [0.9, 0.4, 0.1],
        [0.2, 0.6, 0.8],
        [0.5, 0.5, 0.5],
        [0.3, 0.3, 0.9],
    ];
    let cam = test_camera(32, Vec3::new(0.3, -0.2, 4.0), Vec3::ZERO);
    let s = RenderSettings {
        background: Vec3::new(0.1, 0.2, 0.3),
        ..RenderSettings::smooth()
    };
    let loss = LinearLoss::new(&mut rng, 32, 32);
    let make = |pts: &[Vec3], wd: &[f32], col: &[[f32; 3]]| {
        let mut g = strands_to_gaussians(pts, &starts, wd, col, true).unwrap();
        // Below the 0.99 clamp so the function is smooth.
        g.opacities.iter_mut().for_each(|o| *o = 0.7);
        g
    };
    let g = make(&points, &widths, &colors);
    let (out, st) = render(&g, &cam, &s).unwrap();
    assert!(out.rgb.data.iter().all(|v| v.is_finite()));
    let gg = backward(&g, &cam, &s, &st, &loss.dl).unwrap();
    let sg = strands_backward(&points, &starts, &widths, &gg).unwrap();
    let f = |pts: &[Vec3], wd: &[f32], col: &[[f32; 3]]| {
        loss.eval(&render(&make(pts, wd, col), &cam, &s).unwrap().0)
    };
    let h = 1e-3f32;
    let mut pg = Vec::new();
    // Skip the zero-length segment's points (no derivative there).
    for i in 0..points.len() - 2 {
        for k in 0..3 {
            let mut a = points.clone();
            let mut b = points.clone();
            a[i][k] += h;
            b[i][k] -= h;
            let fd = (f(&a, &widths, &colors) - f(&b, &widths, &colors)) / (2.0 * h as f64);
            pg.push((sg.points[i][k] as f64, fd));
        }
    }
    let mut wg = Vec::new();
    let mut cg = Vec::new();
    for s_ in 0..widths.len() {
        let mut a = widths.clone();
        let mut b = widths.clone();
        a[s_] += h;
        b[s_] -= h;
        let fd = (f(&points, &a, &colors) - f(&points, &b, &colors)) / (2.0 * h as f64);
        wg.push((sg.widths[s_] as f64, fd));
        for k in 0..3 {
            let mut a = colors.clone();
            let mut b = colors.clone();
            a[s_][k] += h;
            b[s_][k] -= h;
            let fd = (f(&points, &widths, &a) - f(&points, &widths, &b)) / (2.0 * h as f64);
            cg.push((sg.colors[s_][k] as f64, fd));
        }
    }
    let scale_of = |v: &[(f64, f64)]| v.iter().map(|p| p.1.abs()).fold(0.0, f64::max) * 2e-3 + 1e-4;
    compare("strand points", &pg, scale_of(&pg));
    compare("strand widths", &wg, scale_of(&wg));
    compare("strand colours", &cg, scale_of(&cg));
    assert!(pg.iter().any(|p| p.0.abs() > 1e-2));
    assert!(sg.points.iter().all(|p| p.is_finite()));
    assert!(sg.widths.iter().all(|p| p.is_finite()));
}
