//! Gaussian sets, their gradients, and the strand-to-Gaussian mapping with
//! its adjoint. See the module doc of [`crate::render`] for the conventions.

use glam::{Quat, Vec3};

use super::{RenderError, SH_C0};

/// Thin standard deviation of a strand Gaussian per unit of strand width:
/// `sigma_thin = 0.5 * width` (the width reads as a diameter, about 2 sigma).
pub const THIN_SIGMA_PER_WIDTH: f32 = 0.5;
/// Opacity of strand Gaussians (fixed, as in Gaussian Haircut / NeuralFur).
pub const STRAND_OPACITY: f32 = 1.0;
/// Segments shorter than this (world units) have no defined direction: their
/// direction gradient is dropped and their rotation is the identity.
pub const MIN_SEGMENT: f32 = 1e-12;

/// A set of anisotropic 3D Gaussians (structure of arrays, one entry per
/// Gaussian in every vector).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Gaussians {
    pub means: Vec<Vec3>,
    /// Standard deviations along the local x, y, z axes (world units).
    pub scales: Vec<Vec3>,
    /// Local-to-world rotations (normalised internally).
    pub rotations: Vec<Quat>,
    /// In [0, 1].
    pub opacities: Vec<f32>,
    /// SH coefficients per colour channel: `sh[i][0]` is band 0, `[1..4]` band 1
    /// (only used when `sh_degree = 1`).
    pub sh: Vec<[Vec3; 4]>,
    /// Fur flag (renders into the fur channel).
    pub fur: Vec<bool>,
}

impl Gaussians {
    pub fn len(&self) -> usize {
        self.means.len()
    }
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }
    /// Appends one Gaussian with a degree-0 colour `rgb`.
    pub fn push(
        &mut self,
        mean: Vec3,
        scale: Vec3,
        rotation: Quat,
        opacity: f32,
        rgb: Vec3,
        fur: bool,
    ) {
        self.means.push(mean);
        self.scales.push(scale);
        self.rotations.push(rotation);
        self.opacities.push(opacity);
        self.sh
            .push([rgb_to_sh0(rgb), Vec3::ZERO, Vec3::ZERO, Vec3::ZERO]);
        self.fur.push(fur);
    }

    /// Checks lengths and finiteness.
    pub fn validate(&self) -> Result<(), RenderError> {
        let n = self.means.len();
        let check = |what: &'static str, found: usize| {
            if found != n {
                Err(RenderError::Length {
                    what,
                    expected: n,
                    found,
                })
            } else {
                Ok(())
            }
        };
        check("gaussians.scales", self.scales.len())?;
        check("gaussians.rotations", self.rotations.len())?;
        check("gaussians.opacities", self.opacities.len())?;
        check("gaussians.sh", self.sh.len())?;
        check("gaussians.fur", self.fur.len())?;
        let nf = |what, index| Err(RenderError::NonFinite { what, index });
        for i in 0..n {
            if !self.means[i].is_finite() {
                return nf("gaussians.means", i);
            }
            if !self.scales[i].is_finite() {
                return nf("gaussians.scales", i);
            }
            if !self.rotations[i].is_finite() {
                return nf("gaussians.rotations", i);
            }
            if !self.opacities[i].is_finite() {
                return nf("gaussians.opacities", i);
            }
            if !self.sh[i].iter().all(|c| c.is_finite()) {
                return nf("gaussians.sh", i);
            }
        }
        Ok(())
    }
}

/// Band-0 SH coefficient that renders as `rgb` (degree 0).
pub fn rgb_to_sh0(rgb: Vec3) -> Vec3 {
    (rgb - Vec3::splat(0.5)) / SH_C0
}

/// dL/d(parameter) for every Gaussian parameter, same layout as [`Gaussians`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GaussianGrads {
    pub means: Vec<Vec3>,
    pub scales: Vec<Vec3>,
    /// Gradient w.r.t. the raw (unnormalised) quaternion components.
    pub rotations: Vec<Quat>,
    pub opacities: Vec<f32>,
    pub sh: Vec<[Vec3; 4]>,
    /// dL/dSigma3 for the world covariance `R diag(s)^2 R^T`, by its six
    /// unique entries `[xx, xy, xz, yy, yz, zz]`; an off-diagonal entry is the
    /// derivative w.r.t. the one shared value (so it is `G_ij + G_ji`).
    pub cov3d: Vec<[f32; 6]>,
    /// dL/d(projected mean) in pixels (screen-space gradient, for 3DGS-style
    /// densification statistics).
    pub means2d: Vec<glam::Vec2>,
}

impl GaussianGrads {
    pub fn zeros(n: usize) -> Self {
        GaussianGrads {
            means: vec![Vec3::ZERO; n],
            scales: vec![Vec3::ZERO; n],
            rotations: vec![Quat::from_xyzw(0.0, 0.0, 0.0, 0.0); n],
            opacities: vec![0.0; n],
            sh: vec![[Vec3::ZERO; 4]; n],
            cov3d: vec![[0.0; 6]; n],
            means2d: vec![glam::Vec2::ZERO; n],
        }
    }
    pub fn len(&self) -> usize {
        self.means.len()
    }
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }
}

/// Gradients of a strand set (see [`strands_backward`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StrandGrads {
    /// One per point.
    pub points: Vec<Vec3>,
    /// One per strand.
    pub widths: Vec<f32>,
    /// One per strand.
    pub colors: Vec<[f32; 3]>,
}

/// Number of segments (= Gaussians) of a strand set.
pub fn segment_count(starts: &[u32]) -> usize {
    starts
        .windows(2)
        .map(|w| (w[1].saturating_sub(w[0]) as usize).saturating_sub(1))
        .sum()
}

fn check_strands(
    points: &[Vec3],
    starts: &[u32],
    widths: &[f32],
    colors: Option<&[[f32; 3]]>,
) -> Result<usize, RenderError> {
    if starts.is_empty() {
        return Err(RenderError::Strands(
            "starts is empty (it must begin with 0 and end with the point count)".into(),
        ));
    }
    let n = starts.len() - 1;
    if starts[0] != 0 {
        return Err(RenderError::Strands(format!(
            "starts[0] = {}, expected 0",
            starts[0]
        )));
    }
    if starts[n] as usize != points.len() {
        return Err(RenderError::Strands(format!(
            "starts[{n}] = {}, expected the point count {}",
            starts[n],
            points.len()
        )));
    }
    if let Some(s) = starts.windows(2).position(|w| w[1] < w[0]) {
        return Err(RenderError::Strands(format!(
            "starts[{}] = {} < starts[{s}] = {} (must be non-decreasing)",
            s + 1,
            starts[s + 1],
            starts[s]
        )));
    }
    if widths.len() != n {
        return Err(RenderError::Length {
            what: "strand widths",
            expected: n,
            found: widths.len(),
        });
    }
    if let Some(c) = colors {
        if c.len() != n {
            return Err(RenderError::Length {
                what: "strand colours",
                expected: n,
                found: c.len(),
            });
        }
        if let Some(i) = c.iter().position(|c| !c.iter().all(|v| v.is_finite())) {
            return Err(RenderError::NonFinite {
                what: "strand colours",
                index: i,
            });
        }
    }
    if let Some(i) = points.iter().position(|p| !p.is_finite()) {
        return Err(RenderError::NonFinite {
            what: "strand points",
            index: i,
        });
    }
    if let Some(i) = widths.iter().position(|w| !w.is_finite()) {
        return Err(RenderError::NonFinite {
            what: "strand widths",
            index: i,
        });
    }
    Ok(n)
}

/// Rotation taking +x onto the unit vector `d`.
pub fn rotation_x_to(d: Vec3) -> Quat {
    // q = [1 + x.d, x cross d] normalised; x cross d = (0, -d.z, d.y).
    let w = 1.0 + d.x;
    let v = Vec3::new(0.0, -d.z, d.y);
    let n2 = w * w + v.length_squared();
    if n2 < 1e-12 || !n2.is_finite() {
        if d.x < 0.0 {
            // Anti-parallel: half turn about +z maps +x to -x.
            return Quat::from_xyzw(0.0, 0.0, 1.0, 0.0);
        }
        return Quat::IDENTITY;
    }
    let inv = 1.0 / n2.sqrt();
    Quat::from_xyzw(v.x * inv, v.y * inv, v.z * inv, w * inv)
}

/// One Gaussian per polyline segment, strand by strand, root to tip
/// (strand `s` owns `points[starts[s]..starts[s+1]]`; a strand with fewer than
/// two points gives none). `widths` and `colors` are per strand.
pub fn strands_to_gaussians(
    points: &[Vec3],
    starts: &[u32],
    widths: &[f32],
    colors: &[[f32; 3]],
    fur: bool,
) -> Result<Gaussians, RenderError> {
    let n = check_strands(points, starts, widths, Some(colors))?;
    let segs = segment_count(starts);
    let mut g = Gaussians {
        means: Vec::with_capacity(segs),
        scales: Vec::with_capacity(segs),
        rotations: Vec::with_capacity(segs),
        opacities: Vec::with_capacity(segs),
        sh: Vec::with_capacity(segs),
        fur: Vec::with_capacity(segs),
    };
    for s in 0..n {
        let (a, b) = (starts[s] as usize, starts[s + 1] as usize);
        let thin = THIN_SIGMA_PER_WIDTH * widths[s];
        let sh0 = rgb_to_sh0(Vec3::from(colors[s]));
        for k in a..b.saturating_sub(1).max(a) {
            let (p, q) = (points[k], points[k + 1]);
            let d = q - p;
            let len = d.length();
            let rot = if len > MIN_SEGMENT {
                rotation_x_to(d / len)
            } else {
                Quat::IDENTITY
            };
            g.means.push(0.5 * (p + q));
            g.scales.push(Vec3::new(0.5 * len, thin, thin));
            g.rotations.push(rot);
            g.opacities.push(STRAND_OPACITY);
            g.sh.push([sh0, Vec3::ZERO, Vec3::ZERO, Vec3::ZERO]);
            g.fur.push(fur);
        }
    }
    Ok(g)
}

/// The adjoint of [`strands_to_gaussians`]: gradients of the points, widths
/// and colours from the Gaussian gradients (uses `means`, `cov3d` and `sh[0]`
/// of `grads`; scale and rotation gradients are not needed because `cov3d`
/// carries the same information without the twist ambiguity).
pub fn strands_backward(
    points: &[Vec3],
    starts: &[u32],
    widths: &[f32],
    grads: &GaussianGrads,
) -> Result<StrandGrads, RenderError> {
    let n = check_strands(points, starts, widths, None)?;
    let segs = segment_count(starts);
    for (what, found) in [
        ("gaussian grads (means)", grads.means.len()),
        ("gaussian grads (cov3d)", grads.cov3d.len()),
        ("gaussian grads (sh)", grads.sh.len()),
    ] {
        if found != segs {
            return Err(RenderError::Length {
                what,
                expected: segs,
                found,
            });
        }
    }
    let mut out = StrandGrads {
        points: vec![Vec3::ZERO; points.len()],
        widths: vec![0.0; n],
        colors: vec![[0.0; 3]; n],
    };
    let mut gi = 0usize;
    for s in 0..n {
        let (a, b) = (starts[s] as usize, starts[s + 1] as usize);
        let thin = THIN_SIGMA_PER_WIDTH * widths[s];
        let mut dthin = 0.0f32;
        let mut dcol = Vec3::ZERO;
        for k in a..b.saturating_sub(1).max(a) {
            let d = points[k + 1] - points[k];
            let len = d.length();
            let c = grads.cov3d[gi];
            // Full symmetric G from the unique-entry gradient.
            let gm = glam::Mat3::from_cols(
                Vec3::new(c[0], 0.5 * c[1], 0.5 * c[2]),
                Vec3::new(0.5 * c[1], c[3], 0.5 * c[4]),
                Vec3::new(0.5 * c[2], 0.5 * c[4], c[5]),
            );
            // Sigma = d d^T / 4 + w^2 (I - dh dh^T).
            let mut dd = 0.5 * (gm * d);
            let trace = c[0] + c[3] + c[5];
            if len > MIN_SEGMENT {
                let dh = d / len;
                let gdh = gm * dh;
                // d(dh) = (I - dh dh^T) d(d) / len.
                let proj = gdh - dh * dh.dot(gdh);
                dd -= (2.0 * thin * thin / len) * proj;
                dthin += 2.0 * thin * (trace - dh.dot(gdh));
            } else {
                // Direction undefined: the forward used the identity rotation
                // (Sigma = w^2 (I - x x^T)); no direction gradient.
                dthin += 2.0 * thin * (trace - c[0]);
            }
            let dm = 0.5 * grads.means[gi];
            out.points[k] += dm - dd;
            out.points[k + 1] += dm + dd;
            dcol += grads.sh[gi][0] / SH_C0;
            gi += 1;
        }
        out.widths[s] = dthin * THIN_SIGMA_PER_WIDTH;
        out.colors[s] = dcol.to_array();
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_maps_x_onto_direction_including_antiparallel() {
        for d in [
            Vec3::X,
            -Vec3::X,
            Vec3::Y,
            Vec3::new(-1.0, 1e-5, 0.0).normalize(),
            Vec3::new(-1.0, 0.0, -1e-9).normalize(),
            Vec3::new(0.3, -0.4, 0.86).normalize(),
        ] {
            let q = rotation_x_to(d);
            let r = q * Vec3::X;
            assert!((r - d).length() < 1e-3, "{d:?} -> {r:?}");
            assert!(q.is_finite());
        }
    }

    #[test]
    fn segments_map_to_midpoint_half_length_and_reject_bad_topology() {
        let pts = vec![
            Vec3::ZERO,
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(5.0, 5.0, 5.0),
        ];
        let g = strands_to_gaussians(&pts, &[0, 3, 4], &[0.1, 0.2], &[[0.2; 3], [0.9; 3]], true)
            .unwrap();
        assert_eq!(g.len(), 2);
        assert_eq!(g.means[0], Vec3::new(1.0, 0.0, 0.0));
        assert_eq!(g.scales[0], Vec3::new(1.0, 0.05, 0.05));
        assert_eq!(g.scales[1].x, 0.0);
        assert!(g.rotations[1].is_finite());
        assert!(strands_to_gaussians(&pts, &[0, 3], &[0.1], &[[0.2; 3]], true).is_err());
        assert!(
            strands_to_gaussians(&pts, &[0, 3, 2, 4], &[0.1; 3], &[[0.2; 3]; 3], true).is_err()
        );
    }
}
