//! Spatial queries on meshes and point sets, shared by every stage that needs them.
//!
//! [`MeshQuery`] wraps parry3d's BVH-accelerated triangle mesh (ray casts,
//! closest points, inside tests through pseudo-normals, which need a closed,
//! consistently oriented mesh). [`PointIndex`] wraps kiddo's immutable k-d
//! tree for nearest-neighbour and radius queries. Both are built once and
//! queried from many threads; results are deterministic (ties resolve the same
//! way for the same input order).

use glam::Vec3;
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use parry3d::math::{Isometry, Point, Vector};
use parry3d::query::{PointQuery, PointQueryWithLocation, Ray, RayCast};
use parry3d::shape::{TriMesh, TriMeshFlags};

use crate::mesh::Mesh;

#[derive(Debug, thiserror::Error)]
pub enum GeomError {
    #[error("the mesh has no triangles")]
    EmptyMesh,
    #[error("the point set is empty")]
    EmptyPoints,
    #[error("the mesh refers to vertex {index} but has only {count} vertices")]
    BadIndex { index: u32, count: usize },
    #[error("non-finite vertex coordinates at vertex {0}")]
    NonFinite(usize),
}

impl From<GeomError> for fure_stage_api::StageError {
    fn from(e: GeomError) -> Self {
        fure_stage_api::StageError::failed(e)
    }
}

fn pt(v: Vec3) -> Point<f32> {
    Point::new(v.x, v.y, v.z)
}

/// Ray, closest-point and inside queries against one triangle mesh.
pub struct MeshQuery {
    mesh: TriMesh,
}

impl MeshQuery {
    pub fn new(mesh: &Mesh) -> Result<Self, GeomError> {
        if mesh.triangles.is_empty() {
            return Err(GeomError::EmptyMesh);
        }
        let count = mesh.positions.len();
        for t in &mesh.triangles {
            if let Some(&index) = t.iter().find(|&&i| i as usize >= count) {
                return Err(GeomError::BadIndex { index, count });
            }
        }
        if let Some(i) = mesh.positions.iter().position(|p| !p.is_finite()) {
            return Err(GeomError::NonFinite(i));
        }
        let vertices = mesh.positions.iter().map(|&p| pt(p)).collect();
        let tri = TriMesh::with_flags(vertices, mesh.triangles.clone(), TriMeshFlags::ORIENTED);
        Ok(MeshQuery { mesh: tri })
    }

    /// Distance along `dir` (normalised here) to the first triangle hit, front or back face, within `max_t`.
    pub fn ray_hit(&self, origin: Vec3, dir: Vec3, max_t: f32) -> Option<f32> {
        let d = dir.try_normalize()?;
        let ray = Ray::new(pt(origin), Vector::new(d.x, d.y, d.z));
        self.mesh
            .cast_ray(&Isometry::identity(), &ray, max_t, false)
    }

    /// Closest point on the surface, its distance, and the triangle it lies on.
    pub fn closest_point(&self, p: Vec3) -> (Vec3, f32, u32) {
        let (proj, (tri, _)) = self
            .mesh
            .project_local_point_and_get_location(&pt(p), false);
        let q = Vec3::new(proj.point.x, proj.point.y, proj.point.z);
        (q, (q - p).length(), tri)
    }

    /// Whether `p` is inside the (closed, outward-oriented) mesh.
    pub fn contains(&self, p: Vec3) -> bool {
        self.mesh.project_local_point(&pt(p), false).is_inside
    }

    /// Signed distance: negative inside.
    pub fn signed_distance(&self, p: Vec3) -> f32 {
        let proj = self.mesh.project_local_point(&pt(p), false);
        let d = (Vec3::new(proj.point.x, proj.point.y, proj.point.z) - p).length();
        if proj.is_inside {
            -d
        } else {
            d
        }
    }
}

/// Nearest-neighbour and radius queries on a fixed point set.
pub struct PointIndex {
    tree: ImmutableKdTree<f32, u32, 3, 32>,
    len: usize,
}

impl PointIndex {
    pub fn new(points: &[Vec3]) -> Result<Self, GeomError> {
        if points.is_empty() {
            return Err(GeomError::EmptyPoints);
        }
        if let Some(i) = points.iter().position(|p| !p.is_finite()) {
            return Err(GeomError::NonFinite(i));
        }
        let pts: Vec<[f32; 3]> = points.iter().map(|p| p.to_array()).collect();
        Ok(PointIndex {
            tree: ImmutableKdTree::new_from_slice(&pts),
            len: points.len(),
        })
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The nearest point's index and distance.
    pub fn nearest(&self, p: Vec3) -> (usize, f32) {
        let n = self.tree.nearest_one::<SquaredEuclidean>(&p.to_array());
        (n.item as usize, n.distance.sqrt())
    }

    /// Up to `n` nearest points, closest first, as (index, distance).
    pub fn nearest_n(&self, p: Vec3, n: usize) -> Vec<(usize, f32)> {
        let mut v: Vec<(usize, f32)> = self
            .tree
            .nearest_n::<SquaredEuclidean>(&p.to_array(), n.min(self.len))
            .into_iter()
            .map(|x| (x.item as usize, x.distance.sqrt()))
            .collect();
        sort_by_distance(&mut v);
        v
    }

    /// All points within distance `r`, closest first, as (index, distance).
    pub fn within(&self, p: Vec3, r: f32) -> Vec<(usize, f32)> {
        let mut v: Vec<(usize, f32)> = self
            .tree
            .within_unsorted::<SquaredEuclidean>(&p.to_array(), r * r)
            .into_iter()
            .map(|x| (x.item as usize, x.distance.sqrt()))
            .collect();
        sort_by_distance(&mut v);
        v
    }
}

/// Distance order with index as tie-break, so results never depend on traversal order.
fn sort_by_distance(v: &mut [(usize, f32)]) {
    v.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
}

/// Sorted, deduplicated one-ring vertex neighbours of every vertex.
pub fn vertex_neighbours(mesh: &Mesh) -> Vec<Vec<u32>> {
    let mut nb = vec![Vec::new(); mesh.positions.len()];
    for [a, b] in mesh.edges() {
        nb[a as usize].push(b);
        nb[b as usize].push(a);
    }
    for n in &mut nb {
        n.sort_unstable();
        n.dedup();
    }
    nb
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An axis-aligned cube [-1, 1]^3 with outward-facing triangles.
    fn cube() -> Mesh {
        let positions: Vec<Vec3> = (0..8)
            .map(|i| {
                Vec3::new(
                    if i & 1 == 0 { -1.0 } else { 1.0 },
                    if i & 2 == 0 { -1.0 } else { 1.0 },
                    if i & 4 == 0 { -1.0 } else { 1.0 },
                )
            })
            .collect();
        let quads = [
            [0, 2, 3, 1], // z = -1
            [4, 5, 7, 6], // z = +1
            [0, 1, 5, 4], // y = -1
            [2, 6, 7, 3], // y = +1
            [0, 4, 6, 2], // x = -1
            [1, 3, 7, 5], // x = +1
        ];
        let triangles = quads
            .iter()
            .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
            .collect();
        let mut m = Mesh {
            positions,
            triangles,
            part: vec![0; 8],
            ..Default::default()
        };
        m.recompute_normals();
        m
    }

    #[test]
    fn cube_queries() {
        let m = cube();
        let q = MeshQuery::new(&m).unwrap();
        assert!(q.contains(Vec3::ZERO));
        assert!(!q.contains(Vec3::new(2.0, 0.0, 0.0)));
        let t = q.ray_hit(Vec3::ZERO, Vec3::X, 10.0).unwrap();
        assert!((t - 1.0).abs() < 1e-5);
        assert!(q.ray_hit(Vec3::new(3.0, 0.0, 0.0), Vec3::X, 10.0).is_none());
        let (c, d, _) = q.closest_point(Vec3::new(0.2, 0.1, 3.0));
        assert!((d - 2.0).abs() < 1e-5 && (c.z - 1.0).abs() < 1e-5);
        assert!((q.signed_distance(Vec3::new(0.5, 0.0, 0.0)) + 0.5).abs() < 1e-5);
    }

    #[test]
    fn point_index_matches_brute_force() {
        let pts: Vec<Vec3> = (0..500)
            .map(|i| {
                let f = i as f32;
                Vec3::new((f * 0.37).sin(), (f * 0.11).cos(), (f * 0.07).sin() * 2.0)
            })
            .collect();
        let idx = PointIndex::new(&pts).unwrap();
        let q = Vec3::new(0.1, 0.2, 0.3);
        let mut brute: Vec<(usize, f32)> = pts
            .iter()
            .enumerate()
            .map(|(i, p)| (i, (*p - q).length()))
            .collect();
        sort_by_distance(&mut brute);
        let got = idx.nearest_n(q, 10);
        assert_eq!(
            got.iter().map(|x| x.0).collect::<Vec<_>>(),
            brute[..10].iter().map(|x| x.0).collect::<Vec<_>>()
        );
        assert_eq!(idx.nearest(q).0, brute[0].0);
        // A radius halfway between two neighbours, so rounding cannot decide membership.
        let r = 0.5 * (brute[20].1 + brute[21].1);
        assert_eq!(
            idx.within(q, r).len(),
            brute.iter().filter(|x| x.1 <= r).count()
        );
    }

    #[test]
    fn empty_inputs_are_errors() {
        assert!(MeshQuery::new(&Mesh::default()).is_err());
        assert!(PointIndex::new(&[]).is_err());
        assert!(PointIndex::new(&[Vec3::NAN]).is_err());
    }

    #[test]
    fn neighbours_of_cube_corner() {
        let nb = vertex_neighbours(&cube());
        assert!(nb[0].contains(&1) && nb[0].contains(&2) && nb[0].contains(&4));
    }
}
