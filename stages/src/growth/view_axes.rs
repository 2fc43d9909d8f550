//! The fur's axis at each root, read from the views: the Gabor orientation
//! maps lifted onto the root's tangent plane and pooled over views and
//! neighbouring roots.
//!
//! Why. The roots' frames come from a smooth field aligned to an anatomical
//! prior (`roots`), and the orientation loss is pi-periodic and confidence
//! weighted: from a frame far off the fur (a coat that does not follow the
//! prior, or a deliberately turned start) gradient steps turn it slowly and
//! stop in between. The orientation term of one straight segment has a
//! closed-form minimiser, though: each view's map gives a line in the image,
//! and the line in the tangent plane that projects onto it is one 2x2 solve.
//! Pooling those lines over views (and over roots within a few pixel
//! footprints, which averages the maps' per-pixel noise) gives the axis the
//! orientation loss is pulling toward, without the descent.
//!
//! How, per root `p` with frame `(T, B, N)`:
//! - Where the fur is seen: `q`, the closest point on the outer surface (the
//!   fur's envelope; the root itself lies under the fur). A view counts when
//!   `q` lies in front of the camera and inside the image, the envelope's
//!   normal faces the camera, and a ray from `q` (lifted off the surface by
//!   `1e-3` of the envelope's bounding-box diagonal) to the camera hits
//!   nothing.
//! - The view's pixel at `q` gives the map angle `alpha` (image x right, y
//!   down, modulo pi) and the normalised confidence `c`. `J`, the 2x2
//!   Jacobian of the projection along `T` and `B` at `q`, maps tangent
//!   directions to image directions, so the tangent line seen along `alpha`
//!   is `d = J^-1 (cos alpha, sin alpha)`.
//! - The view adds `w d d^T` (3D, unit `d`) to the root's structure tensor,
//!   `w = c cos^2(view angle)`: at grazing views `J` is near singular and a
//!   small image-angle error is a large tangent-plane one.
//! - Pooling: every root sums the tensors of the roots within `radius` of it
//!   (itself included; optionally only those of its own part), projects the sum onto its own tangent plane and takes
//!   the principal direction; the coherence `(l1 - l2) / (l1 + l2)` of the
//!   2x2 tensor says how much the views agree (1: one line; 0: none).
//!
//! The null. Lines lifted from maps that carry no direction at all still
//! agree: `J^-1` stretches image directions along the tangent axis the view
//! foreshortens, so a uniform image angle lifts to lines whose mean outer
//! product is `sqrt(P) / tr sqrt(P)` with `P = J^-1 J^-T` (the singular
//! values of `J^-1` in proportion), and views that see a root from one side
//! foreshorten alike. Measured with random maps on the benchmark's roots and
//! cameras: mean coherence 0.11-0.13, a fifth to a quarter of the roots at
//! 0.2 or more. Each view therefore also adds `w` times that expectation to
//! a null tensor, pooled the same way, and [`ViewAxis::excess_coherence`] is
//! the anisotropy of the pooled tensor minus the null's, over the trace: near
//! 0 for random maps (up to sampling noise), near 1 for a line field seen
//! from any side. The turn itself still comes from the pooled tensor: a true
//! line that lies along the stretched axis is where the null leans too, and
//! subtracting it would bias the axis.
//!
//! Windows a part barely fills. A window of a few pixel footprints is wider
//! than a small part (an ear a few pixels across), so such a root's pooled
//! line is mostly its neighbours' (the head's fur runs across the ear's).
//! [`own_part_shares`] gives, per root, the share of its window that its own
//! part fills; callers keep the roots' own frames where it is low (learn
//! module doc).
//!
//! Fur off the tangent plane. The lift assumes the fur lies near the
//! tangent plane. Fur that hangs under a belly or stands up along the
//! normal projects into each view as the normal does, and the tangent line
//! that projects the same way runs toward that camera: the pooled axis is
//! then the views' layout, not the fur. The planes each view's line spans
//! with its camera centre meet in the fur's 3D line
//! ([`view_elevations`]); [`steep_roots`] marks the roots where that line
//! rises above a given elevation, so that a caller can keep their frames.
//! A reading counts only where the planes differ
//! ([`ViewElevation::spread`]): one view, or views from one side, leave the
//! line anywhere in a plane.
//!
//! The result is an axis (no sign): a map cannot tell root from tip. Callers
//! keep the sign of the frame they had (the axis is turned by at most 90
//! degrees); [`vote_signs`] then lets neighbours outvote a root that kept
//! the wrong side. Sums over views and neighbours run in a fixed order, so the
//! result does not depend on the thread count.

use glam::{Mat3, Vec2, Vec3};
use rayon::prelude::*;

use crate::data::camera::Camera;
use crate::data::image::ImageF32;
use crate::data::mesh::Mesh;
use crate::maths::geom::{GeomError, MeshQuery, PointIndex};

/// One training view's orientation map: the camera, the Gabor angle (radians
/// in `[0, pi)`, image x right, y down) and the normalised confidence, at the
/// camera's size.
#[derive(Debug, Clone, Copy)]
pub struct ViewOrientation<'a> {
    pub camera: &'a Camera,
    pub angle: &'a ImageF32,
    pub confidence: &'a ImageF32,
}

impl<'a> ViewOrientation<'a> {
    /// Pairs each camera with its `(angle, confidence)` maps.
    pub fn pair(cameras: &'a [Camera], maps: &'a [(ImageF32, ImageF32)]) -> Vec<Self> {
        cameras
            .iter()
            .zip(maps)
            .map(|(camera, (angle, confidence))| ViewOrientation {
                camera,
                angle,
                confidence,
            })
            .collect()
    }
}

/// A root's axis from the views.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewAxis {
    /// Angle from the frame's tangent `T` toward `B` of the pooled axis, in
    /// `(-pi/2, pi/2]` (so turning by it keeps `T`'s sign as far as it can).
    pub turn: f32,
    /// Agreement of the pooled lines: `(l1 - l2) / (l1 + l2)` in `[0, 1]`
    /// (0 when no view saw the root or its neighbours).
    pub coherence: f32,
    /// The agreement beyond what the views' geometry alone gives: the
    /// anisotropy of the pooled tensor minus that of its expectation under
    /// uniformly random map angles, over the trace (module doc, "The null").
    pub excess_coherence: f32,
    /// Views that saw the root itself.
    pub views: u32,
}

/// Per root, the share of the roots within `radius` of it (itself included)
/// that lie on its own part (`labels`, one per root): how much of its
/// pooling window its own part fills (1 everywhere when `radius` is 0).
pub fn own_part_shares(
    positions: &[Vec3],
    labels: &[u16],
    radius: f32,
) -> Result<Vec<f32>, GeomError> {
    window_shares(positions, radius, |i, j| labels.get(j) == labels.get(i))
}

/// Per root, the share of the roots within `radius` (itself included) that
/// `steep` marks (each root's own mark when `radius` is 0). Why: a steep root
/// that keeps the roots' frame beside neighbours that turn onto the views'
/// axes leaves a seam where the two meet; turning each root by the share of
/// its window that is not steep eases one into the other over the window.
pub fn steep_shares(
    positions: &[Vec3],
    steep: &[bool],
    radius: f32,
) -> Result<Vec<f32>, GeomError> {
    window_shares(positions, radius, |_, j| steep.get(j) == Some(&true))
}

/// Per root `i`, the share of the roots `j` within `radius` (itself
/// included) for which `counts(i, j)` holds; with no window, `counts(i, i)`.
fn window_shares(
    positions: &[Vec3],
    radius: f32,
    counts: impl Fn(usize, usize) -> bool + Sync,
) -> Result<Vec<f32>, GeomError> {
    if radius <= 0.0 || positions.is_empty() {
        return Ok((0..positions.len())
            .map(|i| counts(i, i) as u8 as f32)
            .collect());
    }
    let index = PointIndex::new(positions)?;
    Ok(positions
        .par_iter()
        .enumerate()
        .map(|(i, &p)| {
            let (n, all) = index.count_within(p, radius, |j| counts(i, j as usize));
            n as f32 / all.max(1) as f32
        })
        .collect())
}

/// Lifts the maps onto every root's tangent plane (module doc). `frames`
/// are the roots' `(T, B, N)` as columns; `outer` is the fur's envelope;
/// `radius` is the pooling radius in scene units (0 = each root alone); with
/// `parts` (one label per root) a root pools only the roots of its own part.
pub fn view_axes(
    positions: &[Vec3],
    frames: &[Mat3],
    outer: &Mesh,
    views: &[ViewOrientation<'_>],
    radius: f32,
    parts: Option<&[u16]>,
) -> Result<Vec<ViewAxis>, GeomError> {
    let query = MeshQuery::new(outer)?;
    let (lo, hi) = outer.bounds();
    let lift = 1e-3 * (hi - lo).length();
    let own: Vec<([f32; 6], [f32; 6], u32)> = positions
        .par_iter()
        .zip(frames.par_iter())
        .map(|(&p, f)| root_tensor(p, f, &query, outer, views, lift))
        .collect();
    let index = if radius > 0.0 {
        Some(PointIndex::new(positions)?)
    } else {
        None
    };
    let axes = positions
        .par_iter()
        .enumerate()
        .map(|(i, &p)| {
            let (mut s, mut z) = ([0.0f64; 6], [0.0f64; 6]);
            let mut add = |(t, n, _): &([f32; 6], [f32; 6], u32)| {
                for (a, b) in s.iter_mut().zip(t) {
                    *a += *b as f64;
                }
                for (a, b) in z.iter_mut().zip(n) {
                    *a += *b as f64;
                }
            };
            match &index {
                Some(ix) => {
                    // Ascending indices: a fixed summation order.
                    for j in ix.indices_within(p, radius) {
                        if same_part(parts, i, j as usize) {
                            add(&own[j as usize]);
                        }
                    }
                }
                None => add(&own[i]),
            }
            let (t, b) = (frames[i].x_axis.as_dvec3(), frames[i].y_axis.as_dvec3());
            // The tensor's (along T, along B, across) in the root's tangent plane.
            let plane = |s: &[f64; 6]| {
                let quad = |u: glam::DVec3, v: glam::DVec3| {
                    u.x * (s[0] * v.x + s[1] * v.y + s[2] * v.z)
                        + u.y * (s[1] * v.x + s[3] * v.y + s[4] * v.z)
                        + u.z * (s[2] * v.x + s[4] * v.y + s[5] * v.z)
                };
                (quad(t, t), quad(b, b), quad(t, b))
            };
            let (a, c, bb) = plane(&s);
            let (na, nc, nb) = plane(&z);
            let views = own[i].2;
            let trace = a + c;
            if !(trace > 0.0) {
                return ViewAxis {
                    turn: 0.0,
                    coherence: 0.0,
                    excess_coherence: 0.0,
                    views,
                };
            }
            let turn = 0.5 * (2.0 * bb).atan2(a - c);
            let coherence = ((a - c).powi(2) + 4.0 * bb * bb).sqrt() / trace;
            let excess = (((a - c) - (na - nc)).powi(2) + 4.0 * (bb - nb).powi(2)).sqrt() / trace;
            ViewAxis {
                turn: turn as f32,
                coherence: coherence.clamp(0.0, 1.0) as f32,
                excess_coherence: excess.clamp(0.0, 1.0) as f32,
                views,
            }
        })
        .collect();
    Ok(axes)
}

/// One root's reading of [`view_elevations`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewElevation {
    /// The root's index.
    pub root: usize,
    /// Radians in `[0, pi/2]` above the envelope.
    pub elevation: f32,
    /// The line the views agree on: a unit direction, pointing away from the
    /// envelope (its sign is the line's only where the line leaves the
    /// envelope's tangent plane).
    pub line: Vec3,
    /// How far apart the planes are: the pooled tensor's middle eigenvalue
    /// over its largest, in `[0, 1]`. Near 0 when every plane is nearly the
    /// same (one view, or views from one side): the direction is then only
    /// known to lie in that plane, and its elevation is the power
    /// iteration's pick, not a reading. Two equal planes at angle `phi`
    /// give `tan^2(phi / 2)`.
    pub spread: f32,
    /// The elevation the same views would read from maps that carry no
    /// direction (radians; [`PlaneTensors::with_null`], "The elevation's
    /// null"): where [`Self::elevation`] lies near it, the reading is the
    /// cameras' layout. `None` from tensors made without it.
    pub null_elevation: Option<f32>,
}

/// The fur's elevation above the envelope read from the views, at every
/// `stride`-th root whose neighbourhood some view saw. Each view's Gabor
/// line at the root's envelope point, with the camera centre, spans a plane
/// that holds the fur's 3D direction; the plane normals' outer products
/// (weight: the map's confidence times the cosine of the view angle; views
/// within about 78 degrees of grazing, unoccluded) are summed over the
/// roots within `radius`, and the direction closest to lying in all those
/// planes is the sum's least eigenvector. A line has no sign, so neither has
/// the elevation. Per root it is noisy (the views see the coat's surface,
/// not each strand); the learners use its median over the roots (module doc
/// of `learn`) and, optionally, where it is steep ([`steep_roots`]). One
/// reading; [`PlaneTensors`] keeps the per-root tensors for several.
pub fn view_elevations(
    positions: &[Vec3],
    outer: &Mesh,
    views: &[ViewOrientation<'_>],
    radius: f32,
    stride: usize,
) -> Result<Vec<ViewElevation>, GeomError> {
    Ok(PlaneTensors::new(positions, outer, views)?.elevations(radius, stride))
}

/// A reading of [`view_elevations`] counts in [`steep_roots`] only where
/// its planes are at least this far apart ([`ViewElevation::spread`]; two
/// views about 25 degrees apart): planes that nearly coincide leave the
/// direction anywhere in them.
pub const MIN_PLANE_SPREAD: f32 = 0.05;

/// Per root, whether the views read its fur rising more than `max_elevation`
/// (radians) off the envelope ([`view_elevations`] pooled within `radius`,
/// every root, readings whose planes are at least [`MIN_PLANE_SPREAD`]
/// apart). Why: the turn onto the views' axes lifts each view's line onto
/// the tangent plane, which is the fur's line only while the fur lies near
/// that plane; the line of fur that hangs or stands along the normal lifts
/// to a direction it does not have.
pub fn steep_roots(
    positions: &[Vec3],
    outer: &Mesh,
    views: &[ViewOrientation<'_>],
    radius: f32,
    max_elevation: f32,
) -> Result<Vec<bool>, GeomError> {
    Ok(PlaneTensors::new(positions, outer, views)?.steep_roots(radius, max_elevation))
}

/// Every root's envelope normal and plane-normal tensor (the views' part of
/// [`view_elevations`]), made once and pooled at any radius: the per-root
/// tensors (a ray to every camera per root) cost far more than the pooling,
/// and a learner reads both the median elevation and the steep roots.
///
/// The elevation's null. Every plane holds its view's ray to the root, so
/// planes from lines that carry no direction still share a direction: the
/// rays' mean, which from the views that see a root's side is near the
/// envelope's normal. Maps without direction therefore read steep fur
/// (68-72 degrees on the benchmark's cameras, measured with random maps),
/// whatever the coat does. [`Self::with_null`] also keeps each root's null
/// tensor (12 more rays per view and root, so only on request): per
/// view the same weight times the plane normals' mean outer product over
/// [`NULL_ANGLES`] image angles evenly spread over half a turn (a quadrature
/// of a uniform angle), pooled like the views' own; its least eigenvector's
/// elevation is [`ViewElevation::null_elevation`]. A reading well below its
/// null is the views' own; one near it may be the layout (a learner may
/// weigh it so: learn::stage, `view_elevation_null_margin_deg`).
pub struct PlaneTensors<'p> {
    positions: &'p [Vec3],
    /// Per root: the envelope normal and the views' tensor.
    own: Vec<(Vec3, Mat3)>,
    /// Per root, the null tensor ([`Self::with_null`]).
    nulls: Option<Vec<Mat3>>,
    index: PointIndex,
}

/// Image angles per view in the null tensor ([`PlaneTensors`]): 12, every 15 degrees.
pub const NULL_ANGLES: usize = 12;

impl<'p> PlaneTensors<'p> {
    /// The tensors of the roots at `positions`, seen on the envelope `outer`.
    pub fn new(
        positions: &'p [Vec3],
        outer: &Mesh,
        views: &[ViewOrientation<'_>],
    ) -> Result<Self, GeomError> {
        Self::made(positions, outer, views, false)
    }

    /// As [`Self::new`], with each root's null tensor too, so that every
    /// reading carries [`ViewElevation::null_elevation`].
    pub fn with_null(
        positions: &'p [Vec3],
        outer: &Mesh,
        views: &[ViewOrientation<'_>],
    ) -> Result<Self, GeomError> {
        Self::made(positions, outer, views, true)
    }

    fn made(
        positions: &'p [Vec3],
        outer: &Mesh,
        views: &[ViewOrientation<'_>],
        with_null: bool,
    ) -> Result<Self, GeomError> {
        let query = MeshQuery::new(outer)?;
        let (lo, hi) = outer.bounds();
        let lift = 1e-3 * (hi - lo).length();
        let tensors: Vec<(Vec3, Mat3, Option<Mat3>)> = positions
            .par_iter()
            .map(|&p| plane_tensor(p, &query, outer, views, lift, with_null))
            .collect();
        let nulls = with_null.then(|| tensors.iter().map(|t| t.2.unwrap_or(Mat3::ZERO)).collect());
        let own = tensors.into_iter().map(|(n, m, _)| (n, m)).collect();
        let index = PointIndex::new(positions)?;
        Ok(PlaneTensors {
            positions,
            own,
            nulls,
            index,
        })
    }

    /// [`view_elevations`] pooled within `radius`, at every `stride`-th root.
    pub fn elevations(&self, radius: f32, stride: usize) -> Vec<ViewElevation> {
        let sampled: Vec<usize> = (0..self.positions.len()).step_by(stride.max(1)).collect();
        sampled
            .into_par_iter()
            .filter_map(|i| {
                let (mut m, mut null) = (Mat3::ZERO, Mat3::ZERO);
                // Ascending indices: a fixed summation order.
                for j in self.index.indices_within(self.positions[i], radius) {
                    m += self.own[j as usize].1;
                    if let Some(nulls) = &self.nulls {
                        null += nulls[j as usize];
                    }
                }
                if !(m.x_axis.x + m.y_axis.y + m.z_axis.z > 0.0) {
                    return None;
                }
                let d = least_eigenvector(m);
                let [_, middle, largest] = symmetric_eigenvalues(m);
                let normal = self.own[i].0;
                let outward = if d.dot(normal) < 0.0 { -d } else { d };
                Some(ViewElevation {
                    root: i,
                    line: outward,
                    elevation: d.dot(normal).abs().clamp(0.0, 1.0).asin(),
                    spread: if largest > 0.0 {
                        (middle / largest).clamp(0.0, 1.0) as f32
                    } else {
                        0.0
                    },
                    null_elevation: self.nulls.as_ref().map(|_| {
                        least_eigenvector(null)
                            .dot(normal)
                            .abs()
                            .clamp(0.0, 1.0)
                            .asin()
                    }),
                })
            })
            .collect()
    }

    /// [`steep_roots`] of these tensors.
    pub fn steep_roots(&self, radius: f32, max_elevation: f32) -> Vec<bool> {
        let mut steep = vec![false; self.positions.len()];
        for e in self.elevations(radius, 1) {
            steep[e.root] = e.spread >= MIN_PLANE_SPREAD && e.elevation > max_elevation;
        }
        steep
    }
}

/// The eigenvalues of a symmetric 3x3 matrix, ascending (the trigonometric
/// closed form, in f64).
fn symmetric_eigenvalues(m: Mat3) -> [f64; 3] {
    let a = m.as_dmat3();
    let (a11, a22, a33) = (a.x_axis.x, a.y_axis.y, a.z_axis.z);
    let (a12, a13, a23) = (a.y_axis.x, a.z_axis.x, a.z_axis.y);
    let off = a12 * a12 + a13 * a13 + a23 * a23;
    let q = (a11 + a22 + a33) / 3.0;
    let p2 = (a11 - q).powi(2) + (a22 - q).powi(2) + (a33 - q).powi(2) + 2.0 * off;
    if !(p2 > 1e-30 * q * q) {
        return [q; 3];
    }
    let p = (p2 / 6.0).sqrt();
    let b = (a - glam::DMat3::from_diagonal(glam::DVec3::splat(q))) * (1.0 / p);
    let phi = (0.5 * b.determinant()).clamp(-1.0, 1.0).acos() / 3.0;
    let largest = q + 2.0 * p * phi.cos();
    let least = q + 2.0 * p * (phi + 2.0 * std::f64::consts::PI / 3.0).cos();
    [least, 3.0 * q - largest - least, largest]
}

/// The point of the envelope `outer` nearest to `p` and the unit normal of its face (`None` for
/// a degenerate face): where the views see a root's fur, and which way it faces.
fn envelope_point(p: Vec3, query: &MeshQuery, outer: &Mesh) -> (Vec3, Option<Vec3>) {
    let (q, _, tri) = query.closest_point(p);
    let normal = outer.triangles.get(tri as usize).and_then(|t| {
        let [a, b, c] = t.map(|k| outer.positions[k as usize]);
        (b - a).cross(c - a).try_normalize()
    });
    (q, normal)
}

/// One root's envelope normal, the sum over the views that see its
/// envelope point of `w n n^T`, `n` the normal of the plane through the camera
/// centre and the pixel's Gabor line ([`view_elevations`]), and the null
/// tensor where asked: the same weights on the mean `n n^T` over
/// [`NULL_ANGLES`] image angles ([`PlaneTensors`]).
fn plane_tensor(
    p: Vec3,
    query: &MeshQuery,
    outer: &Mesh,
    views: &[ViewOrientation<'_>],
    lift: f32,
    with_null: bool,
) -> (Vec3, Mat3, Option<Mat3>) {
    let (q, nq) = envelope_point(p, query, outer);
    let nq = nq.unwrap_or(Vec3::Z);
    let (mut m, mut null) = (Mat3::ZERO, Mat3::ZERO);
    let outer_product = |n: Vec3| Mat3::from_cols(n * n.x, n * n.y, n * n.z);
    for v in views {
        let cam = v.camera;
        let to_cam = cam.center() - q;
        let dist = to_cam.length();
        if !(dist > 0.0) {
            continue;
        }
        let facing = nq.dot(to_cam / dist);
        if facing < 0.2 {
            continue;
        }
        let (px, depth) = cam.project(q);
        if !(depth > 0.0) || px.x < 0.0 || px.y < 0.0 {
            continue;
        }
        let (x, y) = (px.x as u32, px.y as u32);
        if x >= cam.width || y >= cam.height {
            continue;
        }
        let k = (y * cam.width + x) as usize;
        let (Some(&alpha), Some(&c)) = (v.angle.data.get(k), v.confidence.data.get(k)) else {
            continue;
        };
        if !(c > 0.0) || !alpha.is_finite() {
            continue;
        }
        if query
            .ray_hit(q + nq * lift, to_cam / dist, dist - lift)
            .is_some()
        {
            continue;
        }
        let (_, r1) = cam.ray(px.x, px.y);
        let plane_normal = |alpha: f32| {
            let u = Vec2::new(alpha.cos(), alpha.sin());
            let (_, r2) = cam.ray(px.x + u.x, px.y + u.y);
            r1.cross(r2).try_normalize()
        };
        let Some(pn) = plane_normal(alpha) else {
            continue;
        };
        m += outer_product(pn) * (c * facing);
        if !with_null {
            continue;
        }
        let w = c * facing / NULL_ANGLES as f32;
        for a in 0..NULL_ANGLES {
            let alpha = a as f32 * std::f32::consts::PI / NULL_ANGLES as f32;
            if let Some(n) = plane_normal(alpha) {
                null += outer_product(n) * w;
            }
        }
    }
    (nq, m, with_null.then_some(null))
}

/// The unit eigenvector of a symmetric 3x3 matrix with the least eigenvalue
/// (power iteration on `trace I - m`, whose largest eigenvalue is `m`'s
/// least).
fn least_eigenvector(m: Mat3) -> Vec3 {
    let shift = Mat3::from_diagonal(Vec3::splat(m.x_axis.x + m.y_axis.y + m.z_axis.z)) - m;
    let mut v = Vec3::new(0.3, 0.5, 0.8).normalize();
    for _ in 0..100 {
        v = (shift * v).try_normalize().unwrap_or(Vec3::Z);
    }
    v
}

/// Flips every frame whose tangent points against the sum of its
/// neighbours' tangents within `radius` (itself excluded), all decided from
/// the frames as given (one Jacobi pass, so the order of the roots does not
/// matter); returns how many were flipped. A flip turns the frame half a turn
/// about its normal. Why: the views give an axis, not a sign, and a root
/// whose pooled axis lies more than 90 degrees from its start keeps the
/// wrong side; its neighbours outvote it.
pub fn vote_signs(
    positions: &[Vec3],
    frames: &mut [Mat3],
    radius: f32,
    parts: Option<&[u16]>,
) -> Result<usize, GeomError> {
    if radius <= 0.0 || positions.is_empty() {
        return Ok(0);
    }
    let index = PointIndex::new(positions)?;
    let flip: Vec<bool> = positions
        .par_iter()
        .enumerate()
        .map(|(i, &p)| {
            let sum: Vec3 = index
                .indices_within(p, radius)
                .into_iter()
                .filter(|&j| j as usize != i && same_part(parts, i, j as usize))
                .map(|j| frames[j as usize].x_axis)
                .sum();
            sum.dot(frames[i].x_axis) < 0.0
        })
        .collect();
    let half = Mat3::from_rotation_z(std::f32::consts::PI);
    let mut flipped = 0;
    for (f, &fl) in frames.iter_mut().zip(&flip) {
        if fl {
            *f *= half;
            flipped += 1;
        }
    }
    Ok(flipped)
}

/// Whether roots `i` and `j` pool together: always without labels, else on
/// one part (a small part such as an ear, whose fur runs across its
/// neighbour's, then reads its own lines only).
fn same_part(parts: Option<&[u16]>, i: usize, j: usize) -> bool {
    parts.is_none_or(|p| p.get(i) == p.get(j))
}

/// One root's structure tensor over the views (`[xx, xy, xz, yy, yz, zz]`),
/// its expectation under uniformly random map angles (same layout), and the
/// number of views that saw it.
fn root_tensor(
    p: Vec3,
    frame: &Mat3,
    query: &MeshQuery,
    outer: &Mesh,
    views: &[ViewOrientation<'_>],
    lift: f32,
) -> ([f32; 6], [f32; 6], u32) {
    let mut s = [0.0f32; 6];
    let mut null = [0.0f32; 6];
    let mut seen = 0u32;
    let (t, b) = (frame.x_axis, frame.y_axis);
    let (q, normal) = envelope_point(p, query, outer);
    let normal = normal.unwrap_or(frame.z_axis);
    for v in views {
        let cam = v.camera;
        let to_cam = cam.center() - q;
        let dist = to_cam.length();
        let Some(dir) = to_cam.try_normalize() else {
            continue;
        };
        let facing = normal.dot(dir);
        if facing <= 0.0 {
            continue;
        }
        let (px, depth) = cam.project(q);
        if !(depth > 0.0) {
            continue;
        }
        let (x, y) = (px.x.floor(), px.y.floor());
        if x < 0.0 || y < 0.0 || x >= cam.width as f32 || y >= cam.height as f32 {
            continue;
        }
        let k = (y as u32 * cam.width + x as u32) as usize;
        let (Some(&alpha), Some(&conf)) = (v.angle.data.get(k), v.confidence.data.get(k)) else {
            continue;
        };
        if !(conf > 0.0) || !alpha.is_finite() {
            continue;
        }
        let origin = q + normal * lift;
        if query.ray_hit(origin, dir, dist - lift).is_some() {
            continue;
        }
        // Projection Jacobian along T and B (central differences, a step far
        // below a pixel footprint).
        let h = 1e-4 * depth;
        let jt = (cam.project(q + t * h).0 - cam.project(q - t * h).0) / (2.0 * h);
        let jb = (cam.project(q + b * h).0 - cam.project(q - b * h).0) / (2.0 * h);
        let det = jt.x * jb.y - jb.x * jt.y;
        if !(det.abs() > 0.0) {
            continue;
        }
        let u = Vec2::new(alpha.cos(), alpha.sin());
        // d = J^-1 u in (T, B) coordinates.
        let d = Vec2::new(jb.y * u.x - jb.x * u.y, -jt.y * u.x + jt.x * u.y) / det;
        let Some(d3) = (t * d.x + b * d.y).try_normalize() else {
            continue;
        };
        let w = conf * facing * facing;
        s[0] += w * d3.x * d3.x;
        s[1] += w * d3.x * d3.y;
        s[2] += w * d3.x * d3.z;
        s[3] += w * d3.y * d3.y;
        s[4] += w * d3.y * d3.z;
        s[5] += w * d3.z * d3.z;
        // The null: with M = J^-1 (its adjugate: the scale cancels) and
        // P = M M^T, a uniform image angle lifts to lines whose mean outer
        // product is sqrt(P) / tr sqrt(P) = (P + sqrt(det P) I) / (tr P + 2
        // sqrt(det P)), in (T, B) coordinates.
        let (m0, m1) = (Vec2::new(jb.y, -jb.x), Vec2::new(-jt.y, jt.x));
        let (p00, p01, p11) = (m0.dot(m0), m0.dot(m1), m1.dot(m1));
        let root_det = (p00 * p11 - p01 * p01).max(0.0).sqrt();
        let norm = p00 + p11 + 2.0 * root_det;
        if norm > 0.0 {
            let (n00, n01, n11) = ((p00 + root_det) / norm, p01 / norm, (p11 + root_det) / norm);
            add_outer(&mut null, w * n00, t, t);
            add_outer(&mut null, w * n11, b, b);
            add_outer(&mut null, w * n01, t, b);
            add_outer(&mut null, w * n01, b, t);
        }
        seen += 1;
    }
    (s, null, seen)
}

/// Adds `w (u v^T + v u^T) / 2` to a symmetric 3x3 tensor `[xx, xy, xz, yy, yz, zz]`.
fn add_outer(s: &mut [f32; 6], w: f32, u: Vec3, v: Vec3) {
    s[0] += w * u.x * v.x;
    s[1] += w * 0.5 * (u.x * v.y + u.y * v.x);
    s[2] += w * 0.5 * (u.x * v.z + u.z * v.x);
    s[3] += w * u.y * v.y;
    s[4] += w * 0.5 * (u.y * v.z + u.z * v.y);
    s[5] += w * u.z * v.z;
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Mat4;

    /// A flat square in the z = 0 plane (normal +z), two triangles.
    fn plane(half: f32) -> Mesh {
        Mesh {
            positions: vec![
                Vec3::new(-half, -half, 0.0),
                Vec3::new(half, -half, 0.0),
                Vec3::new(half, half, 0.0),
                Vec3::new(-half, half, 0.0),
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            ..Default::default()
        }
    }

    fn camera_at(eye: Vec3) -> Camera {
        let c2w = Mat4::look_at_rh(eye, Vec3::ZERO, Vec3::Y).inverse();
        Camera {
            file_path: "v.png".into(),
            c2w,
            fx: 100.0,
            fy: 100.0,
            cx: 32.0,
            cy: 32.0,
            width: 64,
            height: 64,
        }
    }

    /// Three cameras above the plane, each seeing it obliquely from another side.
    fn oblique_cameras() -> [Camera; 3] {
        [
            camera_at(Vec3::new(3.0, 1.0, 4.0)),
            camera_at(Vec3::new(-2.0, 2.5, 3.0)),
            camera_at(Vec3::new(0.5, -3.0, 2.0)),
        ]
    }

    /// Maps whose every angle is drawn uniformly (seeded), at full confidence: no direction.
    fn random_maps(cams: &[Camera], seed: u64) -> Vec<(ImageF32, ImageF32)> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        cams.iter()
            .map(|c| {
                let (mut a, conf) = maps_of(c, Vec3::X);
                for v in a.data.iter_mut() {
                    *v = rng.gen_range(0.0..std::f32::consts::PI);
                }
                (a, conf)
            })
            .collect()
    }

    /// The maps a line field along `axis` on the plane gives in `cam`.
    fn maps_of(cam: &Camera, axis: Vec3) -> (ImageF32, ImageF32) {
        maps_of_field(cam, |_| axis)
    }

    /// The maps of a line field `axis(p)` on the plane.
    fn maps_of_field(cam: &Camera, axis: impl Fn(Vec3) -> Vec3) -> (ImageF32, ImageF32) {
        let mut angle = ImageF32::new(cam.width, cam.height, 1);
        let mut conf = ImageF32::new(cam.width, cam.height, 1);
        for y in 0..cam.height {
            for x in 0..cam.width {
                let (o, d) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
                if d.z.abs() < 1e-6 {
                    continue;
                }
                let p = o + d * (-o.z / d.z);
                let a = cam.project(p).0;
                let b = cam.project(p + axis(p) * 1e-3).0;
                let k = (y * cam.width + x) as usize;
                angle.data[k] = crate::render::orientation_angle(b.x - a.x, b.y - a.y);
                conf.data[k] = 1.0;
            }
        }
        (angle, conf)
    }

    #[test]
    fn oblique_views_recover_the_line_on_the_surface() {
        let mesh = plane(2.0);
        let truth = Vec3::new(1.0, 0.5, 0.0).normalize();
        let cams = oblique_cameras();
        let maps: Vec<_> = cams.iter().map(|c| maps_of(c, truth)).collect();
        let views = ViewOrientation::pair(&cams, &maps);
        // Roots just under the surface (the fur's envelope), frames turned
        // 60 degrees off the truth, one of them with T against it.
        let positions = vec![Vec3::new(0.1, 0.2, -0.05), Vec3::new(-0.3, 0.1, -0.05)];
        let turn = Mat3::from_rotation_z(60f32.to_radians());
        let base = Mat3::from_cols(truth, Vec3::Z.cross(truth), Vec3::Z);
        let flipped = Mat3::from_cols(-truth, Vec3::Z.cross(-truth), Vec3::Z);
        let frames = vec![base * turn, flipped * turn];
        let axes = view_axes(&positions, &frames, &mesh, &views, 0.0, None).unwrap();
        for (a, f) in axes.iter().zip(&frames) {
            assert_eq!(a.views, 3);
            assert!(a.coherence > 0.999, "{a:?}");
            // Turning T by `turn` lands on the true line, keeping T's side.
            let t = *f * Vec3::new(a.turn.cos(), a.turn.sin(), 0.0);
            assert!(t.dot(truth).abs() > 0.9999, "{a:?} {t}");
            assert!((a.turn + 60f32.to_radians()).abs() < 1e-3, "{a:?}");
        }
    }

    #[test]
    fn random_maps_agree_only_as_much_as_the_geometry_makes_them() {
        // Grazing views of one side of the plane: their Jacobians all
        // compress the same tangent axis, so lines lifted from random image
        // angles lean toward it and agree with each other.
        let mesh = plane(2.0);
        let cams = [
            camera_at(Vec3::new(4.0, 0.3, 1.2)),
            camera_at(Vec3::new(4.0, -0.4, 1.0)),
            camera_at(Vec3::new(3.5, 0.1, 1.5)),
        ];
        let random = random_maps(&cams, 5);
        let truth = Vec3::new(1.0, 1.0, 0.0).normalize();
        let true_maps: Vec<_> = cams.iter().map(|c| maps_of(c, truth)).collect();
        let positions: Vec<Vec3> = (0..400)
            .map(|i| {
                Vec3::new(
                    (i % 20) as f32 * 0.02 - 0.2,
                    (i / 20) as f32 * 0.02 - 0.2,
                    -0.01,
                )
            })
            .collect();
        let frames = vec![Mat3::IDENTITY; positions.len()];
        let mean = |maps: &[(ImageF32, ImageF32)]| {
            let views = ViewOrientation::pair(&cams, maps);
            let axes = view_axes(&positions, &frames, &mesh, &views, 0.15, None).unwrap();
            let n = axes.len() as f32;
            (
                axes.iter().map(|a| a.coherence).sum::<f32>() / n,
                axes.iter().map(|a| a.excess_coherence).sum::<f32>() / n,
            )
        };
        let (coherence, excess) = mean(&random);
        assert!(coherence > 0.3, "random maps, coherence {coherence}");
        // (measured: 0.48 and 0.10, the latter the sampling noise of a few
        // hundred pixels)
        assert!(excess < 0.15, "random maps, excess coherence {excess}");
        // A true line field keeps most of its agreement.
        let (coherence, excess) = mean(&true_maps);
        assert!(coherence > 0.999 && excess > 0.5, "{coherence} {excess}");
    }

    #[test]
    fn the_views_give_the_elevation_of_a_rising_line_field() {
        // Lines rising 30 degrees off the plane toward +x: every view sees
        // their projection, and the planes through the cameras meet in them.
        let mesh = plane(2.0);
        let rise = 30f32.to_radians();
        let dir = Vec3::new(rise.cos(), 0.0, rise.sin());
        let cams = oblique_cameras();
        let maps: Vec<_> = cams.iter().map(|c| maps_of(c, dir)).collect();
        let views = ViewOrientation::pair(&cams, &maps);
        let positions: Vec<Vec3> = (0..25)
            .map(|i| Vec3::new((i % 5) as f32 * 0.05, (i / 5) as f32 * 0.05, -0.01))
            .collect();
        let e = view_elevations(&positions, &mesh, &views, 0.1, 4).unwrap();
        assert_eq!(e.len(), 7, "every 4th of 25 roots");
        for r in e {
            assert!(
                (r.elevation - rise).abs() < 0.02,
                "root {}: {} degrees",
                r.root,
                r.elevation.to_degrees()
            );
            assert!(r.spread > 0.05, "{r:?}");
        }
        // One view alone leaves the direction in a plane: still a finite
        // answer, but the spread says that the planes do not pin it down.
        let one = view_elevations(&positions, &mesh, &views[..1], 0.1, 25).unwrap();
        assert!(
            one.iter()
                .all(|r| r.elevation.is_finite() && r.spread < 1e-3),
            "{one:?}"
        );
    }

    #[test]
    fn maps_without_direction_read_the_null_and_lines_on_the_surface_read_below_it() {
        // Views from all around and above a flat coat, as a capture's: random image
        // angles read the cameras' mean ray (steep), and the null says so; lines lying
        // on the surface read flat, far below the same null.
        let mesh = plane(2.0);
        let cams: Vec<Camera> = (0..8)
            .map(|k| {
                let a = k as f32 * std::f32::consts::TAU / 8.0;
                camera_at(Vec3::new(3.0 * a.cos(), 3.0 * a.sin(), 2.5))
            })
            .collect();
        let positions: Vec<Vec3> = (0..25)
            .map(|i| Vec3::new((i % 5) as f32 * 0.05, (i / 5) as f32 * 0.05, -0.01))
            .collect();
        let median = |mut v: Vec<f32>| {
            v.sort_by(f32::total_cmp);
            v[v.len() / 2].to_degrees()
        };
        let random = random_maps(&cams, 3);
        let flat: Vec<_> = cams.iter().map(|c| maps_of(c, Vec3::X)).collect();
        let read = |maps: &[(ImageF32, ImageF32)]| {
            let e = PlaneTensors::with_null(&positions, &mesh, &ViewOrientation::pair(&cams, maps))
                .unwrap()
                .elevations(0.2, 1);
            (
                median(e.iter().map(|r| r.elevation).collect()),
                median(e.iter().filter_map(|r| r.null_elevation).collect()),
            )
        };
        let (noise, noise_null) = read(&random);
        let (lines, lines_null) = read(&flat);
        // The null depends on the cameras and the confidence only, not on the angles; with
        // the cameras spread evenly around the normal, the rays' mean is the normal itself.
        assert!(
            (noise_null - lines_null).abs() < 1e-3,
            "{noise_null} {lines_null}"
        );
        assert!(noise_null > 85.0, "null {noise_null} degrees");
        // Random maps read steep, nearer their null than the flat truth (200 planes leave
        // sampling noise: 67 degrees when written), and lines on the surface read flat.
        assert!(noise > 55.0, "random maps {noise} degrees");
        assert!(
            noise_null - noise < noise - lines,
            "random {noise}, null {noise_null}"
        );
        assert!(lines < 2.0, "lines on the surface read {lines} degrees");
    }

    #[test]
    fn fur_along_the_normal_reads_steep_and_fur_along_the_plane_does_not() {
        let mesh = plane(2.0);
        let cams = oblique_cameras();
        let positions: Vec<Vec3> = (0..25)
            .map(|i| Vec3::new((i % 5) as f32 * 0.05, (i / 5) as f32 * 0.05, -0.01))
            .collect();
        let steep_at = |rise_deg: f32, views: usize| {
            let rise = rise_deg.to_radians();
            let dir = Vec3::new(rise.cos(), 0.0, rise.sin());
            let maps: Vec<_> = cams[..views].iter().map(|c| maps_of(c, dir)).collect();
            let v = ViewOrientation::pair(&cams[..views], &maps);
            let s = steep_roots(&positions, &mesh, &v, 0.1, 60f32.to_radians()).unwrap();
            s.iter().filter(|&&b| b).count()
        };
        assert_eq!(steep_at(75.0, 3), 25, "fur 15 degrees off the normal");
        assert_eq!(steep_at(45.0, 3), 0, "fur at 45 degrees");
        assert_eq!(steep_at(10.0, 3), 0, "fur lying down");
        // One view cannot tell: its plane holds the lying and the standing
        // line alike.
        assert_eq!(steep_at(75.0, 1), 0, "one view");
    }

    #[test]
    fn symmetric_eigenvalues_match_a_rotated_diagonal() {
        let r = Mat3::from_axis_angle(Vec3::new(1.0, 2.0, 3.0).normalize(), 0.7);
        let m = r * Mat3::from_diagonal(Vec3::new(3.0, 0.5, 2.0)) * r.transpose();
        let e = symmetric_eigenvalues(m);
        for (got, want) in e.iter().zip([0.5, 2.0, 3.0]) {
            assert!((got - want).abs() < 1e-5, "{e:?}");
        }
        assert_eq!(symmetric_eigenvalues(Mat3::IDENTITY), [1.0; 3]);
        // Two unit plane normals 60 degrees apart: spread tan^2(30 degrees).
        let (a, b) = (Vec3::X, Vec3::new(0.5, 0.75f32.sqrt(), 0.0));
        let outer = |n: Vec3| Mat3::from_cols(n * n.x, n * n.y, n * n.z);
        let [least, middle, largest] = symmetric_eigenvalues(outer(a) + outer(b));
        assert!(least.abs() < 1e-6 && (middle / largest - 1.0 / 3.0).abs() < 1e-5);
    }

    #[test]
    fn a_frame_against_its_neighbours_is_flipped() {
        let positions: Vec<Vec3> = (0..5)
            .map(|i| Vec3::new(i as f32 * 0.1, 0.0, 0.0))
            .collect();
        let mut frames = vec![Mat3::IDENTITY; 5];
        let half = Mat3::from_rotation_z(std::f32::consts::PI);
        frames[2] = half;
        assert_eq!(vote_signs(&positions, &mut frames, 0.25, None).unwrap(), 1);
        assert!(frames.iter().all(|f| f.x_axis.dot(Vec3::X) > 0.999));
        // Two halves that agree within themselves stay as they are.
        let mut split = vec![Mat3::IDENTITY, Mat3::IDENTITY, half, half];
        let pos = [0.0, 0.1, 1.0, 1.1].map(|x| Vec3::new(x, 0.0, 0.0));
        assert_eq!(vote_signs(&pos, &mut split, 0.25, None).unwrap(), 0);
        // Two roots of another part among them (an ear on a head) are not outvoted by their
        // neighbours when the vote keeps to each part; without that both flip, and the ear's
        // two outvote the head roots on either side as well.
        let parts = [0u16, 0, 1, 1, 0];
        let mut frames = vec![Mat3::IDENTITY; 5];
        frames[2] = half;
        frames[3] = half;
        let mut kept = frames.clone();
        assert_eq!(
            vote_signs(&positions, &mut kept, 0.25, Some(&parts)).unwrap(),
            0
        );
        assert_eq!(vote_signs(&positions, &mut frames, 0.25, None).unwrap(), 4);
    }

    #[test]
    fn pooling_within_a_part_reads_the_parts_own_lines() {
        // Two parts side by side whose fur runs across each other's: along x where x < 0
        // (part 0, three roots), along y where x > 0 (part 1, two roots). Pooled over a radius
        // that spans both, part 1 reads a blend of the two; within its part, its own y.
        let mesh = plane(2.0);
        let field = |p: Vec3| if p.x < 0.0 { Vec3::X } else { Vec3::Y };
        let cams = oblique_cameras();
        let maps: Vec<_> = cams.iter().map(|c| maps_of_field(c, field)).collect();
        let views = ViewOrientation::pair(&cams, &maps);
        let positions: Vec<Vec3> = [-0.5, -0.4, -0.3, 0.3, 0.4]
            .map(|x| Vec3::new(x, 0.0, -0.05))
            .to_vec();
        let parts = [0u16, 0, 0, 1, 1];
        let frames = vec![Mat3::IDENTITY; 5];
        let along_y = |axes: &[ViewAxis], i: usize| {
            let t = frames[i] * Vec3::new(axes[i].turn.cos(), axes[i].turn.sin(), 0.0);
            t.dot(Vec3::Y).abs()
        };
        let across = view_axes(&positions, &frames, &mesh, &views, 1.0, None).unwrap();
        let within = view_axes(&positions, &frames, &mesh, &views, 1.0, Some(&parts)).unwrap();
        for i in [3, 4] {
            assert!(along_y(&within, i) > 0.999, "{:?}", within[i]);
            assert!(within[i].coherence > 0.99, "{:?}", within[i]);
            // Across parts the three x roots outweigh the two y ones.
            assert!(along_y(&across, i) < 0.5, "{:?}", across[i]);
            assert!(across[i].coherence < 0.5, "{:?}", across[i]);
        }
        for i in [0, 1, 2] {
            assert!(along_y(&within, i) < 1e-3, "{:?}", within[i]);
        }
    }

    #[test]
    fn a_small_part_fills_little_of_its_window() {
        // A row of 15 roots of part 0 (x = 0 .. 1.4) with two roots of part 1 (an ear) at
        // x = 0.65 and 0.75 among them. At radius 0.52 the ear's roots see 10 of part 0's and
        // their own two; part 0's far end sees only its own.
        let mut positions: Vec<Vec3> = (0..15)
            .map(|i| Vec3::new(i as f32 * 0.1, 0.0, 0.0))
            .collect();
        positions.push(Vec3::new(0.65, 0.0, 0.0));
        positions.push(Vec3::new(0.75, 0.0, 0.0));
        let mut labels = vec![0u16; 15];
        labels.extend([1u16, 1]);
        let shares = own_part_shares(&positions, &labels, 0.52).unwrap();
        assert!((shares[15] - 2.0 / 12.0).abs() < 1e-6, "{}", shares[15]);
        assert!((shares[16] - 2.0 / 12.0).abs() < 1e-6, "{}", shares[16]);
        assert_eq!(shares[0], 1.0);
        // Part 0's roots beside the ear: 11 of their 13 neighbours are their own.
        assert!((shares[7] - 11.0 / 13.0).abs() < 1e-6, "{}", shares[7]);
        // No window: every root fills its own.
        let alone = own_part_shares(&positions, &labels, 0.0).unwrap();
        assert!(alone.iter().all(|&s| s == 1.0));
    }

    #[test]
    fn a_root_turns_by_the_share_of_its_window_that_is_not_steep() {
        // Ten roots in a row (x = 0 .. 0.9), the last five steep. At radius 0.25 each sees
        // up to two neighbours on either side.
        let positions: Vec<Vec3> = (0..10)
            .map(|i| Vec3::new(i as f32 * 0.1, 0.0, 0.0))
            .collect();
        let steep: Vec<bool> = (0..10).map(|i| i >= 5).collect();
        let shares = steep_shares(&positions, &steep, 0.25).unwrap();
        assert_eq!(shares[0], 0.0);
        assert_eq!(shares[9], 1.0);
        // Across the step the share rises 1/5, 2/5, 3/5 at roots 3, 4, 5.
        for (i, want) in [(3, 0.2), (4, 0.4), (5, 0.6), (6, 0.8)] {
            assert!((shares[i] - want).abs() < 1e-6, "root {i}: {}", shares[i]);
        }
        // No window: each root's own mark.
        let alone = steep_shares(&positions, &steep, 0.0).unwrap();
        assert_eq!(
            alone,
            steep.iter().map(|&s| s as u8 as f32).collect::<Vec<_>>()
        );
    }

    #[test]
    fn occluded_and_back_facing_views_are_skipped() {
        let mesh = plane(2.0);
        let truth = Vec3::X;
        // Below the plane: sees its back face.
        let below = camera_at(Vec3::new(0.5, 0.5, -4.0));
        let (a, c) = maps_of(&below, truth);
        let views = [ViewOrientation {
            camera: &below,
            angle: &a,
            confidence: &c,
        }];
        let frames = vec![Mat3::IDENTITY];
        let axes = view_axes(
            &[Vec3::new(0.0, 0.0, -0.05)],
            &frames,
            &mesh,
            &views,
            0.0,
            None,
        )
        .unwrap();
        assert_eq!(axes[0].views, 0);
        assert_eq!(axes[0].coherence, 0.0);
        assert_eq!(axes[0].turn, 0.0);
    }
}
