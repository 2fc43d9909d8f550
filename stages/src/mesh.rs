//! Triangle meshes with per-vertex part labels: the skin, the outer envelope, the root mesh.

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// An indexed triangle mesh. Normals are per vertex (unit, outward for closed
/// surfaces); `part` indexes `part_names` for every vertex (empty `part_names`
/// means unlabelled, and then `part` is all zeros).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
    pub part: Vec<u16>,
    pub part_names: Vec<String>,
}

impl Mesh {
    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }

    /// Recomputes area-weighted vertex normals from the triangles.
    pub fn recompute_normals(&mut self) {
        let mut n = vec![Vec3::ZERO; self.positions.len()];
        for t in &self.triangles {
            let [a, b, c] = t.map(|i| self.positions[i as usize]);
            let fn_ = (b - a).cross(c - a); // length = 2 * area: area weighting for free
            for &i in t {
                n[i as usize] += fn_;
            }
        }
        for v in &mut n {
            *v = v.try_normalize().unwrap_or(Vec3::Z);
        }
        self.normals = n;
    }

    /// Axis-aligned bounding box (min, max); zeros for an empty mesh.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        if self.positions.is_empty() {
            return (Vec3::ZERO, Vec3::ZERO);
        }
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for p in &self.positions {
            lo = lo.min(*p);
            hi = hi.max(*p);
        }
        (lo, hi)
    }

    /// The scene length scale `D` of the method: the bounding-box diagonal.
    pub fn diagonal(&self) -> f32 {
        let (lo, hi) = self.bounds();
        (hi - lo).length()
    }

    /// Name of the part of vertex `i` ("" when unlabelled).
    pub fn part_name(&self, i: usize) -> &str {
        self.part_names
            .get(self.part.get(i).copied().unwrap_or(0) as usize)
            .map(String::as_str)
            .unwrap_or("")
    }

    /// Unique undirected edges (i < j), sorted.
    pub fn edges(&self) -> Vec<[u32; 2]> {
        let mut e: Vec<[u32; 2]> = self
            .triangles
            .iter()
            .flat_map(|t| [[t[0], t[1]], [t[1], t[2]], [t[2], t[0]]])
            .map(|[a, b]| if a < b { [a, b] } else { [b, a] })
            .collect();
        e.sort_unstable();
        e.dedup();
        e
    }

    /// Total surface area.
    pub fn area(&self) -> f32 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| self.positions[i as usize]);
                0.5 * (b - a).cross(c - a).length()
            })
            .sum()
    }
}
