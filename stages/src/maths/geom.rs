//! Spatial queries on meshes and point sets, shared by every stage that needs them.
//!
//! [`MeshQuery`] wraps parry3d's BVH-accelerated triangle mesh (ray casts,
//! closest points, inside tests through pseudo-normals, which need a closed,
//! consistently oriented mesh). [`PointIndex`] is a small k-d tree for
//! nearest-neighbour and radius queries. Both are built once and
//! queried from many threads; results are deterministic (ties resolve the same
//! way for the same input order).

use glam::Vec3;
use parry3d::math::{Isometry, Point, Vector};
use parry3d::query::{PointQuery, PointQueryWithLocation, Ray, RayCast};
use parry3d::shape::{TriMesh, TriMeshFlags};

use crate::data::mesh::Mesh;

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
///
/// A hand-written, implicit k-d tree (points permuted into leaves of at most
/// `LEAF` points, split at the median of the widest axis). Written here
/// rather than taken from kiddo because kiddo 4's trees panic when more than a
/// bucket's worth of points share a coordinate, which regular grids and
/// duplicated vertices produce all the time.
pub struct PointIndex {
    points: Vec<Vec3>,
    /// Point indices, permuted so that every node owns a contiguous range.
    order: Vec<u32>,
    nodes: Vec<Node>,
}

const LEAF: usize = 16;

#[derive(Clone, Copy)]
struct Node {
    lo: Vec3,
    hi: Vec3,
    start: u32,
    end: u32,
    /// Children indices, `u32::MAX` for leaves.
    left: u32,
    right: u32,
}

impl PointIndex {
    pub fn new(points: &[Vec3]) -> Result<Self, GeomError> {
        if points.is_empty() {
            return Err(GeomError::EmptyPoints);
        }
        if let Some(i) = points.iter().position(|p| !p.is_finite()) {
            return Err(GeomError::NonFinite(i));
        }
        let mut idx = PointIndex {
            points: points.to_vec(),
            order: (0..points.len() as u32).collect(),
            nodes: Vec::with_capacity(2 * points.len() / LEAF + 1),
        };
        idx.build(0, points.len());
        Ok(idx)
    }

    fn build(&mut self, start: usize, end: usize) -> u32 {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for &i in &self.order[start..end] {
            lo = lo.min(self.points[i as usize]);
            hi = hi.max(self.points[i as usize]);
        }
        let id = self.nodes.len() as u32;
        self.nodes.push(Node {
            lo,
            hi,
            start: start as u32,
            end: end as u32,
            left: u32::MAX,
            right: u32::MAX,
        });
        if end - start > LEAF {
            let ext = hi - lo;
            let axis = if ext.x >= ext.y && ext.x >= ext.z {
                0
            } else if ext.y >= ext.z {
                1
            } else {
                2
            };
            let mid = (start + end) / 2;
            let pts = &self.points;
            // Index as tie-break: equal coordinates still split, deterministically.
            self.order[start..end].select_nth_unstable_by(mid - start, |&a, &b| {
                pts[a as usize][axis]
                    .total_cmp(&pts[b as usize][axis])
                    .then(a.cmp(&b))
            });
            let left = self.build(start, mid);
            let right = self.build(mid, end);
            self.nodes[id as usize].left = left;
            self.nodes[id as usize].right = right;
        }
        id
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The nearest point's index and distance.
    pub fn nearest(&self, p: Vec3) -> (usize, f32) {
        self.nearest_n(p, 1)[0]
    }

    /// Up to `n` nearest points, closest first, as (index, distance).
    pub fn nearest_n(&self, p: Vec3, n: usize) -> Vec<(usize, f32)> {
        let n = n.min(self.len());
        if n == 0 {
            return Vec::new();
        }
        // Best candidates so far as (squared distance, index), sorted ascending.
        let mut best: Vec<(f32, u32)> = Vec::with_capacity(n + 1);
        let mut stack = vec![0u32];
        while let Some(id) = stack.pop() {
            let node = self.nodes[id as usize];
            let d2 = box_distance2(p, node.lo, node.hi);
            if best.len() == n && d2 > best[n - 1].0 {
                continue;
            }
            if node.left == u32::MAX {
                for &i in &self.order[node.start as usize..node.end as usize] {
                    let c = (self.points[i as usize].distance_squared(p), i);
                    if best.len() == n && !less(c, best[n - 1]) {
                        continue;
                    }
                    let at = best.partition_point(|&b| less(b, c));
                    best.insert(at, c);
                    best.truncate(n);
                }
            } else {
                // Visit the nearer child first (pushed last).
                let (l, r) = (
                    self.nodes[node.left as usize],
                    self.nodes[node.right as usize],
                );
                if box_distance2(p, l.lo, l.hi) <= box_distance2(p, r.lo, r.hi) {
                    stack.push(node.right);
                    stack.push(node.left);
                } else {
                    stack.push(node.left);
                    stack.push(node.right);
                }
            }
        }
        best.into_iter()
            .map(|(d2, i)| (i as usize, d2.sqrt()))
            .collect()
    }

    /// All points within distance `r`, closest first, as (index, distance).
    pub fn within(&self, p: Vec3, r: f32) -> Vec<(usize, f32)> {
        let mut out = Vec::new();
        self.for_each_within(p, r, |i, d2| out.push((i as usize, d2.sqrt())));
        sort_by_distance(&mut out);
        out
    }

    /// The indices of all points within distance `r`, ascending: a fixed
    /// order for sums over neighbourhoods, without [`PointIndex::within`]'s
    /// distances and sort by them.
    pub fn indices_within(&self, p: Vec3, r: f32) -> Vec<u32> {
        let mut out = Vec::new();
        self.for_each_within(p, r, |i, _| out.push(i));
        sort_indices(&mut out);
        out
    }

    /// How many points lie within distance `r`, and how many of them `keep`
    /// holds for: counts need no order, so neither a list nor a sort.
    pub fn count_within(&self, p: Vec3, r: f32, keep: impl Fn(u32) -> bool) -> (usize, usize) {
        let (mut kept, mut all) = (0, 0);
        self.for_each_within(p, r, |i, _| {
            all += 1;
            kept += keep(i) as usize;
        });
        (kept, all)
    }

    /// Calls `f(index, squared distance)` for every point within distance
    /// `r`, in the tree's order.
    fn for_each_within(&self, p: Vec3, r: f32, mut f: impl FnMut(u32, f32)) {
        let r2 = r * r;
        let mut stack = vec![0u32];
        while let Some(id) = stack.pop() {
            let node = self.nodes[id as usize];
            if box_distance2(p, node.lo, node.hi) > r2 {
                continue;
            }
            if node.left == u32::MAX {
                for &i in &self.order[node.start as usize..node.end as usize] {
                    let d2 = self.points[i as usize].distance_squared(p);
                    if d2 <= r2 {
                        f(i, d2);
                    }
                }
            } else {
                stack.push(node.left);
                stack.push(node.right);
            }
        }
    }
}

/// Sorts indices ascending. The view-axes windows hold thousands of roots each, one window per
/// root, and a comparison sort of every window took 7 % of the tiger codec's CPU samples; a
/// least-significant-digit radix sort by bytes, as many passes as the largest index needs (two
/// below 65,536), does the same in linear time. Integer keys, so the result is the one any sort
/// gives.
fn sort_indices(v: &mut Vec<u32>) {
    const SMALL: usize = 256;
    if v.len() < SMALL {
        v.sort_unstable();
        return;
    }
    let max = v.iter().copied().max().unwrap_or(0);
    let passes = (u32::BITS - max.leading_zeros()).div_ceil(8).max(1);
    let mut buf = vec![0u32; v.len()];
    for pass in 0..passes {
        let shift = 8 * pass;
        let mut next = [0usize; 257];
        for &x in v.iter() {
            next[((x >> shift) & 0xff) as usize + 1] += 1;
        }
        for d in 0..256 {
            next[d + 1] += next[d];
        }
        for &x in v.iter() {
            let d = ((x >> shift) & 0xff) as usize;
            buf[next[d]] = x;
            next[d] += 1;
        }
        std::mem::swap(v, &mut buf);
    }
}

/// Total order on (squared distance, index).
#[inline]
fn less(a: (f32, u32), b: (f32, u32)) -> bool {
    a.0 < b.0 || (a.0 == b.0 && a.1 < b.1)
}

/// Squared distance from `p` to the box [lo, hi] (0 inside).
#[inline]
fn box_distance2(p: Vec3, lo: Vec3, hi: Vec3) -> f32 {
    let d = (lo - p).max(p - hi).max(Vec3::ZERO);
    d.length_squared()
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
        let mut inside: Vec<u32> = brute
            .iter()
            .filter(|x| x.1 <= r)
            .map(|x| x.0 as u32)
            .collect();
        inside.sort_unstable();
        assert_eq!(idx.indices_within(q, r), inside);
        let even = inside.iter().filter(|&&i| i % 2 == 0).count();
        assert_eq!(idx.count_within(q, r, |i| i % 2 == 0), (even, inside.len()));
    }

    #[test]
    fn indices_sort_as_a_comparison_sort_does() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        // Below the radix threshold, one byte, two bytes, four bytes, with repeats.
        for (n, max) in [
            (10, 1000u32),
            (300, 200),
            (5000, 60_000),
            (4000, u32::MAX),
            (700, 3),
        ] {
            let v: Vec<u32> = (0..n).map(|_| rng.gen_range(0..=max)).collect();
            let mut want = v.clone();
            want.sort_unstable();
            let mut got = v;
            sort_indices(&mut got);
            assert_eq!(got, want, "n = {n}, max = {max}");
        }
    }

    #[test]
    fn many_equal_coordinates_do_not_panic() {
        // A lattice plus exact duplicates: every coordinate is shared by hundreds of points.
        let mut pts = Vec::new();
        for i in 0..20 {
            for j in 0..20 {
                pts.push(Vec3::new(i as f32, j as f32, 0.0));
                pts.push(Vec3::new(i as f32, j as f32, 0.0));
            }
        }
        let idx = PointIndex::new(&pts).unwrap();
        let near = idx.nearest_n(Vec3::new(3.1, 4.0, 0.0), 2);
        assert_eq!(
            near.iter().map(|x| x.0 / 2).collect::<Vec<_>>(),
            vec![3 * 20 + 4; 2]
        );
        assert_eq!(idx.within(Vec3::new(3.0, 4.0, 0.0), 1.01).len(), 10);
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
