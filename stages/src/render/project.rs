//! EWA projection of one Gaussian to a screen-space splat, and its adjoint.
//!
//! Formulas (see the [`crate::render`] module doc): `t = W p + t_w`, `z =
//! -t.z`, `u = cx + fx t.x / z`, `v = cy - fy t.y / z`, `J = [[fx/z, 0, fx
//! rx/z], [0, -fy/z, -fy ry/z]]` (rx, ry clamped), `T = J W` (rows `t0`,
//! `t1`), `Sigma2 = T Sigma3 T^T + low_pass I = [[a, b], [b, c]]`, conic
//! `(A, B, C) = (c, -b, a) / (a c - b^2)`.

// `!(x > y)` is deliberate: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use glam::{Mat3, Quat, Vec2, Vec3};

use super::{RenderSettings, SH_C0, SH_C1};
use crate::data::camera::Camera;

/// Per-Gaussian blended features: RGB, alpha (constant 1), depth, the two
/// orientation components and the fur flag.
pub const NF: usize = 8;
pub const F_ALPHA: usize = 3;
pub const F_DEPTH: usize = 4;
pub const F_OX: usize = 5;
pub const F_OY: usize = 6;
pub const F_FUR: usize = 7;

/// Fraction of the image added on each side of the frustum when clamping the
/// Jacobian's x/z, y/z (3DGS: 1.3 tan(fov/2) for a centred principal point).
const FRUSTUM_MARGIN: f32 = 0.15;

/// Camera quantities used by the projection.
#[derive(Debug, Clone, Copy)]
pub struct CamData {
    /// World-to-camera linear part.
    pub w: Mat3,
    pub tw: Vec3,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
    pub center: Vec3,
    pub rx_lim: (f32, f32),
    pub ry_lim: (f32, f32),
}

impl CamData {
    pub fn new(cam: &Camera) -> Result<Self, super::RenderError> {
        let bad = |m: String| Err(super::RenderError::Camera(m));
        if cam.width == 0 || cam.height == 0 {
            return bad(format!("image size {}x{} is empty", cam.width, cam.height));
        }
        if cam.width > 1 << 15 || cam.height > 1 << 15 {
            return bad(format!(
                "image size {}x{} exceeds 32768",
                cam.width, cam.height
            ));
        }
        for (n, v) in [("fx", cam.fx), ("fy", cam.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!("{n} = {v}, expected a positive focal length"));
            }
        }
        if !(cam.cx.is_finite() && cam.cy.is_finite()) {
            return bad("principal point is not finite".into());
        }
        if !cam.c2w.is_finite() || cam.c2w.determinant().abs() < 1e-20 {
            return bad("c2w is not a finite invertible matrix".into());
        }
        let w2c = cam.w2c();
        if !w2c.is_finite() {
            return bad("c2w is not invertible".into());
        }
        let (wf, hf) = (cam.width as f32, cam.height as f32);
        let (mx, my) = (FRUSTUM_MARGIN * wf, FRUSTUM_MARGIN * hf);
        Ok(CamData {
            w: Mat3::from_mat4(w2c),
            tw: w2c.w_axis.truncate(),
            fx: cam.fx,
            fy: cam.fy,
            cx: cam.cx,
            cy: cam.cy,
            width: cam.width,
            height: cam.height,
            center: cam.center(),
            rx_lim: ((-mx - cam.cx) / cam.fx, (wf + mx - cam.cx) / cam.fx),
            ry_lim: ((cam.cy - hf - my) / cam.fy, (cam.cy + my) / cam.fy),
        })
    }
}

/// A projected Gaussian.
#[derive(Debug, Clone, Copy, Default)]
pub struct Splat {
    /// Pixel coordinates of the mean.
    pub mean: Vec2,
    /// Inverse 2D covariance (A, B, C): power = -0.5 (A dx^2 + C dy^2) - B dx dy.
    pub conic: [f32; 3],
    /// 2D covariance (a, b, c) including the low-pass.
    pub cov: [f32; 3],
    pub opacity: f32,
    /// Squared support radius in Mahalanobis units.
    pub k2: f32,
    pub feat: [f32; NF],
    /// Whether the RGB channel c was clamped at 0 (no gradient).
    pub rgb_clamped: [bool; 3],
    pub visible: bool,
    /// First and last pixel row of the support (filled by the rasteriser).
    pub rows: (i32, i32),
}

/// Normalised quaternion and rotation matrix columns (x, y, z, w order).
#[inline]
fn rot_cols(q: Quat) -> (f32, [f32; 4], [Vec3; 3]) {
    let n = q.length();
    let (x, y, z, w) = if n > 0.0 && n.is_finite() {
        (q.x / n, q.y / n, q.z / n, q.w / n)
    } else {
        (0.0, 0.0, 0.0, 1.0)
    };
    let r0 = Vec3::new(
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y + w * z),
        2.0 * (x * z - w * y),
    );
    let r1 = Vec3::new(
        2.0 * (x * y - w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z + w * x),
    );
    let r2 = Vec3::new(
        2.0 * (x * z + w * y),
        2.0 * (y * z - w * x),
        1.0 - 2.0 * (x * x + y * y),
    );
    (n, [x, y, z, w], [r0, r1, r2])
}

/// `Sigma3 = sum_k s_k^2 r_k r_k^T`.
#[inline]
pub fn cov3(scale: Vec3, rot: Quat) -> Mat3 {
    let (_, _, r) = rot_cols(rot);
    let s2 = scale * scale;
    outer(r[0], r[0]) * s2.x + outer(r[1], r[1]) * s2.y + outer(r[2], r[2]) * s2.z
}

#[inline]
fn outer(a: Vec3, b: Vec3) -> Mat3 {
    Mat3::from_cols(a * b.x, a * b.y, a * b.z)
}

/// Colour for view direction `dir` (unit, camera centre to mean).
#[inline]
fn sh_color(sh: &[Vec3; 4], degree: u32, dir: Vec3) -> Vec3 {
    let mut c = Vec3::splat(0.5) + SH_C0 * sh[0];
    if degree >= 1 {
        c += SH_C1 * (-dir.y * sh[1] + dir.z * sh[2] - dir.x * sh[3]);
    }
    c
}

/// Jacobian rows and the camera-space intermediates.
struct Proj {
    t: Vec3,
    z: f32,
    rx: f32,
    ry: f32,
    clamp_x: bool,
    clamp_y: bool,
    j0: Vec3,
    j1: Vec3,
}

#[inline]
fn jacobian(cam: &CamData, p: Vec3) -> Proj {
    let t = cam.w * p + cam.tw;
    let z = -t.z;
    let rx0 = t.x / z;
    let ry0 = t.y / z;
    let rx = rx0.clamp(cam.rx_lim.0, cam.rx_lim.1);
    let ry = ry0.clamp(cam.ry_lim.0, cam.ry_lim.1);
    Proj {
        t,
        z,
        rx,
        ry,
        clamp_x: rx != rx0,
        clamp_y: ry != ry0,
        j0: Vec3::new(cam.fx / z, 0.0, cam.fx * rx / z),
        j1: Vec3::new(0.0, -cam.fy / z, -cam.fy * ry / z),
    }
}

/// Projects one Gaussian with its `opacity` and fur flag.
pub fn project_one(
    gaussian: GaussianParams,
    opacity: f32,
    fur: bool,
    cam: &CamData,
    s: &RenderSettings,
) -> Splat {
    let GaussianParams {
        mean,
        scale,
        rot,
        sh,
    } = gaussian;
    let mut out = Splat::default();
    let pr = jacobian(cam, mean);
    if !(pr.z >= s.near) || !(opacity > s.alpha_min) || !(opacity > 0.0) {
        return out;
    }
    let sig = cov3(scale, rot);
    let t0 = cam.w.transpose() * pr.j0;
    let t1 = cam.w.transpose() * pr.j1;
    let st0 = sig * t0;
    let st1 = sig * t1;
    let a = t0.dot(st0) + s.low_pass;
    let b = t0.dot(st1);
    let c = t1.dot(st1) + s.low_pass;
    let det = a * c - b * b;
    if !(det > 0.0) || !det.is_finite() {
        return out;
    }
    let mut k2 = s.extent_sigmas * s.extent_sigmas;
    if s.alpha_min > 0.0 {
        k2 = k2.min(2.0 * (opacity / s.alpha_min).ln());
    }
    let u = cam.cx + cam.fx * pr.t.x / pr.z;
    let v = cam.cy - cam.fy * pr.t.y / pr.z;
    // Bounding box of the support, then the image test.
    let (ex, ey) = ((k2 * a).sqrt(), (k2 * c).sqrt());
    let (wf, hf) = (cam.width as f32, cam.height as f32);
    if !(u + ex > 0.0 && u - ex < wf && v + ey > 0.0 && v - ey < hf) {
        return out;
    }
    let dir = (mean - cam.center).normalize_or_zero();
    let col = sh_color(sh, s.sh_degree, dir);
    let inv = 1.0 / det;
    out.mean = Vec2::new(u, v);
    out.conic = [c * inv, -b * inv, a * inv];
    out.cov = [a, b, c];
    out.opacity = opacity;
    out.k2 = k2;
    out.feat = [
        col.x.max(0.0),
        col.y.max(0.0),
        col.z.max(0.0),
        1.0,
        pr.z,
        (a - c) / (a + c),
        2.0 * b / (a + c),
        if fur { 1.0 } else { 0.0 },
    ];
    out.rgb_clamped = [col.x < 0.0, col.y < 0.0, col.z < 0.0];
    out.visible = true;
    out
}

/// Gradient of the loss w.r.t. one splat's screen-space quantities.
#[derive(Debug, Clone, Copy, Default)]
pub struct SplatGrad {
    pub mean: [f32; 2],
    pub conic: [f32; 3],
    pub opacity: f32,
    /// Feature gradients (the alpha feature's entry is unused).
    pub feat: [f32; NF],
}

impl SplatGrad {
    #[inline]
    pub fn add(&mut self, o: &SplatGrad) {
        self.mean[0] += o.mean[0];
        self.mean[1] += o.mean[1];
        for k in 0..3 {
            self.conic[k] += o.conic[k];
        }
        self.opacity += o.opacity;
        for k in 0..NF {
            self.feat[k] += o.feat[k];
        }
    }
}

/// Gradients of one Gaussian's parameters.
#[derive(Debug, Clone, Copy, Default)]
pub struct ParamGrad {
    pub mean: Vec3,
    pub scale: Vec3,
    pub rot: Quat,
    pub opacity: f32,
    pub sh: [Vec3; 4],
    pub cov3d: [f32; 6],
}

/// One Gaussian's geometry and colour, read by [`project_one`] and
/// [`project_backward`].
#[derive(Debug, Clone, Copy)]
pub struct GaussianParams<'a> {
    pub mean: Vec3,
    pub scale: Vec3,
    pub rot: Quat,
    pub sh: &'a [Vec3; 4],
}

impl<'a> GaussianParams<'a> {
    /// Gaussian `i` of `g`.
    #[inline]
    pub fn of(g: &'a super::Gaussians, i: usize) -> Self {
        GaussianParams {
            mean: g.means[i],
            scale: g.scales[i],
            rot: g.rotations[i],
            sh: &g.sh[i],
        }
    }
}

/// Adjoint of the conic (the inverse screen covariance) and of the
/// orientation feature: the gradient on the screen covariance `(a, b, c)`.
#[inline]
fn screen_cov_grad(splat: &Splat, g: &SplatGrad) -> (f32, f32, f32) {
    let [a, b, c] = splat.cov;
    let [ca, cb, cc] = splat.conic;
    // Conic (A, B, C) = (c, -b, a) / det.
    let (ga_c, gb_c, gc_c) = (g.conic[0], g.conic[1], g.conic[2]);
    // The inverse of a symmetric 2x2 matrix has dInv = -Inv dS Inv, so with
    // Gi = [[gA, gB/2], [gB/2, gC]], dL/dS = -Inv Gi Inv (B is one parameter).
    let mut da = -(ga_c * ca * ca + gb_c * ca * cb + gc_c * cb * cb);
    let mut dc = -(ga_c * cb * cb + gb_c * cb * cc + gc_c * cc * cc);
    let mut db = -(2.0 * ga_c * ca * cb + gb_c * (ca * cc + cb * cb) + 2.0 * gc_c * cb * cc);
    // Orientation feature: ox = (a - c) / (a + c), oy = 2 b / (a + c).
    let sum = a + c;
    let (gox, goy) = (g.feat[F_OX], g.feat[F_OY]);
    let inv2 = 1.0 / (sum * sum);
    da += gox * 2.0 * c * inv2 - goy * 2.0 * b * inv2;
    dc += -gox * 2.0 * a * inv2 - goy * 2.0 * b * inv2;
    db += goy * 2.0 / sum;
    (da, db, dc)
}

/// Adjoint onto the camera-space mean `t`: through the Jacobian's entries
/// (gradients `dj0`, `dj1` on its rows), the screen mean and the depth feature.
#[inline]
fn camera_space_grad(pr: &Proj, (dj0, dj1): (Vec3, Vec3), g: &SplatGrad, cam: &CamData) -> Vec3 {
    let z = pr.z;
    // J entries -> camera-space t.
    let (fx, fy) = (cam.fx, cam.fy);
    let z2 = z * z;
    let mut dtx = 0.0f32;
    let mut dty = 0.0f32;
    let mut dz = 0.0f32;
    dz += dj0.x * (-fx / z2);
    if pr.clamp_x {
        dz += dj0.z * (-fx * pr.rx / z2);
    } else {
        dtx += dj0.z * fx / z2;
        dz += dj0.z * (-2.0 * fx * pr.rx / z2);
    }
    dz += dj1.y * (fy / z2);
    if pr.clamp_y {
        dz += dj1.z * (fy * pr.ry / z2);
    } else {
        dty += dj1.z * (-fy / z2);
        dz += dj1.z * (2.0 * fy * pr.ry / z2);
    }
    // Mean: u = cx + fx tx / z, v = cy - fy ty / z.
    let (gu, gv) = (g.mean[0], g.mean[1]);
    dtx += gu * fx / z;
    dz += -gu * fx * pr.t.x / z2;
    dty += -gv * fy / z;
    dz += gv * fy * pr.t.y / z2;
    // Depth feature.
    dz += g.feat[F_DEPTH];
    Vec3::new(dtx, dty, -dz)
}

/// Adjoint of the SH colour: the bands' gradients into `out.sh` and, from
/// band 1, the view direction's share into `out.mean`.
#[inline]
fn sh_backward(
    out: &mut ParamGrad,
    p: &GaussianParams<'_>,
    splat: &Splat,
    g: &SplatGrad,
    cam: &CamData,
    s: &RenderSettings,
) {
    let sh = p.sh;
    let dcol = Vec3::new(
        if splat.rgb_clamped[0] { 0.0 } else { g.feat[0] },
        if splat.rgb_clamped[1] { 0.0 } else { g.feat[1] },
        if splat.rgb_clamped[2] { 0.0 } else { g.feat[2] },
    );
    out.sh[0] = SH_C0 * dcol;
    if s.sh_degree >= 1 {
        let rel = p.mean - cam.center;
        let len = rel.length();
        if len > 0.0 {
            let dir = rel / len;
            out.sh[1] = -SH_C1 * dir.y * dcol;
            out.sh[2] = SH_C1 * dir.z * dcol;
            out.sh[3] = -SH_C1 * dir.x * dcol;
            let ddir = SH_C1 * Vec3::new(-sh[3].dot(dcol), -sh[1].dot(dcol), sh[2].dot(dcol));
            out.mean += (ddir - dir * dir.dot(ddir)) / len;
        }
    }
}

/// Adjoint of `Sigma3 = sum_k s_k^2 r_k r_k^T` given its gradient `g3`:
/// `out.cov3d`, `out.scale` and `out.rot` (through the raw quaternion's
/// normalisation).
#[inline]
fn cov3_backward(out: &mut ParamGrad, g3: Mat3, scale: Vec3, rot: Quat) {
    let g3c = [g3.x_axis, g3.y_axis, g3.z_axis];
    out.cov3d = [
        g3c[0].x,
        g3c[1].x + g3c[0].y,
        g3c[2].x + g3c[0].z,
        g3c[1].y,
        g3c[2].y + g3c[1].z,
        g3c[2].z,
    ];
    let (n, [x, y, zq, w], r) = rot_cols(rot);
    let s2 = scale * scale;
    let gr0 = g3 * r[0];
    let gr1 = g3 * r[1];
    let gr2 = g3 * r[2];
    out.scale = Vec3::new(
        2.0 * scale.x * r[0].dot(gr0),
        2.0 * scale.y * r[1].dot(gr1),
        2.0 * scale.z * r[2].dot(gr2),
    );
    let g0 = 2.0 * s2.x * gr0;
    let g1 = 2.0 * s2.y * gr1;
    let g2 = 2.0 * s2.z * gr2;
    if n > 0.0 && n.is_finite() {
        let dw = 2.0 * (g0.y * zq - g0.z * y - g1.x * zq + g1.z * x + g2.x * y - g2.y * x);
        let dx = 2.0 * (y * g0.y + zq * g0.z + y * g1.x + w * g1.z + zq * g2.x - w * g2.y)
            - 4.0 * x * (g1.y + g2.z);
        let dy = 2.0 * (x * g0.y - w * g0.z + x * g1.x + zq * g1.z + w * g2.x + zq * g2.y)
            - 4.0 * y * (g0.x + g2.z);
        let dzq = 2.0 * (w * g0.y + x * g0.z - w * g1.x + y * g1.z + x * g2.x + y * g2.y)
            - 4.0 * zq * (g0.x + g1.y);
        let dq = glam::Vec4::new(dx, dy, dzq, dw);
        let qn = glam::Vec4::new(x, y, zq, w);
        let draw = (dq - qn * qn.dot(dq)) / n;
        out.rot = Quat::from_xyzw(draw.x, draw.y, draw.z, draw.w);
    }
}

/// Adjoint of [`project_one`] for a visible splat.
pub fn project_backward(
    p: GaussianParams<'_>,
    splat: &Splat,
    g: &SplatGrad,
    cam: &CamData,
    s: &RenderSettings,
) -> ParamGrad {
    let mut out = ParamGrad {
        rot: Quat::from_xyzw(0.0, 0.0, 0.0, 0.0),
        ..Default::default()
    };
    if !splat.visible {
        return out;
    }
    out.opacity = g.opacity;
    let pr = jacobian(cam, p.mean);
    let (da, db, dc) = screen_cov_grad(splat, g);
    // Sigma2 = T Sigma3 T^T.
    let sig = cov3(p.scale, p.rot);
    let t0 = cam.w.transpose() * pr.j0;
    let t1 = cam.w.transpose() * pr.j1;
    let st0 = sig * t0;
    let st1 = sig * t1;
    let g3 = outer(t0, t0) * da + (outer(t0, t1) + outer(t1, t0)) * (0.5 * db) + outer(t1, t1) * dc;
    let dt0 = 2.0 * da * st0 + db * st1;
    let dt1 = 2.0 * dc * st1 + db * st0;
    let dj0 = cam.w * dt0;
    let dj1 = cam.w * dt1;
    let dt = camera_space_grad(&pr, (dj0, dj1), g, cam);
    out.mean = cam.w.transpose() * dt;
    // Colour (SH).
    sh_backward(&mut out, &p, splat, g, cam, s);
    // Sigma3 = sum_k s_k^2 r_k r_k^T.
    cov3_backward(&mut out, g3, p.scale, p.rot);
    out
}
