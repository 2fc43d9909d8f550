//! The decoder `D_psi` (mean + basis . z, fine-tuned) and the paper's
//! placement equation, each with its vector-Jacobian product.
//!
//! Placement (method.md section 7):
//! `s_k = r + l T (s^_k - s^_1) / (s_cm (a + eps))` with `a` the decoded
//! polyline's arc length. Our roots already carry their length in scene units
//! (`Roots::length` = `l_p / s_cm`), so the code uses `len = l / s_cm`
//! directly. `T` is the root's orthonormal frame with columns
//! (tangent, bitangent, normal), the canonical frame of the basis. With
//! `eps = 1e-6` (the decoded strands have unit arc length to start with) every
//! placed strand has arc length `len * a / (a + eps)`: its target to 1e-6
//! relative, whatever the code `z` or the fine-tuned decoder produce.

use glam::{Mat3, Vec3};

/// The `eps` of the placement equation.
pub const PLACEMENT_EPS: f32 = 1e-6;

/// The fine-tuned decoder psi: a mean strand and `K` components, all in the
/// canonical root frame, stored flat (`mean` then each component, `L` points
/// of 3 floats each) so one Adam state covers it.
#[derive(Debug, Clone, PartialEq)]
pub struct Decoder {
    pub points: usize,
    pub k: usize,
    pub params: Vec<f32>,
}

impl Decoder {
    /// From a mean (`L` points) and components (`K` of `L` points each).
    pub fn new(mean: &[Vec3], components: &[Vec<Vec3>]) -> Self {
        let points = mean.len();
        let mut params = Vec::with_capacity(points * 3 * (components.len() + 1));
        for p in mean {
            params.extend_from_slice(&p.to_array());
        }
        for c in components {
            for p in c {
                params.extend_from_slice(&p.to_array());
            }
        }
        Decoder {
            points,
            k: components.len(),
            params,
        }
    }

    #[inline]
    fn at(&self, block: usize, j: usize) -> Vec3 {
        let o = (block * self.points + j) * 3;
        Vec3::new(self.params[o], self.params[o + 1], self.params[o + 2])
    }

    /// The mean strand (the decoding of `z = 0`).
    pub fn mean(&self) -> Vec<Vec3> {
        (0..self.points).map(|j| self.at(0, j)).collect()
    }

    /// Decodes `z` (`K` values) into `out` (`L` points).
    pub fn decode(&self, z: &[f32], out: &mut [Vec3]) {
        for (j, o) in out.iter_mut().enumerate().take(self.points) {
            let mut p = self.at(0, j);
            for (k, zk) in z.iter().enumerate().take(self.k) {
                p += *zk * self.at(k + 1, j);
            }
            *o = p;
        }
    }

    /// Given `g` = d loss / d decoded points, writes d loss / d z into `gz`
    /// and, when `gpsi` is given, adds d loss / d psi to it.
    pub fn backward(&self, z: &[f32], g: &[Vec3], gz: &mut [f32], gpsi: Option<&mut [f32]>) {
        for (k, gzk) in gz.iter_mut().enumerate().take(self.k) {
            *gzk = (0..self.points).map(|j| self.at(k + 1, j).dot(g[j])).sum();
        }
        if let Some(gp) = gpsi {
            for (j, gj) in g.iter().enumerate().take(self.points) {
                let o = j * 3;
                gp[o] += gj.x;
                gp[o + 1] += gj.y;
                gp[o + 2] += gj.z;
                for (k, zk) in z.iter().enumerate().take(self.k) {
                    let o = ((k + 1) * self.points + j) * 3;
                    gp[o] += zk * gj.x;
                    gp[o + 1] += zk * gj.y;
                    gp[o + 2] += zk * gj.z;
                }
            }
        }
    }
}

/// The root frame as a matrix with columns (tangent, bitangent, normal).
pub fn frame(tangent: Vec3, bitangent: Vec3, normal: Vec3) -> Mat3 {
    Mat3::from_cols(tangent, bitangent, normal)
}

/// Arc length of a polyline.
pub fn arc_length(p: &[Vec3]) -> f32 {
    p.windows(2).map(|w| (w[1] - w[0]).length()).sum()
}

/// Places a decoded local strand at `root` with frame `t` and length `len`
/// (scene units), writing world points into `out`.
pub fn place(local: &[Vec3], root: Vec3, t: Mat3, len: f32, out: &mut [Vec3]) {
    let a = arc_length(local);
    let scale = len / (a + PLACEMENT_EPS);
    let s1 = local[0];
    for (o, s) in out.iter_mut().zip(local) {
        *o = root + scale * (t * (*s - s1));
    }
}

/// Vector-Jacobian product of [`place`] with respect to the local points:
/// given `g` = d loss / d world points, writes d loss / d local points into `gl`.
pub fn place_backward(local: &[Vec3], t: Mat3, len: f32, g: &[Vec3], gl: &mut [Vec3]) {
    let n = local.len();
    let a = arc_length(local);
    let inv = 1.0 / (a + PLACEMENT_EPS);
    let tt = t.transpose();
    let s1 = local[0];
    // h_k = d loss / d q_k with q_k = (s^_k - s^_1) / (a + eps).
    let mut sum_h = Vec3::ZERO;
    let mut g_a = 0.0f32;
    for k in 0..n {
        let h = len * (tt * g[k]);
        gl[k] = h * inv;
        sum_h += h;
        g_a -= h.dot(local[k] - s1) * inv * inv;
    }
    // The root's own term: q_k depends on -s^_1 for every k.
    gl[0] -= sum_h * inv;
    // Through the arc length: da/ds^_j = e_{j-1} - e_j (unit segment directions).
    for j in 0..n.saturating_sub(1) {
        let d = local[j + 1] - local[j];
        let e = d.try_normalize().unwrap_or(Vec3::ZERO);
        gl[j + 1] += g_a * e;
        gl[j] -= g_a * e;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_frame(rng: &mut ChaCha8Rng) -> Mat3 {
        let n = Vec3::new(rng.gen(), rng.gen(), rng.gen()).normalize() - Vec3::splat(0.2);
        let n = n.normalize();
        let t = n.any_orthonormal_vector();
        frame(t, n.cross(t), n)
    }

    #[test]
    fn placed_strands_have_exactly_their_length() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for _ in 0..50 {
            let local: Vec<Vec3> = (0..12)
                .map(|_| Vec3::new(rng.gen(), rng.gen(), rng.gen()) * 3.0)
                .collect();
            let len = rng.gen_range(0.01..2.0f32);
            let root = Vec3::new(rng.gen(), rng.gen(), rng.gen());
            let mut out = vec![Vec3::ZERO; 12];
            place(&local, root, random_frame(&mut rng), len, &mut out);
            assert!((arc_length(&out) - len).abs() <= 1e-5 * len.max(1.0));
            assert!((out[0] - root).length() < 1e-6);
        }
    }

    #[test]
    fn placement_gradient_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let l = 6;
        let local: Vec<Vec3> = (0..l)
            .map(|i| Vec3::new(rng.gen(), rng.gen(), i as f32 + rng.gen::<f32>()))
            .collect();
        let t = random_frame(&mut rng);
        let len = 0.7;
        let w: Vec<Vec3> = (0..l)
            .map(|_| Vec3::new(rng.gen(), rng.gen(), rng.gen()) - 0.5)
            .collect();
        let f = |loc: &[Vec3]| -> f64 {
            let mut out = vec![Vec3::ZERO; l];
            place(loc, Vec3::ONE, t, len, &mut out);
            out.iter().zip(&w).map(|(a, b)| a.dot(*b) as f64).sum()
        };
        let mut gl = vec![Vec3::ZERO; l];
        place_backward(&local, t, len, &w, &mut gl);
        let h = 1e-3;
        for j in 0..l {
            for c in 0..3 {
                let mut p = local.clone();
                p[j][c] += h;
                let fp = f(&p);
                p[j][c] -= 2.0 * h;
                let fm = f(&p);
                let fd = (fp - fm) / (2.0 * h as f64);
                assert!(
                    (fd - gl[j][c] as f64).abs() < 2e-3,
                    "point {j} axis {c}: fd {fd} vs {}",
                    gl[j][c]
                );
            }
        }
    }

    #[test]
    // Finite differences perturb parameter i and read gradient i.
    #[allow(clippy::needless_range_loop)]
    fn decoder_gradient_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let l = 5;
        let mean: Vec<Vec3> = (0..l).map(|i| Vec3::Z * i as f32).collect();
        let comps: Vec<Vec<Vec3>> = (0..3)
            .map(|_| {
                (0..l)
                    .map(|_| Vec3::new(rng.gen(), rng.gen(), rng.gen()))
                    .collect()
            })
            .collect();
        let mut dec = Decoder::new(&mean, &comps);
        let z = [0.3f32, -0.2, 0.5];
        let w: Vec<Vec3> = (0..l)
            .map(|_| Vec3::new(rng.gen(), rng.gen(), rng.gen()))
            .collect();
        let f = |dec: &Decoder, z: &[f32]| -> f64 {
            let mut out = vec![Vec3::ZERO; l];
            dec.decode(z, &mut out);
            out.iter().zip(&w).map(|(a, b)| a.dot(*b) as f64).sum()
        };
        let mut gz = [0.0f32; 3];
        let mut gp = vec![0.0f32; dec.params.len()];
        dec.backward(&z, &w, &mut gz, Some(&mut gp));
        let h = 1e-2f32;
        for k in 0..3 {
            let mut zp = z;
            zp[k] += h;
            let mut zm = z;
            zm[k] -= h;
            let fd = (f(&dec, &zp) - f(&dec, &zm)) / (2.0 * h as f64);
            assert!((fd - gz[k] as f64).abs() < 1e-3);
        }
        for i in 0..dec.params.len() {
            let o = dec.params[i];
            dec.params[i] = o + h;
            let fp = f(&dec, &z);
            dec.params[i] = o - h;
            let fm = f(&dec, &z);
            dec.params[i] = o;
            let fd = (fp - fm) / (2.0 * h as f64);
            assert!((fd - gp[i] as f64).abs() < 1e-3, "param {i}");
        }
    }
}
