//! A bounding volume hierarchy over axis-aligned boxes for the ground-truth ray tracer.
//!
//! Built top-down with a binned surface-area heuristic (16 bins along the axis of largest
//! centroid extent, leaves of at most 4 primitives or when no split beats the leaf cost),
//! stored depth-first (a node's left child follows it; the right child's index is stored).
//! The build is single-threaded and uses only comparisons of fixed data, so the tree is the
//! same for the same boxes. Traversal is an explicit stack, nearer child first, and calls back
//! into the caller's exact primitive test with the current closest distance.

use glam::Vec3;

/// An axis-aligned box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    pub lo: Vec3,
    pub hi: Vec3,
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb {
        lo: Vec3::splat(f32::INFINITY),
        hi: Vec3::splat(f32::NEG_INFINITY),
    };
    pub fn grow(&mut self, o: &Aabb) {
        self.lo = self.lo.min(o.lo);
        self.hi = self.hi.max(o.hi);
    }
    pub fn grow_point(&mut self, p: Vec3) {
        self.lo = self.lo.min(p);
        self.hi = self.hi.max(p);
    }
    pub fn area(&self) -> f32 {
        let d = (self.hi - self.lo).max(Vec3::ZERO);
        2.0 * (d.x * d.y + d.y * d.z + d.z * d.x)
    }
    pub fn centre(&self) -> Vec3 {
        (self.lo + self.hi) * 0.5
    }
    /// Entry distance of the ray (origin `o`, reciprocal direction `inv`) within [0, tmax].
    #[inline]
    fn hit(&self, o: Vec3, inv: Vec3, tmax: f32) -> Option<f32> {
        let t0 = (self.lo - o) * inv;
        let t1 = (self.hi - o) * inv;
        let tn = t0.min(t1).max_element().max(0.0);
        let tf = t0.max(t1).min_element().min(tmax);
        (tn <= tf).then_some(tn)
    }
}

#[derive(Debug, Clone, Copy)]
struct Node {
    bb: Aabb,
    /// Leaf: first index into `order`; inner: index of the right child.
    a: u32,
    /// Leaf: primitive count (> 0); inner: 0.
    count: u32,
}

/// The hierarchy: nodes plus the primitive order its leaves index.
#[derive(Debug, Clone)]
pub struct Bvh {
    nodes: Vec<Node>,
    order: Vec<u32>,
}

const BINS: usize = 16;
const LEAF: usize = 4;

impl Bvh {
    /// Builds a hierarchy over `boxes` (primitive `i` has box `boxes[i]`).
    pub fn build(boxes: &[Aabb]) -> Bvh {
        let mut order: Vec<u32> = (0..boxes.len() as u32).collect();
        let centres: Vec<Vec3> = boxes.iter().map(Aabb::centre).collect();
        let mut nodes = Vec::with_capacity(2 * boxes.len() / LEAF + 1);
        if !boxes.is_empty() {
            build_rec(boxes, &centres, &mut order, 0, boxes.len(), &mut nodes, 0);
        }
        Bvh { nodes, order }
    }

    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Closest-hit traversal. `test(prim, tmax)` returns the hit distance if primitive `prim`
    /// is hit closer than `tmax`. Returns the closest (distance, primitive).
    #[inline]
    pub fn closest<F: FnMut(u32, f32) -> Option<f32>>(
        &self,
        o: Vec3,
        d: Vec3,
        tmax: f32,
        mut test: F,
    ) -> Option<(f32, u32)> {
        if self.nodes.is_empty() {
            return None;
        }
        let inv = Vec3::new(1.0 / d.x, 1.0 / d.y, 1.0 / d.z);
        let mut best: Option<(f32, u32)> = None;
        let mut tmax = tmax;
        let mut stack = [0u32; 96];
        let mut sp = 0usize;
        let mut idx = 0u32;
        self.nodes[0].bb.hit(o, inv, tmax)?;
        loop {
            let n = &self.nodes[idx as usize];
            if n.count > 0 {
                for &p in &self.order[n.a as usize..(n.a + n.count) as usize] {
                    if let Some(t) = test(p, tmax) {
                        if t < tmax {
                            tmax = t;
                            best = Some((t, p));
                        }
                    }
                }
            } else {
                let l = idx + 1;
                let r = n.a;
                let hl = self.nodes[l as usize].bb.hit(o, inv, tmax);
                let hr = self.nodes[r as usize].bb.hit(o, inv, tmax);
                match (hl, hr) {
                    (Some(tl), Some(tr)) => {
                        let (near, far) = if tl <= tr { (l, r) } else { (r, l) };
                        if sp < stack.len() {
                            stack[sp] = far;
                            sp += 1;
                        }
                        idx = near;
                        continue;
                    }
                    (Some(_), None) => {
                        idx = l;
                        continue;
                    }
                    (None, Some(_)) => {
                        idx = r;
                        continue;
                    }
                    (None, None) => {}
                }
            }
            // Pop, skipping nodes now farther than the closest hit.
            loop {
                if sp == 0 {
                    return best;
                }
                sp -= 1;
                let c = stack[sp];
                if self.nodes[c as usize].bb.hit(o, inv, tmax).is_some() {
                    idx = c;
                    break;
                }
            }
        }
    }
}

fn build_rec(
    boxes: &[Aabb],
    centres: &[Vec3],
    order: &mut [u32],
    start: usize,
    end: usize,
    nodes: &mut Vec<Node>,
    depth: u32,
) -> u32 {
    let me = nodes.len() as u32;
    let mut bb = Aabb::EMPTY;
    let mut cb = Aabb::EMPTY;
    for &p in &order[start..end] {
        bb.grow(&boxes[p as usize]);
        cb.grow_point(centres[p as usize]);
    }
    nodes.push(Node {
        bb,
        a: start as u32,
        count: (end - start) as u32,
    });
    let count = end - start;
    if count <= LEAF || depth >= 60 {
        return me;
    }
    let ext = cb.hi - cb.lo;
    let axis = if ext.x >= ext.y && ext.x >= ext.z {
        0
    } else if ext.y >= ext.z {
        1
    } else {
        2
    };
    if ext[axis] <= 0.0 {
        return me;
    }
    let scale = BINS as f32 / ext[axis];
    let bin_of =
        |p: u32| (((centres[p as usize][axis] - cb.lo[axis]) * scale) as usize).min(BINS - 1);
    let mut bins = [(Aabb::EMPTY, 0usize); BINS];
    for &p in &order[start..end] {
        let b = bin_of(p);
        bins[b].0.grow(&boxes[p as usize]);
        bins[b].1 += 1;
    }
    // Sweep: cost of splitting after bin i.
    let mut left_area = [0.0f32; BINS];
    let mut left_n = [0usize; BINS];
    let mut acc = Aabb::EMPTY;
    let mut n = 0;
    for i in 0..BINS {
        acc.grow(&bins[i].0);
        n += bins[i].1;
        left_area[i] = acc.area();
        left_n[i] = n;
    }
    let mut acc = Aabb::EMPTY;
    let mut n = 0;
    let mut best = (f32::INFINITY, 0usize);
    for i in (1..BINS).rev() {
        acc.grow(&bins[i].0);
        n += bins[i].1;
        if left_n[i - 1] == 0 || n == 0 {
            continue;
        }
        let cost = left_area[i - 1] * left_n[i - 1] as f32 + acc.area() * n as f32;
        if cost < best.0 {
            best = (cost, i);
        }
    }
    let leaf_cost = bb.area() * count as f32;
    if best.1 == 0 || (best.0 >= leaf_cost && count <= 2 * LEAF) {
        return me;
    }
    // Stable partition: primitives in bins < best.1 first.
    let slice = &mut order[start..end];
    let (mut l, mut r): (Vec<u32>, Vec<u32>) = (Vec::new(), Vec::new());
    for &p in slice.iter() {
        if bin_of(p) < best.1 {
            l.push(p);
        } else {
            r.push(p);
        }
    }
    let mid = start + l.len();
    slice[..l.len()].copy_from_slice(&l);
    slice[l.len()..].copy_from_slice(&r);
    nodes[me as usize].count = 0;
    build_rec(boxes, centres, order, start, mid, nodes, depth + 1);
    let right = build_rec(boxes, centres, order, mid, end, nodes, depth + 1);
    nodes[me as usize].a = right;
    me
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn closest_hit_matches_brute_force() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        // Random spheres, tested exactly.
        let spheres: Vec<(Vec3, f32)> = (0..2000)
            .map(|_| {
                (
                    Vec3::new(rng.gen(), rng.gen(), rng.gen()) * 4.0 - 2.0,
                    rng.gen::<f32>() * 0.05 + 0.01,
                )
            })
            .collect();
        let boxes: Vec<Aabb> = spheres
            .iter()
            .map(|(c, r)| Aabb {
                lo: *c - Vec3::splat(*r),
                hi: *c + Vec3::splat(*r),
            })
            .collect();
        let bvh = Bvh::build(&boxes);
        let hit = |o: Vec3, d: Vec3, i: u32| -> Option<f32> {
            let (c, r) = spheres[i as usize];
            let oc = o - c;
            let b = oc.dot(d);
            let disc = b * b - (oc.dot(oc) - r * r);
            if disc < 0.0 {
                return None;
            }
            let t = -b - disc.sqrt();
            (t > 0.0).then_some(t)
        };
        let mut hits = 0;
        for _ in 0..500 {
            let o = Vec3::new(rng.gen(), rng.gen(), rng.gen()) * 6.0 - 3.0;
            let d = (Vec3::new(rng.gen(), rng.gen(), rng.gen()) - 0.5).normalize();
            let got = bvh.closest(o, d, 100.0, |i, tmax| hit(o, d, i).filter(|t| *t < tmax));
            let want = (0..spheres.len() as u32)
                .filter_map(|i| hit(o, d, i).map(|t| (t, i)))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            assert_eq!(got.map(|g| g.1), want.map(|w| w.1));
            hits += got.is_some() as usize;
        }
        assert!(hits > 20, "too few hits to mean anything: {hits}");
    }
}
