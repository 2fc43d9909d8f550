//! The post-check: reduce displacements that fold, collapse or
//! self-intersect the displaced mesh (the appendix's last step).
//!
//! A face of the displaced mesh `x_i - d_i n_i` is *bad* when
//! - it is **inverted**: its normal points against the outer mesh's face
//!   normal (`dot <= 0`);
//! - it has **severely collapsed**: its area is below `collapse_ratio`
//!   (default 0.1) of the outer face's area (faces degenerate already on
//!   the outer mesh are skipped);
//! - it **newly intersects** another face: the two faces share no vertex,
//!   cross each other in the displaced mesh, and did not in the outer mesh.
//!
//! Every round multiplies the displacement of all vertices of bad faces by
//! `reduce_factor` (default 0.5) and checks again, for at most `max_rounds`
//! (default 12) rounds; vertices still on bad faces after that get `d = 0`
//! (their outer position), repeated until clean or nothing is left to
//! zero. Reductions only shrink `d`, so the bounds `0 <= d <= u` still hold.
//!
//! Intersections are found with a uniform grid over triangle bounding boxes
//! (cell size twice the mean edge length) and an exact-enough test for
//! non-coplanar triangles: two triangles cross when an edge of one passes
//! through the other (six segment/triangle tests). Coplanar overlaps are
//! not reported (they have measure zero for displaced meshes). Candidate
//! pairs are sorted, so the result does not depend on hashing or threads.

use std::collections::{BTreeSet, HashMap};

use glam::Vec3;
use rayon::prelude::*;
use serde::Serialize;

/// Settings of the post-check.
#[derive(Debug, Clone)]
pub struct PostCheckSettings {
    pub collapse_ratio: f32,
    pub reduce_factor: f32,
    pub max_rounds: usize,
    pub check_intersections: bool,
}

impl Default for PostCheckSettings {
    fn default() -> Self {
        PostCheckSettings {
            collapse_ratio: 0.1,
            reduce_factor: 0.5,
            max_rounds: 12,
            check_intersections: true,
        }
    }
}

/// What the post-check found and did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct PostCheckReport {
    pub rounds: usize,
    pub inverted_faces_initial: usize,
    pub collapsed_faces_initial: usize,
    pub intersecting_pairs_initial: usize,
    /// Intersecting face pairs already present on the outer mesh (ignored).
    pub intersecting_pairs_outer: usize,
    pub vertices_reduced: usize,
    pub vertices_zeroed: usize,
    pub clean: bool,
}

/// Displaced positions `x_i - d_i n_i`.
pub fn displace(positions: &[Vec3], normals: &[Vec3], d: &[f32]) -> Vec<Vec3> {
    positions
        .iter()
        .zip(normals)
        .zip(d)
        .map(|((&x, &n), &di)| x - di * n)
        .collect()
}

fn face_normal(p: &[Vec3], t: &[u32; 3]) -> Vec3 {
    let [a, b, c] = t.map(|i| p[i as usize]);
    (b - a).cross(c - a)
}

/// Whether segment `p q` passes through triangle `a b c` (Moller-Trumbore
/// with the segment parameter in [0, 1]).
fn segment_hits_triangle(p: Vec3, q: Vec3, a: Vec3, b: Vec3, c: Vec3) -> bool {
    let dir = q - p;
    let e1 = b - a;
    let e2 = c - a;
    let h = dir.cross(e2);
    let det = e1.dot(h);
    let scale = e1.length() * e2.length() * dir.length();
    if det.abs() <= 1e-9 * scale.max(f32::MIN_POSITIVE) {
        return false;
    }
    let inv = 1.0 / det;
    let s = p - a;
    let u = inv * s.dot(h);
    if !(0.0..=1.0).contains(&u) {
        return false;
    }
    let qv = s.cross(e1);
    let v = inv * dir.dot(qv);
    if v < 0.0 || u + v > 1.0 {
        return false;
    }
    let t = inv * e2.dot(qv);
    (0.0..=1.0).contains(&t)
}

fn triangles_cross(p: &[Vec3], ta: &[u32; 3], tb: &[u32; 3]) -> bool {
    let a = ta.map(|i| p[i as usize]);
    let b = tb.map(|i| p[i as usize]);
    for k in 0..3 {
        if segment_hits_triangle(a[k], a[(k + 1) % 3], b[0], b[1], b[2])
            || segment_hits_triangle(b[k], b[(k + 1) % 3], a[0], a[1], a[2])
        {
            return true;
        }
    }
    false
}

/// All pairs `(f, g)`, `f < g`, of faces sharing no vertex that cross.
pub fn intersecting_pairs(positions: &[Vec3], triangles: &[[u32; 3]]) -> Vec<(u32, u32)> {
    if triangles.len() < 2 {
        return Vec::new();
    }
    let mut edge_sum = 0.0f64;
    for t in triangles {
        for k in 0..3 {
            edge_sum +=
                (positions[t[k] as usize] - positions[t[(k + 1) % 3] as usize]).length() as f64;
        }
    }
    let cell = (2.0 * edge_sum / (3 * triangles.len()) as f64) as f32;
    if !(cell > 0.0 && cell.is_finite()) {
        return Vec::new();
    }
    let boxes: Vec<(Vec3, Vec3)> = triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| positions[i as usize]);
            (a.min(b).min(c), a.max(b).max(c))
        })
        .collect();
    let key = |v: Vec3| -> [i32; 3] {
        let k = (v / cell).floor();
        [k.x as i32, k.y as i32, k.z as i32]
    };
    let mut grid: HashMap<[i32; 3], Vec<u32>> = HashMap::new();
    for (f, (lo, hi)) in boxes.iter().enumerate() {
        let (a, b) = (key(*lo), key(*hi));
        // Guard against absurdly large triangles flooding the grid.
        let span = (b[0] - a[0] + 1) as i64 * (b[1] - a[1] + 1) as i64 * (b[2] - a[2] + 1) as i64;
        if span > 4096 {
            continue;
        }
        for x in a[0]..=b[0] {
            for y in a[1]..=b[1] {
                for z in a[2]..=b[2] {
                    grid.entry([x, y, z]).or_default().push(f as u32);
                }
            }
        }
    }
    let mut cells: Vec<&Vec<u32>> = grid.values().filter(|v| v.len() > 1).collect();
    cells.sort_by_key(|v| v[0]);
    let mut pairs: Vec<(u32, u32)> = cells
        .par_iter()
        .flat_map_iter(|faces| {
            let mut out = Vec::new();
            for (ai, &fa) in faces.iter().enumerate() {
                for &fb in &faces[ai + 1..] {
                    let (f, g) = (fa.min(fb), fa.max(fb));
                    let (ta, tb) = (&triangles[f as usize], &triangles[g as usize]);
                    if ta.iter().any(|v| tb.contains(v)) {
                        continue;
                    }
                    let (la, ha) = boxes[f as usize];
                    let (lb, hb) = boxes[g as usize];
                    if la.cmpgt(hb).any() || lb.cmpgt(ha).any() {
                        continue;
                    }
                    if triangles_cross(positions, ta, tb) {
                        out.push((f, g));
                    }
                }
            }
            out
        })
        .collect();
    pairs.sort_unstable();
    pairs.dedup();
    pairs
}

/// Reduces `d` in place until the displaced mesh has no inverted,
/// collapsed or newly intersecting faces.
pub fn post_check(
    positions: &[Vec3],
    normals: &[Vec3],
    triangles: &[[u32; 3]],
    d: &mut [f32],
    s: &PostCheckSettings,
) -> PostCheckReport {
    let mut report = PostCheckReport::default();
    let outer_normals: Vec<Vec3> = triangles
        .iter()
        .map(|t| face_normal(positions, t))
        .collect();
    let outer_pairs: BTreeSet<(u32, u32)> = if s.check_intersections {
        intersecting_pairs(positions, triangles)
            .into_iter()
            .collect()
    } else {
        BTreeSet::new()
    };
    report.intersecting_pairs_outer = outer_pairs.len();
    let mut reduced = vec![false; d.len()];
    let mut zeroed = vec![false; d.len()];
    let max_total = s.max_rounds + d.len() + 1;
    for round in 0..max_total {
        let p = displace(positions, normals, d);
        let mut bad = vec![false; triangles.len()];
        let mut inverted = 0;
        let mut collapsed = 0;
        for (f, t) in triangles.iter().enumerate() {
            let n0 = outer_normals[f];
            let a0 = n0.length();
            if a0 <= 0.0 {
                continue;
            }
            let n1 = face_normal(&p, t);
            if n1.dot(n0) <= 0.0 {
                inverted += 1;
                bad[f] = true;
            } else if n1.length() < s.collapse_ratio * a0 {
                collapsed += 1;
                bad[f] = true;
            }
        }
        let mut new_pairs = 0;
        if s.check_intersections {
            for (f, g) in intersecting_pairs(&p, triangles) {
                if !outer_pairs.contains(&(f, g)) {
                    new_pairs += 1;
                    bad[f as usize] = true;
                    bad[g as usize] = true;
                }
            }
        }
        if round == 0 {
            report.inverted_faces_initial = inverted;
            report.collapsed_faces_initial = collapsed;
            report.intersecting_pairs_initial = new_pairs;
        }
        report.rounds = round;
        // Vertices of bad faces that can still move back.
        let mut verts: Vec<u32> = triangles
            .iter()
            .zip(&bad)
            .filter(|(_, &b)| b)
            .flat_map(|(t, _)| t.iter().copied())
            .filter(|&v| d[v as usize] > 0.0)
            .collect();
        verts.sort_unstable();
        verts.dedup();
        if verts.is_empty() {
            report.clean = inverted + collapsed + new_pairs == 0;
            break;
        }
        let zero = round >= s.max_rounds;
        for &v in &verts {
            let v = v as usize;
            if zero {
                d[v] = 0.0;
                zeroed[v] = true;
            } else {
                d[v] *= s.reduce_factor;
            }
            reduced[v] = true;
        }
    }
    report.vertices_reduced = reduced.iter().filter(|&&b| b).count();
    report.vertices_zeroed = zeroed.iter().filter(|&&b| b).count();
    report
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crossing_and_separate_triangles() {
        let p = vec![
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
            // A triangle piercing the first one vertically.
            Vec3::new(0.2, 0.2, -0.5),
            Vec3::new(0.2, 0.2, 0.5),
            Vec3::new(0.3, 0.3, 0.5),
            // One floating above.
            Vec3::new(0.2, 0.2, 1.0),
            Vec3::new(0.8, 0.2, 1.0),
            Vec3::new(0.2, 0.8, 1.0),
        ];
        let tris = vec![[0, 1, 2], [3, 4, 5], [6, 7, 8]];
        assert_eq!(intersecting_pairs(&p, &tris), vec![(0, 1)]);
    }

    /// A flat strip of quads, normals +z.
    fn strip(n: usize) -> (Vec<Vec3>, Vec<Vec3>, Vec<[u32; 3]>) {
        let mut p = Vec::new();
        for i in 0..=n {
            p.push(Vec3::new(i as f32, 0.0, 0.0));
            p.push(Vec3::new(i as f32, 1.0, 0.0));
        }
        let mut t = Vec::new();
        for i in 0..n as u32 {
            let (a, b, c, d) = (2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3);
            t.push([a, c, b]);
            t.push([b, c, d]);
        }
        let normals = vec![Vec3::Z; p.len()];
        (p, normals, t)
    }

    #[test]
    fn folds_are_reduced_and_clean_input_is_untouched() {
        let (p, nrm, t) = strip(6);
        // Uniform displacement: a rigid shift, nothing to fix.
        let mut d = vec![0.3; p.len()];
        let rep = post_check(&p, &nrm, &t, &mut d, &PostCheckSettings::default());
        assert!(rep.clean);
        assert_eq!(rep.vertices_reduced, 0);
        assert!(d.iter().all(|&x| x == 0.3));
        // Tilt the normals of one vertex so a large d folds its faces over.
        let mut nrm2 = nrm.clone();
        nrm2[6] = Vec3::new(0.95, 0.0, 0.3).normalize();
        let mut d = vec![0.0; p.len()];
        d[6] = 3.0;
        let before = d[6];
        let rep = post_check(&p, &nrm2, &t, &mut d, &PostCheckSettings::default());
        assert!(rep.inverted_faces_initial > 0, "{rep:?}");
        assert!(rep.clean, "{rep:?}");
        assert!(d[6] < before && d[6] >= 0.0);
        // The result really is fold-free.
        let q = displace(&p, &nrm2, &d);
        for tri in &t {
            assert!(face_normal(&q, tri).z > 0.0);
        }
    }
}
