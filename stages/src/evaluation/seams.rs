//! Direction seams at part boundaries: does the growth direction jump where one labelled part of
//! the skin meets another, more than the ground truth's does there?
//!
//! Roots are placed and framed per part, so a part whose tangent field points the other way, or a
//! frame that turns at the label boundary, shows as a seam (issue 15: "no direction discontinuity
//! at part boundaries where the GT has none"). The mean direction error cannot see it: a seam is a
//! thin band of roots. This module measures it on both strand sets alike (metrics only: the GT
//! skin's labels and tangent planes are ground truth).
//!
//! # The measure
//! 1. Each strand of an even stride of at most [`SEAM_SAMPLE`] strands gets its root, its in-plane
//!    direction (the root-to-tip chord projected onto the GT skin's tangent plane at the root's
//!    closest point, normalised; strands standing straight up are skipped, as in the direction
//!    error) and a part: the label of the closest triangle's vertex nearest that point.
//! 2. Around each sampled root, the neighbours closer than `radius_cm` on its own part and on
//!    each other part are summed into mean directions (growth sign counted). Where both sides
//!    have at least [`MIN_SIDE`] neighbours, the root sees the boundary `A|B`, and the angle
//!    between the two sides' mean directions (0-180 degrees) is its **jump** there. Means, not
//!    single pairs: a coat's strand-to-strand scatter (the GT's neighbours differ by about 11
//!    degrees on the tiger, a learner's smooth field by 5) would otherwise read as a seam on the
//!    noisier set and hide one on the smoother.
//! 3. A set's jump at `A|B` is the mean over the roots that see it; `opposed_frac` is the share
//!    of those roots whose two sides grow more than 90 degrees apart (a sign flip). The radius is
//!    fixed in centimetres, so the measure does not depend on the sampling density or the unit.
//! 4. A method's **seam excess** at `A|B` is its jump minus the GT's jump there: the GT's fur turns
//!    at some boundaries too (leg joints, the tail's root), and that turn is not a seam.
//!    Boundaries seen by fewer than [`MIN_BOUNDARY_ROOTS`] roots on either side are not judged.
//!    The report gives the worst boundary and the mean over boundaries weighted by the method's
//!    roots there. `within_deg` (the mean angle between neighbouring strands on one part) is kept
//!    beside it: the set's own scatter.
//!
//! Sums run in f64 in index order, so the result does not depend on threads.

use std::collections::BTreeMap;

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::data::mesh::Mesh;
use crate::data::strands::Strands;
use crate::maths::geom::{MeshQuery, PointIndex};
use fure_stage_api::StageError;

/// Most strands of a set the measure samples (an even stride over the rest).
pub const SEAM_SAMPLE: usize = 40_000;

/// Fewest roots near a boundary, on each side of the comparison, for it to be judged.
pub const MIN_BOUNDARY_ROOTS: usize = 30;

/// Fewest neighbours on each side of a boundary for a root to see it.
pub const MIN_SIDE: usize = 3;

/// The angle between two directions (degrees, 0-180); 0 when either vanishes.
fn angle_deg(a: Vec3, b: Vec3) -> f64 {
    let l = a.length() * b.length();
    if !(l > 0.0) {
        return 0.0;
    }
    ((a.dot(b) / l).clamp(-1.0, 1.0) as f64).acos().to_degrees()
}

/// One boundary between two parts, seen from the roots near it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Boundary {
    /// `A|B`, the two part names in name order.
    pub parts: String,
    /// Roots with at least [`MIN_SIDE`] neighbours on each side.
    pub roots: usize,
    /// Mean over those roots of the angle between the two sides' mean directions (degrees).
    pub jump_deg: f64,
    /// Fraction of those roots whose two sides grow more than 90 degrees apart.
    pub opposed_frac: f64,
}

/// Neighbouring strands' direction agreement within parts and across each boundary of one set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeamStats {
    pub radius_cm: f64,
    pub within_pairs: usize,
    /// Mean angle between neighbouring strands on one part (degrees): the set's own scatter.
    pub within_deg: f64,
    /// Boundaries in name order.
    pub boundaries: Vec<Boundary>,
}

/// A method's seams over the GT's: the boundaries both sets judge.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeamExcess {
    /// Boundary with the largest excess, `A|B`.
    pub worst_boundary: String,
    /// The method's jump minus the GT's there (degrees).
    pub worst_excess_deg: f64,
    /// Mean excess over the judged boundaries, weighted by the method's roots there.
    pub mean_excess_deg: f64,
    pub boundaries_judged: usize,
    /// Every judged boundary's excess (degrees), by `A|B`.
    pub by_boundary: BTreeMap<String, f64>,
}

/// Per sampled strand: root, in-plane unit direction, part.
fn sampled_directions(
    strands: &Strands,
    skin: &Mesh,
    query: &MeshQuery,
) -> Vec<Option<(Vec3, Vec3, u16)>> {
    let stride = strands.len().div_ceil(SEAM_SAMPLE).max(1);
    let picks: Vec<usize> = (0..strands.len()).step_by(stride).collect();
    picks
        .par_iter()
        .map(|&i| {
            let p = strands.strand(i);
            let (a, b) = (*p.first()?, *p.last()?);
            let chord = b - a;
            let full = chord.length();
            if !(full > 0.0) {
                return None;
            }
            let (n, closest, tri) = skin_plane_at(query, skin, a);
            let in_plane = chord - n * chord.dot(n);
            // Straight up: no in-plane direction (the direction error's rule).
            if !(in_plane.length() > 1e-3 * full) {
                return None;
            }
            Some((a, in_plane.normalize(), skin_part_at(skin, closest, tri)))
        })
        .collect()
}

/// The unit normal of the skin triangle closest to `p` (zero for a degenerate one), the closest
/// point and the triangle: the tangent plane in which in-plane directions are taken.
pub fn skin_plane_at(query: &MeshQuery, skin: &Mesh, p: Vec3) -> (Vec3, Vec3, u32) {
    let (closest, _, tri) = query.closest_point(p);
    let [a, b, c] = skin.triangles[tri as usize].map(|v| skin.positions[v as usize]);
    ((b - a).cross(c - a).normalize_or_zero(), closest, tri)
}

/// The part label of the skin at `closest`, a point of triangle `tri`: the label of the
/// triangle's vertex nearest it (0 on an unlabelled skin).
pub fn skin_part_at(skin: &Mesh, closest: Vec3, tri: u32) -> u16 {
    let corners = skin.triangles[tri as usize];
    let nearest = corners
        .iter()
        .copied()
        .min_by(|&u, &v| {
            let du = (skin.positions[u as usize] - closest).length_squared();
            let dv = (skin.positions[v as usize] - closest).length_squared();
            du.total_cmp(&dv)
        })
        .unwrap_or(corners[0]);
    skin.part.get(nearest as usize).copied().unwrap_or(0)
}

/// The seam statistics of one strand set on a labelled skin (`s_cm` centimetres per scene unit,
/// neighbours within `radius_cm`). `None` when the skin has no part labels or no pair was found.
pub fn seam_stats(
    strands: &Strands,
    skin: &Mesh,
    s_cm: f32,
    radius_cm: f32,
) -> Result<Option<SeamStats>, StageError> {
    if skin.part.len() != skin.positions.len() || skin.part_names.len() < 2 || strands.is_empty() {
        return Ok(None);
    }
    let query = MeshQuery::new(skin).map_err(StageError::failed)?;
    let samples: Vec<(Vec3, Vec3, u16)> = sampled_directions(strands, skin, &query)
        .into_iter()
        .flatten()
        .collect();
    if samples.len() < 2 {
        return Ok(None);
    }
    let roots: Vec<Vec3> = samples.iter().map(|s| s.0).collect();
    let index = PointIndex::new(&roots).map_err(StageError::failed)?;
    let radius = radius_cm / s_cm;
    // Per root: its within-part pair angles (j > i, so each pair counts once) and, for every other
    // part among its neighbours, the angle between the two sides' summed directions; reduced
    // below in root order.
    type Partial = (f64, usize, Vec<((u16, u16), f64)>);
    let partials: Vec<Partial> = (0..samples.len())
        .into_par_iter()
        .map(|i| {
            let (_, di, pi) = samples[i];
            let (mut sum, mut n) = (0.0f64, 0usize);
            let (mut own, mut own_n) = (Vec3::ZERO, 0usize);
            let mut other: BTreeMap<u16, (Vec3, usize)> = BTreeMap::new();
            for j in index.indices_within(roots[i], radius) {
                let j = j as usize;
                let (_, dj, pj) = samples[j];
                if pj == pi {
                    own += dj;
                    own_n += 1;
                    if j > i {
                        sum += angle_deg(di, dj);
                        n += 1;
                    }
                } else {
                    let e = other.entry(pj).or_insert((Vec3::ZERO, 0));
                    e.0 += dj;
                    e.1 += 1;
                }
            }
            let jumps = other
                .into_iter()
                .filter(|&(_, (_, m))| own_n >= MIN_SIDE && m >= MIN_SIDE)
                .map(|(q, (d, _))| ((pi.min(q), pi.max(q)), angle_deg(own, d)))
                .collect();
            (sum, n, jumps)
        })
        .collect();
    let (mut within_sum, mut within_pairs) = (0.0f64, 0usize);
    let mut per: BTreeMap<(u16, u16), (f64, usize, usize)> = BTreeMap::new();
    for (sum, n, jumps) in partials {
        within_sum += sum;
        within_pairs += n;
        for (key, angle) in jumps {
            let e = per.entry(key).or_default();
            e.0 += angle;
            e.1 += 1;
            e.2 += usize::from(angle > 90.0);
        }
    }
    if within_pairs == 0 && per.is_empty() {
        return Ok(None);
    }
    let within_deg = if within_pairs > 0 {
        within_sum / within_pairs as f64
    } else {
        0.0
    };
    let name = |p: u16| {
        skin.part_names
            .get(p as usize)
            .cloned()
            .unwrap_or_else(|| format!("part{p}"))
    };
    let mut boundaries: Vec<Boundary> = per
        .iter()
        .map(|(&(a, b), &(sum, n, opposed))| {
            let (na, nb) = (name(a), name(b));
            let parts = if na <= nb {
                format!("{na}|{nb}")
            } else {
                format!("{nb}|{na}")
            };
            Boundary {
                parts,
                roots: n,
                jump_deg: sum / n as f64,
                opposed_frac: opposed as f64 / n as f64,
            }
        })
        .collect();
    boundaries.sort_by(|x, y| x.parts.cmp(&y.parts));
    Ok(Some(SeamStats {
        radius_cm: radius_cm as f64,
        within_pairs,
        within_deg,
        boundaries,
    }))
}

/// The method's seams over the GT's, on the boundaries where both have at least
/// [`MIN_BOUNDARY_ROOTS`] roots near it; `None` when there is no such boundary.
pub fn seam_excess(pred: &SeamStats, gt: &SeamStats) -> Option<SeamExcess> {
    let gt_by: BTreeMap<&str, &Boundary> = gt
        .boundaries
        .iter()
        .filter(|b| b.roots >= MIN_BOUNDARY_ROOTS)
        .map(|b| (b.parts.as_str(), b))
        .collect();
    let judged: Vec<(&Boundary, f64)> = pred
        .boundaries
        .iter()
        .filter(|b| b.roots >= MIN_BOUNDARY_ROOTS)
        .filter_map(|b| {
            gt_by
                .get(b.parts.as_str())
                .map(|g| (b, b.jump_deg - g.jump_deg))
        })
        .collect();
    let worst = judged
        .iter()
        .max_by(|x, y| x.1.total_cmp(&y.1).then_with(|| y.0.parts.cmp(&x.0.parts)))?;
    let weight: usize = judged.iter().map(|(b, _)| b.roots).sum();
    let mean = judged.iter().map(|(b, e)| e * b.roots as f64).sum::<f64>() / weight as f64;
    Some(SeamExcess {
        worst_boundary: worst.0.parts.clone(),
        worst_excess_deg: worst.1,
        mean_excess_deg: mean,
        boundaries_judged: judged.len(),
        by_boundary: judged.iter().map(|(b, e)| (b.parts.clone(), *e)).collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat 40 x 20 cm skin (z = 0, normal +z) in two parts split at x = 0: `left` (x < 0)
    /// and `right`, triangulated on a 1 cm grid.
    fn two_part_skin(scale: f32) -> Mesh {
        let (nx, ny) = (41usize, 21usize);
        let mut m = Mesh {
            part_names: vec!["left".into(), "right".into()],
            ..Default::default()
        };
        for j in 0..ny {
            for i in 0..nx {
                let p = Vec3::new(i as f32 - 20.0, j as f32 - 10.0, 0.0) * scale;
                m.positions.push(p);
                m.normals.push(Vec3::Z);
                m.part.push(u16::from(i > 20));
            }
        }
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let v = |a: usize, b: usize| (b * nx + a) as u32;
                m.triangles.push([v(i, j), v(i + 1, j), v(i + 1, j + 1)]);
                m.triangles.push([v(i, j), v(i + 1, j + 1), v(i, j + 1)]);
            }
        }
        m
    }

    /// Roots beyond this x are labelled `right` (their nearest skin vertex is x >= 1).
    const RIGHT: f32 = 0.5;

    /// Strands on a 0.5 cm grid of the skin, lying at 20 degrees along `dir(x)` (in-plane).
    fn strands_on(scale: f32, dir: impl Fn(f32, f32) -> Vec3) -> Strands {
        let mut s = Strands::new();
        for j in 0..38 {
            for i in 0..78 {
                let (x, y) = (i as f32 * 0.5 - 19.25, j as f32 * 0.5 - 9.25);
                let d = dir(x, y).normalize();
                let root = Vec3::new(x, y, 0.0);
                let tip = root + (d * 20f32.to_radians().cos() + Vec3::Z * 0.34) * 2.0;
                s.push(&[root * scale, tip * scale], 0, 1e-3, [0.5; 3]);
            }
        }
        s
    }

    #[test]
    fn a_part_whose_fur_points_the_other_way_is_a_seam_and_a_turn_the_gt_shares_is_not() {
        let skin = two_part_skin(1.0);
        let gt = strands_on(1.0, |x, y| {
            Vec3::new(1.0, 0.3 * (x * 0.2 + y * 0.3).sin(), 0.0)
        });
        let flipped = strands_on(1.0, |x, y| {
            let d = Vec3::new(1.0, 0.3 * (x * 0.2 + y * 0.3).sin(), 0.0);
            if x > RIGHT {
                -d
            } else {
                d
            }
        });
        let g = seam_stats(&gt, &skin, 1.0, 2.1).unwrap().unwrap();
        let f = seam_stats(&flipped, &skin, 1.0, 2.1).unwrap().unwrap();
        assert_eq!(g.boundaries.len(), 1);
        assert_eq!(g.boundaries[0].parts, "left|right");
        assert!(g.boundaries[0].jump_deg < 6.0, "{g:?}");
        assert!(f.boundaries[0].jump_deg > 170.0, "{f:?}");
        assert!(f.boundaries[0].opposed_frac > 0.99, "{f:?}");
        assert!(g.boundaries[0].opposed_frac == 0.0, "{g:?}");
        let e = seam_excess(&f, &g).unwrap();
        assert_eq!(e.worst_boundary, "left|right");
        assert!(e.worst_excess_deg > 140.0, "{e:?}");
        // The same strands as the GT: no excess.
        let same = seam_excess(&g, &g).unwrap();
        assert!(same.worst_excess_deg.abs() < 1e-9);
        // A GT that turns 90 degrees at the boundary, and a method that turns with it: no seam.
        let turn = |x: f32, _: f32| if x > RIGHT { Vec3::Y } else { Vec3::X };
        let gt_turn = seam_stats(&strands_on(1.0, turn), &skin, 1.0, 2.1)
            .unwrap()
            .unwrap();
        assert!(gt_turn.boundaries[0].jump_deg > 60.0, "{gt_turn:?}");
        let e = seam_excess(&gt_turn, &gt_turn).unwrap();
        assert!(e.worst_excess_deg.abs() < 1e-9);
        // A method that keeps going straight where the GT turns is judged by the GT's turn:
        // negative excess (smoother than the truth), not a seam.
        let e = seam_excess(&g, &gt_turn).unwrap();
        assert!(e.worst_excess_deg < -60.0, "{e:?}");
    }

    #[test]
    fn the_measure_does_not_depend_on_the_unit() {
        let dir = |x: f32, y: f32| {
            let d = Vec3::new(1.0, 0.5 * (x * 0.3).sin() + 0.2 * y.cos(), 0.0);
            if x > RIGHT {
                Vec3::new(-d.y, d.x, 0.0)
            } else {
                d
            }
        };
        let cm = seam_stats(&strands_on(1.0, dir), &two_part_skin(1.0), 1.0, 2.1)
            .unwrap()
            .unwrap();
        let m = seam_stats(&strands_on(0.01, dir), &two_part_skin(0.01), 100.0, 2.1)
            .unwrap()
            .unwrap();
        assert_eq!(cm.within_pairs, m.within_pairs);
        assert_eq!(cm.boundaries[0].roots, m.boundaries[0].roots);
        assert!((cm.within_deg - m.within_deg).abs() < 1e-3, "{cm:?} {m:?}");
        assert!((cm.boundaries[0].jump_deg - m.boundaries[0].jump_deg).abs() < 1e-3);
    }

    #[test]
    fn a_skin_without_labels_or_strands_gives_no_measure() {
        let mut skin = two_part_skin(1.0);
        let s = strands_on(1.0, |_, _| Vec3::X);
        assert!(seam_stats(&Strands::new(), &skin, 1.0, 2.1)
            .unwrap()
            .is_none());
        skin.part_names.truncate(1);
        assert!(seam_stats(&s, &skin, 1.0, 2.1).unwrap().is_none());
    }
}
