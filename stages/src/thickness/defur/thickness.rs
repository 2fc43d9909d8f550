//! Shell widths on the outer mesh: raw nearest-shell widths, supported local
//! thickness, part calibration and displacement bounds (the appendix's
//! "Inputs and shell measurements", "Supported local thickness",
//! "Part-level calibration" and the bound `u_i`).
//!
//! Choices where the paper is vague (all exposed as stage parameters):
//! - Percentiles use linear interpolation between order statistics
//!   (NumPy's default `linear` method), over the values as given.
//! - The correspondence weight is a Gaussian in distance times the normal
//!   agreement: `omega_ik = exp(-0.5 (|x_i - y_k| / sigma)^2) * (n_i . nu_k)`
//!   with `sigma = support_radius / 3` (so the 0.03 D acceptance radius sits
//!   at three standard deviations). `omega` lies in (0, 1], so the support
//!   `c_i = max omega_ik` does too, and `c_i ~ 1` when a shell vertex sits on
//!   `x_i` with the same normal (the usual case: Frosting's base mesh is the
//!   outer mesh).
//! - Shell vertices take the part label of their nearest outer-mesh vertex
//!   (the appendix says so).
//! - Ray hits for the bound start `1e-5 D` inside the surface (to skip the
//!   vertex's own triangles) and that offset is added back to the distance.

use std::collections::BTreeMap;

use glam::Vec3;
use rayon::prelude::*;
use serde::Serialize;

use crate::data::shell::ShellWidths;
use crate::maths::geom::{MeshQuery, PointIndex};
use crate::maths::stats::percentile_sorted;

/// Index of the nearest shell vertex for every query point (in parallel, order kept).
pub fn nearest_shell(index: &PointIndex, points: &[Vec3]) -> Vec<usize> {
    points.par_iter().map(|&p| index.nearest(p).0).collect()
}

/// The raw, unrestricted nearest-shell width `tau_i` of every point.
pub fn raw_widths(shell: &ShellWidths, index: &PointIndex, points: &[Vec3]) -> Vec<f32> {
    nearest_shell(index, points)
        .into_iter()
        .map(|k| shell.widths[k])
        .collect()
}

/// Part label of every shell vertex: that of its nearest outer vertex.
pub fn shell_labels(shell: &ShellWidths, outer_index: &PointIndex, outer_part: &[u16]) -> Vec<u16> {
    shell
        .positions
        .par_iter()
        .map(|&y| outer_part[outer_index.nearest(y).0])
        .collect()
}

/// Settings of the supported-thickness step (absolute, in scene units).
#[derive(Debug, Clone)]
pub struct SupportSettings {
    /// Acceptance distance (0.03 D).
    pub radius: f32,
    /// Neighbours considered (12).
    pub max_neighbours: usize,
    /// Minimum `n_i . nu_k` (0.3, strict).
    pub normal_min: f32,
    /// Widths above this are unreliable (the global 97.5th percentile).
    pub width_max: f32,
    /// Gaussian distance scale of the weights.
    pub sigma: f32,
}

/// Supported local thickness per outer vertex.
#[derive(Debug, Clone, Default)]
pub struct Support {
    /// Weighted mean of accepted widths (0 where unsupported).
    pub tbar: Vec<f32>,
    /// Support `c_i = max omega_ik` (0 where unsupported).
    pub c: Vec<f32>,
    /// Accepted correspondences per vertex.
    pub accepted: Vec<u8>,
}

/// Computes `tbar_i` and `c_i` for every outer vertex.
pub fn supported_thickness(
    positions: &[Vec3],
    normals: &[Vec3],
    part: &[u16],
    shell: &ShellWidths,
    shell_part: &[u16],
    shell_index: &PointIndex,
    s: &SupportSettings,
) -> Support {
    let per: Vec<(f32, f32, u8)> = (0..positions.len())
        .into_par_iter()
        .map(|i| {
            let x = positions[i];
            let n = normals[i];
            let mut wsum = 0.0f64;
            let mut wtau = 0.0f64;
            let mut cmax = 0.0f32;
            let mut count = 0u8;
            for (k, dist) in shell_index.nearest_n(x, s.max_neighbours) {
                if !(dist < s.radius) || shell_part[k] != part[i] || shell.widths[k] > s.width_max {
                    continue;
                }
                let dot = n.dot(shell.normals[k]);
                if !(dot > s.normal_min) {
                    continue;
                }
                let g = (-0.5 * (dist / s.sigma).powi(2)).exp();
                let omega = g * dot;
                if !(omega > 0.0) {
                    continue;
                }
                wsum += omega as f64;
                wtau += omega as f64 * shell.widths[k] as f64;
                cmax = cmax.max(omega);
                count += 1;
            }
            if count > 0 && wsum > 0.0 {
                ((wtau / wsum) as f32, cmax, count)
            } else {
                (0.0, 0.0, 0)
            }
        })
        .collect();
    let mut out = Support::default();
    for (t, c, a) in per {
        out.tbar.push(t);
        out.c.push(c);
        out.accepted.push(a);
    }
    out
}

/// One part's calibration, in scene units.
#[derive(Debug, Clone, Serialize)]
pub struct PartCalibration {
    pub name: String,
    pub vertices: usize,
    pub protected: bool,
    /// The part's 95th percentile of raw widths (the cap).
    pub cap: f32,
    pub w75: f32,
    pub w95: f32,
    /// Reference thickness `h_p` used.
    pub h: f32,
    /// Whether `h` came from a supplied reference (else it is `W75`).
    pub h_supplied: bool,
    /// The part guidance `B_p`.
    pub b: f32,
}

/// Part calibration: cap raw widths at each part's P95, take P75 and P95 of
/// the capped values, `B_p = min(0.65 W75 + 0.35 h_p, W95)`, `h_p = W75`
/// when no reference is supplied (an explicit 0 stays 0). `reference`
/// maps part names to `h_p` in scene units. Parts without vertices get zeros.
pub fn calibrate_parts(
    tau: &[f32],
    part: &[u16],
    part_names: &[String],
    protected: &[bool],
    reference: &BTreeMap<String, f32>,
) -> Vec<PartCalibration> {
    let nparts = part_names.len().max(1);
    let mut per: Vec<Vec<f32>> = vec![Vec::new(); nparts];
    for (&t, &p) in tau.iter().zip(part) {
        if let Some(v) = per.get_mut(p as usize) {
            v.push(t);
        }
    }
    per.into_iter()
        .enumerate()
        .map(|(p, mut v)| {
            let name = part_names.get(p).cloned().unwrap_or_default();
            let is_protected = protected.get(p).copied().unwrap_or(false);
            let vertices = v.len();
            let supplied = reference.get(&name).copied();
            if v.is_empty() {
                return PartCalibration {
                    name,
                    vertices,
                    protected: is_protected,
                    cap: 0.0,
                    w75: 0.0,
                    w95: 0.0,
                    h: supplied.unwrap_or(0.0),
                    h_supplied: supplied.is_some(),
                    b: 0.0,
                };
            }
            v.sort_by(f32::total_cmp);
            let cap = percentile_sorted(&v, 95.0);
            for x in v.iter_mut() {
                *x = x.min(cap);
            }
            let w75 = percentile_sorted(&v, 75.0);
            let w95 = percentile_sorted(&v, 95.0);
            let h = supplied.unwrap_or(w75);
            let b = (0.65 * w75 + 0.35 * h).min(w95);
            PartCalibration {
                name,
                vertices,
                protected: is_protected,
                cap,
                w75,
                w95,
                h,
                h_supplied: supplied.is_some(),
                b,
            }
        })
        .collect()
}

/// Settings of the displacement bound (fractions of D).
#[derive(Debug, Clone)]
pub struct BoundSettings {
    /// Scene length scale D.
    pub scale: f32,
    /// `u_i <= hit_frac * r_hit` (0.45).
    pub hit_frac: f32,
    /// `u_i <= max_frac * D` (0.05).
    pub max_frac: f32,
    /// `r_hit` when the inward ray hits nothing (0.1, of D).
    pub miss_frac: f32,
}

/// Bounds `u_i = min(hit_frac r_hit_i, max_frac D)` and the hit distances
/// (`None` for a miss) from rays cast from `x_i` along `-n_i`.
pub fn displacement_bounds(
    query: &MeshQuery,
    positions: &[Vec3],
    normals: &[Vec3],
    s: &BoundSettings,
) -> (Vec<f32>, Vec<Option<f32>>) {
    let eps = 1e-5 * s.scale;
    let max_t = 4.0 * s.scale;
    let hits: Vec<Option<f32>> = positions
        .par_iter()
        .zip(normals.par_iter())
        .map(|(&x, &n)| {
            let dir = -n;
            query.ray_hit(x + dir * eps, dir, max_t).map(|t| t + eps)
        })
        .collect();
    let u = hits
        .iter()
        .map(|h| {
            let r = h.unwrap_or(s.miss_frac * s.scale);
            (s.hit_frac * r).min(s.max_frac * s.scale).max(0.0)
        })
        .collect();
    (u, hits)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calibration_follows_the_appendix() {
        // Part 0: widths 1..=100, part 1: constant 2.
        let mut tau: Vec<f32> = (1..=100).map(|x| x as f32).collect();
        let mut part = vec![0u16; 100];
        tau.extend([2.0; 10]);
        part.extend([1u16; 10]);
        let names = vec!["torso".to_string(), "ears".to_string(), "tail".to_string()];
        let mut refs = BTreeMap::new();
        refs.insert("ears".to_string(), 0.0); // explicit zero stays zero
        let cal = calibrate_parts(&tau, &part, &names, &[false, false, false], &refs);
        let cap = 1.0 + 0.95 * 99.0;
        assert!((cal[0].cap - cap).abs() < 1e-4);
        let w75 = 1.0 + 0.75 * 99.0;
        assert!((cal[0].w75 - w75).abs() < 1e-4);
        assert!(!cal[0].h_supplied);
        assert!((cal[0].b - w75).abs() < 1e-3, "missing h -> B = W75");
        assert!(cal[1].h_supplied && cal[1].h == 0.0);
        assert!((cal[1].b - 0.65 * 2.0).abs() < 1e-6);
        assert_eq!(cal[2].vertices, 0);
        // A large reference is capped by W95.
        refs.insert("torso".to_string(), 1000.0);
        let cal = calibrate_parts(&tau, &part, &names, &[false; 3], &refs);
        assert!((cal[0].b - cal[0].w95).abs() < 1e-4);
    }
}
