//! Finite-difference and behaviour tests of the renderer.

#![allow(clippy::needless_range_loop)]

use glam::{Mat4, Quat, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;
use crate::data::camera::Camera;
use crate::data::image::ImageF32;

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

pub(crate) fn random_image(rng: &mut ChaCha8Rng, w: u32, h: u32, c: u32, amp: f32) -> ImageF32 {
    let mut im = ImageF32::new(w, h, c);
    for v in im.data.iter_mut() {
        *v = rng.gen_range(-amp..amp);
    }
    im
}

/// Random gradients of every output (depth at a smaller amplitude).
pub(crate) fn random_output_grads(rng: &mut ChaCha8Rng, w: u32, h: u32) -> OutputGrads {
    OutputGrads {
        rgb: Some(random_image(rng, w, h, 3, 1.0)),
        alpha: Some(random_image(rng, w, h, 1, 1.0)),
        depth: Some(random_image(rng, w, h, 1, 0.3)),
        orientation: Some(random_image(rng, w, h, 2, 1.0)),
        fur: Some(random_image(rng, w, h, 1, 1.0)),
    }
}

/// A scalar loss that is linear in every output, and its output gradients.
struct LinearLoss {
    dl: OutputGrads,
}

impl LinearLoss {
    fn new(rng: &mut ChaCha8Rng, w: u32, h: u32) -> Self {
        LinearLoss {
            dl: random_output_grads(rng, w, h),
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

/// A brute-force reference: every Gaussian at every pixel, depth-sorted.
fn brute_force(g: &Gaussians, cam: &Camera, s: &RenderSettings) -> RenderOutput {
    use super::project::{project_one, CamData, GaussianParams, F_DEPTH, NF};
    let cd = CamData::new(cam).unwrap();
    let mut sp: Vec<_> = (0..g.len())
        .map(|i| project_one(GaussianParams::of(g, i), g.opacities[i], g.fur[i], &cd, s))
        .filter(|p| p.visible)
        .collect();
    sp.sort_by(|a, b| a.feat[F_DEPTH].total_cmp(&b.feat[F_DEPTH]));
    let (w, h) = (cam.width, cam.height);
    let mut out = RenderOutput::zeros(w, h);
    for y in 0..h {
        for x in 0..w {
            let mut t = 1.0f32;
            let mut acc = [0.0f32; NF];
            for p in &sp {
                let dx = x as f32 + 0.5 - p.mean.x;
                let dy = y as f32 + 0.5 - p.mean.y;
                let [a, b, c] = p.conic;
                let q = a * dx * dx + c * dy * dy + 2.0 * b * dx * dy;
                if q > p.k2 {
                    continue;
                }
                let alpha = (p.opacity * (-0.5 * q).exp()).min(s.alpha_max);
                if alpha < s.alpha_min {
                    continue;
                }
                let tn = t * (1.0 - alpha);
                if tn < s.transmittance_min {
                    break;
                }
                for k in 0..NF {
                    acc[k] += p.feat[k] * alpha * t;
                }
                t = tn;
            }
            let i = (y * w + x) as usize;
            for k in 0..3 {
                out.rgb.data[3 * i + k] = acc[k] + t * s.background[k];
            }
            out.alpha.data[i] = 1.0 - t;
            out.depth.data[i] = acc[4];
            out.orientation.data[2 * i] = acc[5];
            out.orientation.data[2 * i + 1] = acc[6];
            out.fur.data[i] = acc[7];
        }
    }
    out
}

fn max_diff(a: &ImageF32, b: &ImageF32) -> f32 {
    a.data
        .iter()
        .zip(&b.data)
        .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()))
}

#[test]
fn tiled_render_matches_brute_force_reference() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut g = random_gaussians(&mut rng, 300);
    // Spread them so some straddle tile borders and the image edge.
    for m in g.means.iter_mut() {
        *m *= 2.5;
    }
    let cam = test_camera(50, Vec3::new(0.5, 1.0, 5.0), Vec3::ZERO);
    for s in [
        RenderSettings::default(),
        RenderSettings {
            background: Vec3::new(1.0, 0.5, 0.0),
            sh_degree: 1,
            ..RenderSettings::smooth()
        },
    ] {
        let (out, st) = render(&g, &cam, &s).unwrap();
        let reference = brute_force(&g, &cam, &s);
        assert!(st.instance_count() > 300, "{}", st.instance_count());
        assert!(out.alpha.data.iter().filter(|&&a| a > 0.5).count() > 200);
        for (name, a, b) in [
            ("rgb", &out.rgb, &reference.rgb),
            ("alpha", &out.alpha, &reference.alpha),
            ("depth", &out.depth, &reference.depth),
            ("orientation", &out.orientation, &reference.orientation),
            ("fur", &out.fur, &reference.fur),
        ] {
            let d = max_diff(a, b);
            assert!(d < 1e-4, "{name}: max difference {d}");
        }
    }
}

fn grads_bits(gr: &GaussianGrads) -> Vec<u32> {
    let mut v = Vec::new();
    for i in 0..gr.len() {
        v.extend(gr.means[i].to_array().map(f32::to_bits));
        v.extend(gr.scales[i].to_array().map(f32::to_bits));
        v.extend(gr.rotations[i].to_array().map(f32::to_bits));
        v.push(gr.opacities[i].to_bits());
        for c in gr.sh[i] {
            v.extend(c.to_array().map(f32::to_bits));
        }
        v.extend(gr.cov3d[i].map(f32::to_bits));
    }
    v
}

/// 3,000 random Gaussians, small and spread over a 64 px view (many per
/// tile, so thread counts and summation orders have work to differ on), and
/// degree-1 settings.
fn crowded_scene(rng: &mut ChaCha8Rng) -> (Gaussians, RenderSettings) {
    let mut g = random_gaussians(rng, 3000);
    for (m, s) in g.means.iter_mut().zip(g.scales.iter_mut()) {
        *m *= 2.0;
        *s *= 0.4;
    }
    let s = RenderSettings {
        sh_degree: 1,
        ..Default::default()
    };
    (g, s)
}

#[test]
fn images_and_gradients_are_identical_for_any_thread_count() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (g, s) = crowded_scene(&mut rng);
    let cam = test_camera(64, Vec3::new(0.0, 0.5, 4.5), Vec3::ZERO);
    let loss = LinearLoss::new(&mut rng, 64, 64);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let (out, st) = render(&g, &cam, &s).unwrap();
            let gr = backward(&g, &cam, &s, &st, &loss.dl).unwrap();
            let img: Vec<u32> = out.rgb.data.iter().map(|v| v.to_bits()).collect();
            (img, grads_bits(&gr))
        })
    };
    let one = run(1);
    assert!(one.1.iter().any(|&b| f32::from_bits(b) != 0.0));
    for threads in [2, 3, 8] {
        let other = run(threads);
        assert!(one.0 == other.0, "image differs with {threads} threads");
        assert!(one.1 == other.1, "gradients differ with {threads} threads");
    }
}

#[test]
fn degenerate_inputs_give_finite_results() {
    let cam = test_camera(32, Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO);
    let mut g = Gaussians::default();
    let rgb = Vec3::splat(0.5);
    // Behind the camera, at the camera centre, far outside the image, zero
    // scales, zero quaternion, huge and tiny Gaussians, zero opacity.
    g.push(
        Vec3::new(0.0, 0.0, 5.0),
        Vec3::splat(0.2),
        Quat::IDENTITY,
        0.8,
        rgb,
        false,
    );
    g.push(
        Vec3::new(0.0, 0.0, 3.0),
        Vec3::splat(0.2),
        Quat::IDENTITY,
        0.8,
        rgb,
        false,
    );
    g.push(
        Vec3::new(50.0, 0.0, 0.0),
        Vec3::splat(0.2),
        Quat::IDENTITY,
        0.8,
        rgb,
        false,
    );
    g.push(Vec3::ZERO, Vec3::ZERO, Quat::IDENTITY, 0.8, rgb, true);
    g.push(
        Vec3::new(0.1, 0.0, 0.0),
        Vec3::splat(0.1),
        Quat::from_xyzw(0.0, 0.0, 0.0, 0.0),
        0.8,
        rgb,
        true,
    );
    g.push(
        Vec3::new(0.0, 0.1, 0.0),
        Vec3::splat(1e4),
        Quat::IDENTITY,
        0.5,
        rgb,
        true,
    );
    g.push(
        Vec3::new(0.0, -0.1, 0.0),
        Vec3::splat(1e-20),
        Quat::IDENTITY,
        0.5,
        rgb,
        true,
    );
    g.push(
        Vec3::new(0.2, 0.1, 0.0),
        Vec3::splat(0.1),
        Quat::IDENTITY,
        0.0,
        rgb,
        true,
    );
    // A strand with a zero-length and an anti-parallel segment.
    let pts = [
        Vec3::new(0.3, 0.3, 0.0),
        Vec3::new(0.3, 0.3, 0.0),
        Vec3::new(-0.3, 0.3, 0.0),
        Vec3::new(0.3, 0.3, 0.0),
    ];
    let sg = strands_to_gaussians(&pts, &[0, 4], &[0.02], &[[0.9, 0.1, 0.1]], true).unwrap();
    g.means.extend(&sg.means);
    g.scales.extend(&sg.scales);
    g.rotations.extend(&sg.rotations);
    g.opacities.extend(&sg.opacities);
    g.sh.extend(&sg.sh);
    g.fur.extend(&sg.fur);
    for s in [RenderSettings::default(), RenderSettings::smooth()] {
        let (out, st) = render(&g, &cam, &s).unwrap();
        for img in [&out.rgb, &out.alpha, &out.depth, &out.orientation, &out.fur] {
            assert!(img.data.iter().all(|v| v.is_finite()));
        }
        assert!(!st.splats_visible(0) && !st.splats_visible(1) && !st.splats_visible(2));
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let loss = LinearLoss::new(&mut rng, 32, 32);
        let gr = backward(&g, &cam, &s, &st, &loss.dl).unwrap();
        assert!(grads_bits(&gr)
            .iter()
            .all(|&b| f32::from_bits(b).is_finite()));
        let n = sg.len();
        let sgr = GaussianGrads {
            means: gr.means[g.len() - n..].to_vec(),
            cov3d: gr.cov3d[g.len() - n..].to_vec(),
            sh: gr.sh[g.len() - n..].to_vec(),
            ..Default::default()
        };
        let back = strands_backward(&pts, &[0, 4], &[0.02], &sgr).unwrap();
        assert!(back.points.iter().all(|p| p.is_finite()));
        assert!(back.points.iter().any(|p| p.length() > 0.0));
    }
    // Non-finite input is an error naming the array and index.
    let mut bad = g.clone();
    bad.means[3].x = f32::NAN;
    let e = render(&bad, &cam, &RenderSettings::default()).unwrap_err();
    assert!(e.to_string().contains("means[3]"), "{e}");
    bad.means[3].x = 0.0;
    bad.opacities.pop();
    assert!(render(&bad, &cam, &RenderSettings::default()).is_err());
}

#[test]
fn orientation_channel_follows_the_image_convention() {
    use std::f32::consts::PI;
    // Camera on +z looking at the origin: world +x is right, world -y is down.
    let cam = test_camera(32, Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO);
    for (dir, want) in [
        (Vec3::new(1.0, 0.0, 0.0), 0.0),
        (Vec3::new(1.0, -1.0, 0.0), 0.25 * PI),
        (Vec3::new(0.0, 1.0, 0.0), 0.5 * PI),
        (Vec3::new(-1.0, -1.0, 0.0), 0.75 * PI),
    ] {
        let pts = [-0.4 * dir, 0.4 * dir];
        let g = strands_to_gaussians(&pts, &[0, 2], &[0.01], &[[1.0; 3]], true).unwrap();
        let (out, _) = render(&g, &cam, &RenderSettings::default()).unwrap();
        let o = out.orientation.pixel(16, 16);
        let theta = orientation_from_feature(o[0], o[1]);
        let (d, _) = losses::angle_diff(theta, want);
        assert!(d < 0.02, "{dir:?}: theta {theta}, want {want}");
        // Thin strands are strongly anisotropic on screen.
        assert!((o[0] * o[0] + o[1] * o[1]).sqrt() > 0.8 * out.alpha.pixel(16, 16)[0]);
        // The segment direction's screen projection has the same orientation.
        let (a, _) = cam.project(pts[0]);
        let (b, _) = cam.project(pts[1]);
        let t2 = orientation_angle(b.x - a.x, b.y - a.y);
        assert!(losses::angle_diff(t2, want).0 < 1e-3);
    }
}

#[test]
fn compositing_is_front_to_back_whatever_the_input_order() {
    let cam = test_camera(32, Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO);
    let mut g = Gaussians::default();
    let red = Vec3::new(1.0, 0.0, 0.0);
    let blue = Vec3::new(0.0, 0.0, 1.0);
    // Back (blue) first in the input, front (red) second.
    g.push(
        Vec3::new(0.0, 0.0, -0.5),
        Vec3::splat(0.5),
        Quat::IDENTITY,
        0.95,
        blue,
        false,
    );
    g.push(
        Vec3::new(0.0, 0.0, 0.5),
        Vec3::splat(0.5),
        Quat::IDENTITY,
        0.95,
        red,
        true,
    );
    let (out, _) = render(&g, &cam, &RenderSettings::default()).unwrap();
    let c = out.rgb.pixel(16, 16);
    // Front alpha 0.95: red 0.95, blue 0.05 * 0.95.
    assert!(
        (c[0] - 0.95).abs() < 0.01 && (c[2] - 0.0475).abs() < 0.01,
        "{c:?}"
    );
    assert!((out.fur.pixel(16, 16)[0] - 0.95).abs() < 0.01);
    // Depth: 0.95 * 2.5 + 0.0475 * 3.5.
    let d = out.depth.pixel(16, 16)[0];
    assert!((d - (0.95 * 2.5 + 0.0475 * 3.5)).abs() < 0.02, "{d}");
    // The peak sits at the projected mean.
    let (uv, _) = cam.project(Vec3::new(0.0, 0.0, 0.5));
    assert!((uv.x - 16.0).abs() < 1e-4 && (uv.y - 16.0).abs() < 1e-4);
}

#[test]
fn bad_settings_cameras_and_gradient_images_are_errors() {
    let cam = test_camera(16, Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO);
    let mut g = Gaussians::default();
    g.push(
        Vec3::ZERO,
        Vec3::splat(0.2),
        Quat::IDENTITY,
        0.5,
        Vec3::ONE,
        false,
    );
    for s in [
        RenderSettings {
            alpha_max: 1.0,
            ..Default::default()
        },
        RenderSettings {
            sh_degree: 2,
            ..Default::default()
        },
        RenderSettings {
            near: 0.0,
            ..Default::default()
        },
    ] {
        assert!(matches!(
            render(&g, &cam, &s),
            Err(RenderError::Settings(_))
        ));
    }
    let mut bad_cam = cam.clone();
    bad_cam.fx = 0.0;
    assert!(matches!(
        render(&g, &bad_cam, &RenderSettings::default()),
        Err(RenderError::Camera(_))
    ));
    let s = RenderSettings::default();
    let (_, st) = render(&g, &cam, &s).unwrap();
    let dl = OutputGrads {
        rgb: Some(ImageF32::new(16, 16, 1)),
        ..Default::default()
    };
    let e = backward(&g, &cam, &s, &st, &dl).unwrap_err();
    assert!(e.to_string().contains("rgb gradient"), "{e}");
    let mut g2 = g.clone();
    g2.push(Vec3::ONE, Vec3::ONE, Quat::IDENTITY, 0.5, Vec3::ONE, false);
    assert!(backward(&g2, &cam, &s, &st, &OutputGrads::default()).is_err());
    // No output gradient: all parameter gradients are exactly zero.
    let gr = backward(&g, &cam, &s, &st, &OutputGrads::default()).unwrap();
    assert!(grads_bits(&gr).iter().all(|&b| f32::from_bits(b) == 0.0));
}

#[test]
fn blend_sums_are_the_colour_gradients_and_add_up_to_the_alpha() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (g, s) = crowded_scene(&mut rng);
    let cam = test_camera(64, Vec3::new(0.3, 0.5, 4.5), Vec3::ZERO);
    let mut target = random_image(&mut rng, 64, 64, 3, 1.0);
    target.data.iter_mut().for_each(|v| *v = v.abs());
    let mut weight = ImageF32::new(64, 64, 1);
    weight
        .data
        .iter_mut()
        .for_each(|v| *v = if rng.gen_bool(0.7) { 1.0 } else { 0.0 });
    let sums = blend_sums(&g, &cam, &s, &target, &weight).unwrap();
    // Against the backward pass of the linear losses.
    let by_backward = device::Renderer::Cpu
        .blend_sums_by_backward(&g, &cam, &s, &target, &weight)
        .unwrap();
    let scale = sums.iter().flatten().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(scale > 1.0, "the view should blend whole pixels: {scale}");
    let worst = sums
        .iter()
        .flatten()
        .zip(by_backward.iter().flatten())
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(worst < 1e-4 * scale, "worst {worst} of {scale}");
    // Every pixel's weights add up to its alpha.
    let (out, _) = render(&g, &cam, &s).unwrap();
    let expected: f64 = out
        .alpha
        .data
        .iter()
        .zip(&weight.data)
        .map(|(a, w)| (a * w) as f64)
        .sum();
    let total: f64 = sums.iter().map(|v| v[3] as f64).sum();
    assert!(
        (total - expected).abs() < 1e-4 * expected,
        "{total} against {expected}"
    );
    // Any thread count gives the same bits.
    let bits = |threads: usize| -> Vec<u32> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| blend_sums(&g, &cam, &s, &target, &weight).unwrap())
            .iter()
            .flatten()
            .map(|v| v.to_bits())
            .collect()
    };
    assert_eq!(bits(1), bits(3));
}
