//! The implicit body: a smooth union of primitives, its skin mesh and its fur flow field.
//!
//! The body is a signed distance function (SDF) built from ellipsoids and round cones (capsules
//! with linearly varying radius), folded in preset order with a polynomial smooth minimum
//! (`smin(a, b, k) = min(a, b) - h^2 k / 4`, `h = max(k - |a - b|, 0) / k`); non-fur parts (eyes,
//! nose, pads, horns, hooves) are hard unions so their borders stay sharp. Squashed primitives are
//! evaluated in an unsquashed frame and their distance scaled by the squash factor, a conservative
//! bound that keeps the sign exact.
//!
//! The skin mesh comes from surface nets on a regular grid (one vertex per sign-changing cell at
//! the mean of its edge crossings, one quad per sign-changing grid edge, split along the shorter
//! diagonal), then each vertex is projected onto the zero set with three Newton steps and given
//! the SDF gradient as its normal. The grid spacing is chosen by the stage from the pixel
//! footprint. Each vertex is labelled with the part of the primitive whose own distance is
//! smallest there.
//!
//! The flow field (direction fur grows in) blends the primitives' flow vectors with weights
//! `exp(-(d_k - d_min) / sigma)`, `sigma = 0.04` scene units (2 % of the body length), so the
//! field runs smoothly head to tail and down the legs across part borders.

use glam::{Quat, Vec3};
use rayon::prelude::*;

use super::presets::{Preset, Shape};
use crate::data::mesh::Mesh;

/// Width (scene units) of the flow-field blend.
const FLOW_SIGMA: f32 = 0.04;

#[derive(Debug, Clone)]
pub struct Prim {
    pub shape: Shape,
    pub part: u16,
    pub blend: f32,
    /// (axis, factor, centre).
    pub squash: Option<(Vec3, f32, Vec3)>,
    pub flow: Vec3,
    pub centre: Vec3,
    pub bound: f32,
    pub fur: bool,
}

/// The implicit body in scene units.
#[derive(Debug, Clone)]
pub struct Body {
    pub prims: Vec<Prim>,
    pub part_names: Vec<String>,
}

fn sd_round_cone(p: Vec3, a: Vec3, b: Vec3, r1: f32, r2: f32) -> f32 {
    let ba = b - a;
    let l2 = ba.dot(ba);
    if l2 < 1e-12 {
        return (p - a).length() - r1.max(r2);
    }
    let rr = r1 - r2;
    let a2 = l2 - rr * rr;
    let il2 = 1.0 / l2;
    let pa = p - a;
    let y = pa.dot(ba);
    let z = y - l2;
    let xv = pa * l2 - ba * y;
    let x2 = xv.dot(xv);
    let y2 = y * y * l2;
    let z2 = z * z * l2;
    let k = rr.signum() * rr * rr * x2;
    if z.signum() * a2 * z2 > k {
        return (x2 + z2).sqrt() * il2 - r2;
    }
    if y.signum() * a2 * y2 < k {
        return (x2 + y2).sqrt() * il2 - r1;
    }
    ((x2 * a2 * il2).max(0.0).sqrt() + y * rr) * il2 - r1
}

fn sd_ellipsoid(p: Vec3, c: Vec3, r: Vec3, rot: Quat) -> f32 {
    let q = rot.inverse() * (p - c);
    let k0 = (q / r).length();
    let k1 = (q / (r * r)).length();
    if k1 < 1e-12 {
        return -r.min_element();
    }
    k0 * (k0 - 1.0) / k1
}

fn smin(a: f32, b: f32, k: f32) -> f32 {
    if k <= 0.0 {
        return a.min(b);
    }
    let h = (k - (a - b).abs()).max(0.0) / k;
    a.min(b) - h * h * k * 0.25
}

impl Prim {
    /// A lower bound of [`Prim::sdf`] from the bounding sphere (scaled like a squashed shape).
    #[inline]
    fn lower_bound(&self, p: Vec3) -> f32 {
        let l = (p - self.centre).length() - self.bound;
        match self.squash {
            Some((_, f, _)) if l > 0.0 => l * f.min(1.0),
            _ => l,
        }
    }

    pub fn sdf(&self, p: Vec3) -> f32 {
        let (q, scale) = match self.squash {
            Some((axis, f, c)) => {
                let d = p - c;
                (p + axis * (d.dot(axis) * (1.0 / f - 1.0)), f.min(1.0))
            }
            None => (p, 1.0),
        };
        let d = match &self.shape {
            Shape::Ellipsoid { c, r, rot } => sd_ellipsoid(q, *c, *r, *rot),
            Shape::RoundCone { a, b, ra, rb } => sd_round_cone(q, *a, *b, *ra, *rb),
        };
        d * scale
    }
}

impl Body {
    /// Converts a preset (cm) to scene units (`1 unit = s_cm` cm). Parts with a `direction`
    /// override use it as their flow.
    pub fn from_preset(preset: &Preset, s_cm: f32) -> Body {
        let k = 1.0 / s_cm;
        let prims = preset
            .prims
            .iter()
            .map(|ps| {
                let part = preset.part_index(ps.part).unwrap_or(0) as u16;
                let fp = &preset.parts[part as usize].1;
                let shape = match &ps.shape {
                    Shape::Ellipsoid { c, r, rot } => Shape::Ellipsoid {
                        c: *c * k,
                        r: *r * k,
                        rot: *rot,
                    },
                    Shape::RoundCone { a, b, ra, rb } => Shape::RoundCone {
                        a: *a * k,
                        b: *b * k,
                        ra: ra * k,
                        rb: rb * k,
                    },
                };
                let (centre, bound) = match &shape {
                    Shape::Ellipsoid { c, r, .. } => (*c, r.max_element()),
                    Shape::RoundCone { a, b, ra, rb } => {
                        ((*a + *b) * 0.5, (*b - *a).length() * 0.5 + ra.max(*rb))
                    }
                };
                Prim {
                    shape,
                    part,
                    blend: ps.blend * k,
                    squash: ps.squash.map(|(axis, f)| (axis, f, centre)),
                    flow: fp.direction.unwrap_or(ps.flow),
                    centre,
                    bound,
                    fur: fp.fur,
                }
            })
            .collect();
        Body {
            prims,
            part_names: preset.parts.iter().map(|(n, _)| n.to_string()).collect(),
        }
    }

    /// Signed distance (negative inside).
    ///
    /// A primitive whose bounding-sphere lower bound is at least `d + blend` (with `d` the union
    /// so far) is skipped: there its smooth-min term is exactly zero, so skipping changes nothing.
    pub fn sdf(&self, p: Vec3) -> f32 {
        let Some(first) = self.prims.first() else {
            return f32::INFINITY;
        };
        let mut d = first.sdf(p);
        for pr in &self.prims[1..] {
            if pr.lower_bound(p) >= d + pr.blend.max(0.0) {
                continue;
            }
            d = smin(d, pr.sdf(p), pr.blend);
        }
        d
    }

    /// Like [`Body::sdf`] but returns a cheap positive lower bound when `p` is farther than
    /// `band` from every primitive's bounding sphere.
    fn sdf_banded(&self, p: Vec3, band: f32) -> f32 {
        let lb = self
            .prims
            .iter()
            .map(|pr| (p - pr.centre).length() - pr.bound)
            .fold(f32::INFINITY, f32::min);
        if lb > band {
            lb
        } else {
            self.sdf(p)
        }
    }

    /// The part whose own primitive distance is smallest at `p`.
    pub fn label(&self, p: Vec3) -> u16 {
        let mut best = (f32::INFINITY, 0u16);
        for pr in &self.prims {
            if pr.lower_bound(p) >= best.0 {
                continue;
            }
            let d = pr.sdf(p);
            if d < best.0 {
                best = (d, pr.part);
            }
        }
        best.1
    }

    /// Unit gradient of the SDF (outward normal on the surface) by central differences.
    pub fn gradient(&self, p: Vec3) -> Vec3 {
        let e = 1e-3;
        let g = Vec3::new(
            self.sdf(p + Vec3::X * e) - self.sdf(p - Vec3::X * e),
            self.sdf(p + Vec3::Y * e) - self.sdf(p - Vec3::Y * e),
            self.sdf(p + Vec3::Z * e) - self.sdf(p - Vec3::Z * e),
        );
        g.try_normalize().unwrap_or(Vec3::Y)
    }

    /// The blended fur flow direction at `p` (not yet projected onto the tangent plane).
    pub fn flow(&self, p: Vec3) -> Vec3 {
        let ds: Vec<f32> = self
            .prims
            .iter()
            .map(|pr| if pr.fur { pr.sdf(p) } else { f32::INFINITY })
            .collect();
        let dmin = ds.iter().copied().fold(f32::INFINITY, f32::min);
        if !dmin.is_finite() {
            return -Vec3::X;
        }
        let mut f = Vec3::ZERO;
        for (pr, d) in self.prims.iter().zip(&ds) {
            if d.is_finite() {
                f += pr.flow * (-(d - dmin) / FLOW_SIGMA).exp();
            }
        }
        f.try_normalize().unwrap_or(-Vec3::X)
    }

    /// Axis-aligned bounds of all primitives (conservative).
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for pr in &self.prims {
            lo = lo.min(pr.centre - Vec3::splat(pr.bound));
            hi = hi.max(pr.centre + Vec3::splat(pr.bound));
        }
        (lo, hi)
    }

    /// The skin mesh by surface nets with grid spacing `cell` (scene units).
    pub fn mesh(&self, cell: f32) -> Mesh {
        let (lo, hi) = self.bounds();
        let grid = NetGrid::around(lo, hi, cell);
        let vals = self.sample_grid(&grid);
        let (cell_vert, positions) = cell_vertices(&grid, &vals);
        let triangles = edge_quads(&grid, &vals, &cell_vert, &positions);
        self.project_onto_surface(&positions, triangles, cell)
    }

    /// The banded SDF at every grid node (x fastest, then y, then z), slices in parallel.
    fn sample_grid(&self, grid: &NetGrid) -> Vec<f32> {
        let band = 3.0 * grid.cell + self.prims.iter().map(|p| p.blend).fold(0.0, f32::max);
        (0..=grid.nz)
            .into_par_iter()
            .map(|k| {
                let mut v = Vec::with_capacity((grid.nx + 1) * (grid.ny + 1));
                for j in 0..=grid.ny {
                    for i in 0..=grid.nx {
                        v.push(self.sdf_banded(grid.pos(i, j, k), band));
                    }
                }
                v
            })
            .collect::<Vec<_>>()
            .concat()
    }

    /// The mesh from the net vertices projected onto the zero set (three clamped Newton steps,
    /// kept in place if that fails), with SDF-gradient normals and nearest-primitive labels.
    fn project_onto_surface(
        &self,
        positions: &[Vec3],
        triangles: Vec<[u32; 3]>,
        cell: f32,
    ) -> Mesh {
        let projected: Vec<(Vec3, Vec3, u16)> = positions
            .par_iter()
            .map(|&p0| {
                let mut p = p0;
                for _ in 0..3 {
                    let f = self.sdf(p);
                    let g = self.gradient(p);
                    let step = f.clamp(-cell, cell);
                    p -= g * step;
                }
                if !p.is_finite() || (p - p0).length() > 2.0 * cell {
                    p = p0;
                }
                (p, self.gradient(p), self.label(p))
            })
            .collect();
        Mesh {
            positions: projected.iter().map(|v| v.0).collect(),
            normals: projected.iter().map(|v| v.1).collect(),
            triangles,
            part: projected.iter().map(|v| v.2).collect(),
            part_names: self.part_names.clone(),
        }
    }
}

/// Corner offsets of a grid cell, bit 0 = x, bit 1 = y, bit 2 = z.
const CORNERS: [(usize, usize, usize); 8] = [
    (0, 0, 0),
    (1, 0, 0),
    (0, 1, 0),
    (1, 1, 0),
    (0, 0, 1),
    (1, 0, 1),
    (0, 1, 1),
    (1, 1, 1),
];

/// The twelve cell edges as pairs of `CORNERS` indices.
const EDGES: [(usize, usize); 12] = [
    (0, 1),
    (2, 3),
    (4, 5),
    (6, 7),
    (0, 2),
    (1, 3),
    (4, 6),
    (5, 7),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
];

/// The regular surface-nets grid: `nx * ny * nz` cells of side `cell` from `lo`.
struct NetGrid {
    lo: Vec3,
    cell: f32,
    nx: usize,
    ny: usize,
    nz: usize,
}

impl NetGrid {
    /// The grid covering `lo..hi` with a margin of two cells on every side.
    fn around(lo: Vec3, hi: Vec3, cell: f32) -> NetGrid {
        let lo = lo - Vec3::splat(2.0 * cell);
        let hi = hi + Vec3::splat(2.0 * cell);
        let n = ((hi - lo) / cell).ceil().as_uvec3();
        NetGrid {
            lo,
            cell,
            nx: n.x as usize,
            ny: n.y as usize,
            nz: n.z as usize,
        }
    }

    /// Index of grid node `(i, j, k)` in the node samples.
    fn node(&self, i: usize, j: usize, k: usize) -> usize {
        i + (self.nx + 1) * (j + (self.ny + 1) * k)
    }

    /// Index of cell `(i, j, k)` in the cell-to-vertex map.
    fn cell_id(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.nx * (j + self.ny * k)
    }

    /// Position of grid node `(i, j, k)`.
    fn pos(&self, i: usize, j: usize, k: usize) -> Vec3 {
        self.lo + Vec3::new(i as f32, j as f32, k as f32) * self.cell
    }
}

/// One vertex per sign-changing cell: the cell-to-vertex map (`u32::MAX` where a cell has none)
/// and the vertex positions.
fn cell_vertices(grid: &NetGrid, vals: &[f32]) -> (Vec<u32>, Vec<Vec3>) {
    let mut cell_vert = vec![u32::MAX; grid.nx * grid.ny * grid.nz];
    let mut positions = Vec::new();
    for k in 0..grid.nz {
        for j in 0..grid.ny {
            for i in 0..grid.nx {
                let f: [f32; 8] = CORNERS.map(|(a, b, c)| vals[grid.node(i + a, j + b, k + c)]);
                let Some(offset) = mean_edge_crossing(&f) else {
                    continue;
                };
                cell_vert[grid.cell_id(i, j, k)] = positions.len() as u32;
                positions.push(grid.pos(i, j, k) + offset * grid.cell);
            }
        }
    }
    (cell_vert, positions)
}

/// The mean of a cell's edge zero crossings in cell coordinates, given its corner values; `None`
/// when all corners lie on one side.
fn mean_edge_crossing(f: &[f32; 8]) -> Option<Vec3> {
    let inside = f.iter().filter(|v| **v < 0.0).count();
    if inside == 0 || inside == 8 {
        return None;
    }
    let mut acc = Vec3::ZERO;
    let mut cnt = 0.0;
    for (e0, e1) in EDGES {
        if (f[e0] < 0.0) != (f[e1] < 0.0) {
            let t = f[e0] / (f[e0] - f[e1]);
            let (a0, b0, c0) = CORNERS[e0];
            let (a1, b1, c1) = CORNERS[e1];
            let p0 = Vec3::new(a0 as f32, b0 as f32, c0 as f32);
            let p1 = Vec3::new(a1 as f32, b1 as f32, c1 as f32);
            acc += p0 + (p1 - p0) * t;
            cnt += 1.0;
        }
    }
    Some(acc / cnt)
}

/// The triangles of one quad around every sign-changing interior grid edge, each facing from
/// the inside to the outside.
fn edge_quads(
    grid: &NetGrid,
    vals: &[f32],
    cell_vert: &[u32],
    positions: &[Vec3],
) -> Vec<[u32; 3]> {
    let (nx, ny, nz) = (grid.nx, grid.ny, grid.nz);
    let quad = |cells: [usize; 4]| cells.map(|c| cell_vert[c]);
    let cid = |i: usize, j: usize, k: usize| grid.cell_id(i, j, k);
    let mut triangles: Vec<[u32; 3]> = Vec::new();
    for k in 0..=nz {
        for j in 0..=ny {
            for i in 0..=nx {
                let f0 = vals[grid.node(i, j, k)];
                let s = if f0 < 0.0 { 1.0 } else { -1.0 };
                if i < nx
                    && j >= 1
                    && k >= 1
                    && j < ny
                    && k < nz
                    && (f0 < 0.0) != (vals[grid.node(i + 1, j, k)] < 0.0)
                {
                    let c = quad([
                        cid(i, j - 1, k - 1),
                        cid(i, j, k - 1),
                        cid(i, j, k),
                        cid(i, j - 1, k),
                    ]);
                    push_quad(&mut triangles, c, Vec3::X * s, positions);
                }
                if j < ny
                    && i >= 1
                    && k >= 1
                    && i < nx
                    && k < nz
                    && (f0 < 0.0) != (vals[grid.node(i, j + 1, k)] < 0.0)
                {
                    let c = quad([
                        cid(i - 1, j, k - 1),
                        cid(i, j, k - 1),
                        cid(i, j, k),
                        cid(i - 1, j, k),
                    ]);
                    push_quad(&mut triangles, c, Vec3::Y * s, positions);
                }
                if k < nz
                    && i >= 1
                    && j >= 1
                    && i < nx
                    && j < ny
                    && (f0 < 0.0) != (vals[grid.node(i, j, k + 1)] < 0.0)
                {
                    let c = quad([
                        cid(i - 1, j - 1, k),
                        cid(i, j - 1, k),
                        cid(i, j, k),
                        cid(i - 1, j, k),
                    ]);
                    push_quad(&mut triangles, c, Vec3::Z * s, positions);
                }
            }
        }
    }
    triangles
}

/// Appends quad `c` (vertex ids) as two triangles wound to face `outward` and split along the
/// shorter diagonal; skipped where a cell of the quad has no vertex.
fn push_quad(triangles: &mut Vec<[u32; 3]>, c: [u32; 4], outward: Vec3, positions: &[Vec3]) {
    if c.contains(&u32::MAX) {
        return;
    }
    let p = c.map(|v| positions[v as usize]);
    let nq = (p[2] - p[0]).cross(p[3] - p[1]);
    let c = if nq.dot(outward) < 0.0 {
        [c[3], c[2], c[1], c[0]]
    } else {
        c
    };
    let p = c.map(|v| positions[v as usize]);
    if (p[2] - p[0]).length_squared() <= (p[3] - p[1]).length_squared() {
        triangles.push([c[0], c[1], c[2]]);
        triangles.push([c[0], c[2], c[3]]);
    } else {
        triangles.push([c[0], c[1], c[3]]);
        triangles.push([c[1], c[2], c[3]]);
    }
}

#[cfg(test)]
mod tests {
    use super::super::presets::preset;
    use super::*;

    #[test]
    fn round_cone_sdf_matches_sphere_and_capsule() {
        let a = Vec3::ZERO;
        let b = Vec3::new(2.0, 0.0, 0.0);
        assert!((sd_round_cone(Vec3::new(1.0, 3.0, 0.0), a, b, 1.0, 1.0) - 2.0).abs() < 1e-5);
        assert!((sd_round_cone(Vec3::new(-3.0, 0.0, 0.0), a, b, 1.0, 0.5) - 2.0).abs() < 1e-5);
        assert!((sd_round_cone(Vec3::new(4.0, 0.0, 0.0), a, b, 1.0, 0.5) - 1.5).abs() < 1e-5);
        assert!(sd_round_cone(Vec3::new(1.0, 0.2, 0.0), a, b, 1.0, 0.5) < 0.0);
    }

    #[test]
    fn skin_mesh_is_closed_oriented_and_on_the_surface() {
        let p = preset("cat").unwrap();
        let body = Body::from_preset(&p, p.body_length_cm / 2.0);
        let m = body.mesh(0.04);
        assert!(m.triangles.len() > 1000);
        // Closed: every undirected edge is shared by exactly two triangles, in opposite directions.
        let mut dir: Vec<(u32, u32)> = m
            .triangles
            .iter()
            .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
            .collect();
        dir.sort_unstable();
        let n_dup = dir.windows(2).filter(|w| w[0] == w[1]).count();
        // Surface nets may pinch where a feature is thinner than a cell (ear tips): allow a few.
        assert!(
            n_dup * 1000 <= dir.len(),
            "{n_dup} directed edges appear twice"
        );
        let mut und: Vec<(u32, u32)> = dir.iter().map(|&(a, b)| (a.min(b), a.max(b))).collect();
        und.sort_unstable();
        let mut i = 0;
        let mut bad = 0;
        while i < und.len() {
            let mut j = i;
            while j < und.len() && und[j] == und[i] {
                j += 1;
            }
            if j - i != 2 {
                bad += 1;
            }
            i = j;
        }
        assert!(
            bad * 1000 <= und.len(),
            "{bad} non-manifold edges of {}",
            und.len()
        );
        // Outward: signed volume positive; vertices on the zero set.
        let vol: f32 = m
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| m.positions[i as usize]);
                a.dot(b.cross(c)) / 6.0
            })
            .sum();
        assert!(vol > 0.0);
        let max_d = m
            .positions
            .iter()
            .map(|p| body.sdf(*p).abs())
            .fold(0.0f32, f32::max);
        assert!(max_d < 0.01, "max |sdf| on the mesh {max_d}");
        // Every part is present on the mesh.
        for k in 0..m.part_names.len() {
            assert!(
                m.part.iter().any(|&q| q as usize == k),
                "part {} missing",
                m.part_names[k]
            );
        }
    }
}
