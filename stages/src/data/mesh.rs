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

    /// What is wrong with the part labels, if anything: not one per vertex,
    /// or a label beyond the part names (a message for a writer's error).
    pub fn part_label_problem(&self) -> Option<String> {
        let nv = self.positions.len();
        if self.part.len() != nv {
            return Some(format!("{} part labels for {nv} vertices", self.part.len()));
        }
        let i = self
            .part
            .iter()
            .position(|&p| p as usize >= self.part_names.len())?;
        Some(format!(
            "vertex {i} has part {} but there are {} part names",
            self.part[i],
            self.part_names.len()
        ))
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

/// How the triangles of a mesh use its edges: what a closed 2-manifold surface
/// (every edge shared by exactly two triangles) needs, with one example of each
/// defect so that an error can point at it. "First" means first in the sorted
/// order of vertex pairs (or triangle order), so reports are deterministic.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Topology {
    /// Distinct undirected edges.
    pub edges: usize,
    /// Edges used by exactly one triangle (the rims of holes).
    pub boundary_edges: usize,
    pub first_boundary_edge: Option<[u32; 2]>,
    /// Edges used by three or more triangles, with the first one and its triangle count.
    pub nonmanifold_edges: usize,
    pub first_nonmanifold_edge: Option<([u32; 2], usize)>,
    /// Triangles that name one vertex twice (zero area by construction).
    pub degenerate_triangles: usize,
    pub first_degenerate_triangle: Option<usize>,
    /// Triangles that name a vertex index past the end of `positions`.
    pub out_of_range_triangles: usize,
}

impl Topology {
    /// Whether every edge is shared by exactly two triangles and no triangle is degenerate.
    pub fn is_closed_manifold(&self) -> bool {
        self.boundary_edges == 0
            && self.nonmanifold_edges == 0
            && self.degenerate_triangles == 0
            && self.out_of_range_triangles == 0
    }

    /// A sentence per defect (empty for a closed manifold). Vertex numbers are
    /// 1-based, as in the `f` lines of an OBJ file.
    pub fn problems(&self) -> Vec<String> {
        let mut out = Vec::new();
        if self.out_of_range_triangles > 0 {
            out.push(format!(
                "{} triangles name vertices that do not exist",
                self.out_of_range_triangles
            ));
        }
        if let Some(t) = self.first_degenerate_triangle {
            out.push(format!(
                "{} degenerate triangles name a vertex twice (the first is face {})",
                self.degenerate_triangles,
                t + 1
            ));
        }
        if let Some(([a, b], n)) = self.first_nonmanifold_edge {
            out.push(format!(
                "non-manifold: {} edges are shared by more than two triangles (e.g. the edge between vertices {} and {} has {n}); expected each edge shared by exactly two",
                self.nonmanifold_edges,
                a + 1,
                b + 1
            ));
        }
        if let Some([a, b]) = self.first_boundary_edge {
            out.push(format!(
                "not watertight: {} boundary edges belong to a single triangle (e.g. the edge between vertices {} and {}); expected a closed surface without holes",
                self.boundary_edges,
                a + 1,
                b + 1
            ));
        }
        out
    }
}

impl Mesh {
    /// Edge-use statistics of the triangles (see [`Topology`]).
    pub fn topology(&self) -> Topology {
        let n = self.positions.len();
        let mut topo = Topology::default();
        let mut edges: Vec<[u32; 2]> = Vec::with_capacity(3 * self.triangles.len());
        for (ti, t) in self.triangles.iter().enumerate() {
            if t.iter().any(|&i| i as usize >= n) {
                topo.out_of_range_triangles += 1;
                continue;
            }
            if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
                topo.degenerate_triangles += 1;
                topo.first_degenerate_triangle.get_or_insert(ti);
                continue;
            }
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                edges.push([a.min(b), a.max(b)]);
            }
        }
        edges.sort_unstable();
        let mut i = 0;
        while i < edges.len() {
            let mut j = i + 1;
            while j < edges.len() && edges[j] == edges[i] {
                j += 1;
            }
            let uses = j - i;
            topo.edges += 1;
            if uses == 1 {
                topo.boundary_edges += 1;
                topo.first_boundary_edge.get_or_insert(edges[i]);
            } else if uses > 2 {
                topo.nonmanifold_edges += 1;
                topo.first_nonmanifold_edge.get_or_insert((edges[i], uses));
            }
            i = j;
        }
        topo
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn part_label_problems_are_named() {
        let mut m = tetra();
        m.part_names = vec!["torso".into(), "tail".into()];
        m.part = vec![0, 1, 1, 0];
        assert_eq!(m.part_label_problem(), None);
        m.part[2] = 2;
        assert_eq!(
            m.part_label_problem().as_deref(),
            Some("vertex 2 has part 2 but there are 2 part names")
        );
        m.part.pop();
        assert_eq!(
            m.part_label_problem().as_deref(),
            Some("3 part labels for 4 vertices")
        );
    }

    fn tetra() -> Mesh {
        Mesh {
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z],
            triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
            ..Default::default()
        }
    }

    #[test]
    fn topology_finds_holes_fins_and_degenerate_faces() {
        let t = tetra();
        let topo = t.topology();
        assert!(topo.is_closed_manifold(), "{topo:?}");
        assert_eq!(topo.edges, 6);
        assert!(topo.problems().is_empty());

        let mut open = tetra();
        open.triangles.pop();
        let topo = open.topology();
        assert_eq!(topo.boundary_edges, 3);
        assert_eq!(topo.first_boundary_edge, Some([1, 2]));
        assert!(topo.problems()[0].contains("not watertight"));

        // A fin: a fifth vertex with a triangle on edge 0-1, used by three triangles then.
        let mut fin = tetra();
        fin.positions.push(Vec3::new(0.5, -1.0, 0.0));
        fin.triangles.push([0, 1, 4]);
        let topo = fin.topology();
        assert_eq!(topo.nonmanifold_edges, 1);
        assert_eq!(topo.first_nonmanifold_edge, Some(([0, 1], 3)));
        let p = topo.problems().join("; ");
        assert!(p.contains("vertices 1 and 2 has 3"), "{p}");

        let mut deg = tetra();
        deg.triangles.push([2, 2, 3]);
        deg.triangles.push([0, 1, 9]);
        let topo = deg.topology();
        assert_eq!(topo.degenerate_triangles, 1);
        assert_eq!(topo.first_degenerate_triangle, Some(4));
        assert_eq!(topo.out_of_range_triangles, 1);
        assert!(!topo.is_closed_manifold());
    }
}
