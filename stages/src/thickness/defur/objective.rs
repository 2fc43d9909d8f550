//! The bounded defurring objective (the appendix's equation) and its solve.
//!
//! `E(d) = sum_i c_i (d_i - t_i)^2 + eta sum_i (d_i - b_i)^2
//!        + lambda sum_{(i,j) in E} a_ij (d_i - d_j)^2`
//! subject to `0 <= d_i <= u_i` and `d_i = 0` on the protected set, with
//! `a_ij = 1 / |x_i - x_j|` times 1 within a part and `cross_part_weight`
//! (0.15) across parts.
//!
//! Choices: edge lengths below `1e-6 D` are clamped to that value so that
//! duplicate vertices cannot make a weight infinite; the solve starts from
//! the per-vertex minimiser without the smoothness term,
//! `(c_i t_i + eta b_i) / (c_i + eta)`, clamped to the box (the paper does
//! not say where L-BFGS-B starts; the optimum does not depend on it because
//! the problem is strictly convex for `eta > 0`). Arithmetic is in f64; the
//! objective is evaluated sequentially in a fixed order, so results are
//! bit-for-bit reproducible.

use glam::Vec3;

use super::lbfgsb::{self, Report, Settings, SolverError};

/// A ready-to-solve defurring problem.
#[derive(Debug, Clone)]
pub struct DefurProblem {
    pub c: Vec<f64>,
    pub t: Vec<f64>,
    pub b: Vec<f64>,
    pub eta: f64,
    /// Edges `(i, j, lambda * a_ij)`.
    pub edges: Vec<(u32, u32, f64)>,
    /// Upper bounds (0 for protected vertices).
    pub upper: Vec<f64>,
}

/// Inputs of [`DefurProblem::new`], all per vertex except the constants.
pub struct ProblemInput<'a> {
    pub positions: &'a [Vec3],
    pub part: &'a [u16],
    pub edges: &'a [[u32; 2]],
    pub c: &'a [f32],
    pub t: &'a [f32],
    pub b: &'a [f32],
    pub upper: &'a [f32],
    pub protected: &'a [bool],
    pub eta: f64,
    pub lambda: f64,
    pub cross_part_weight: f64,
    /// Scene length scale D (for the edge-length floor).
    pub scale: f64,
}

impl DefurProblem {
    pub fn new(inp: &ProblemInput<'_>) -> DefurProblem {
        let floor = 1e-6 * inp.scale.max(f64::MIN_POSITIVE);
        let edges = inp
            .edges
            .iter()
            .map(|&[i, j]| {
                let len = (inp.positions[i as usize] - inp.positions[j as usize]).length() as f64;
                let same = inp.part[i as usize] == inp.part[j as usize];
                let w = if same { 1.0 } else { inp.cross_part_weight };
                (i, j, inp.lambda * w / len.max(floor))
            })
            .collect();
        let upper = inp
            .upper
            .iter()
            .zip(inp.protected)
            .map(|(&u, &p)| if p { 0.0 } else { (u as f64).max(0.0) })
            .collect();
        DefurProblem {
            c: inp.c.iter().map(|&x| x as f64).collect(),
            t: inp.t.iter().map(|&x| x as f64).collect(),
            b: inp.b.iter().map(|&x| x as f64).collect(),
            eta: inp.eta,
            edges,
            upper,
        }
    }

    pub fn len(&self) -> usize {
        self.c.len()
    }

    pub fn is_empty(&self) -> bool {
        self.c.is_empty()
    }

    /// Objective value; writes the gradient into `g`.
    pub fn value_grad(&self, d: &[f64], g: &mut [f64]) -> f64 {
        let mut f = 0.0;
        for i in 0..d.len() {
            let rl = d[i] - self.t[i];
            let rb = d[i] - self.b[i];
            f += self.c[i] * rl * rl + self.eta * rb * rb;
            g[i] = 2.0 * self.c[i] * rl + 2.0 * self.eta * rb;
        }
        for &(i, j, w) in &self.edges {
            let (i, j) = (i as usize, j as usize);
            let r = d[i] - d[j];
            f += w * r * r;
            g[i] += 2.0 * w * r;
            g[j] -= 2.0 * w * r;
        }
        f
    }

    /// The clamped per-vertex starting point.
    pub fn start(&self) -> Vec<f64> {
        (0..self.len())
            .map(|i| {
                let den = self.c[i] + self.eta;
                let x = if den > 0.0 {
                    (self.c[i] * self.t[i] + self.eta * self.b[i]) / den
                } else {
                    0.0
                };
                x.clamp(0.0, self.upper[i])
            })
            .collect()
    }

    /// The Hessian diagonal `2 (c_i + eta + sum_j w_ij)`.
    pub fn hessian_diagonal(&self) -> Vec<f64> {
        let mut h: Vec<f64> = (0..self.len())
            .map(|i| 2.0 * (self.c[i] + self.eta))
            .collect();
        for &(i, j, w) in &self.edges {
            h[i as usize] += 2.0 * w;
            h[j as usize] += 2.0 * w;
        }
        h
    }

    /// Solves with the projected L-BFGS, Jacobi-preconditioned when asked.
    pub fn solve(&self, settings: &Settings, precondition: bool) -> Result<Report, SolverError> {
        let lower = vec![0.0; self.len()];
        let h0: Option<Vec<f64>> = precondition.then(|| {
            self.hessian_diagonal()
                .into_iter()
                .map(|h| {
                    if h > 0.0 && h.is_finite() {
                        1.0 / h
                    } else {
                        1.0
                    }
                })
                .collect()
        });
        lbfgsb::minimize_preconditioned(
            |x, g| self.value_grad(x, g),
            &self.start(),
            &lower,
            &self.upper,
            h0.as_deref(),
            settings,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A random small problem on a path + chords graph.
    fn random_problem(n: usize, seed: u64) -> DefurProblem {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let positions: Vec<Vec3> = (0..n)
            .map(|_| Vec3::new(rng.gen(), rng.gen(), rng.gen()))
            .collect();
        let part: Vec<u16> = (0..n).map(|i| (i * 3 / n) as u16).collect();
        let mut edges: Vec<[u32; 2]> = (0..n as u32 - 1).map(|i| [i, i + 1]).collect();
        for _ in 0..n {
            let a = rng.gen_range(0..n as u32);
            let b = rng.gen_range(0..n as u32);
            if a != b {
                edges.push([a.min(b), a.max(b)]);
            }
        }
        let c: Vec<f32> = (0..n)
            .map(|_| if rng.gen_bool(0.3) { 0.0 } else { rng.gen() })
            .collect();
        let t: Vec<f32> = (0..n).map(|_| rng.gen_range(0.0..0.1)).collect();
        let b: Vec<f32> = (0..n).map(|_| rng.gen_range(0.0..0.08)).collect();
        let upper: Vec<f32> = (0..n).map(|_| rng.gen_range(0.0..0.06)).collect();
        let protected: Vec<bool> = (0..n).map(|_| rng.gen_bool(0.1)).collect();
        DefurProblem::new(&ProblemInput {
            positions: &positions,
            part: &part,
            edges: &edges,
            c: &c,
            t: &t,
            b: &b,
            upper: &upper,
            protected: &protected,
            eta: 0.25,
            lambda: 8.0,
            cross_part_weight: 0.15,
            scale: 1.7,
        })
    }

    /// Reference: projected Gauss-Seidel on the exact coordinate minimiser,
    /// run to a fixed point.
    fn reference(p: &DefurProblem) -> Vec<f64> {
        let n = p.len();
        let mut nb: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n];
        for &(i, j, w) in &p.edges {
            nb[i as usize].push((j as usize, w));
            nb[j as usize].push((i as usize, w));
        }
        let mut d = vec![0.0; n];
        for _ in 0..1_000_000 {
            let mut change = 0.0f64;
            for i in 0..n {
                let mut num = p.c[i] * p.t[i] + p.eta * p.b[i];
                let mut den = p.c[i] + p.eta;
                for &(j, w) in &nb[i] {
                    num += w * d[j];
                    den += w;
                }
                let x = (num / den).clamp(0.0, p.upper[i]);
                change = change.max((x - d[i]).abs());
                d[i] = x;
            }
            if change < 1e-16 {
                break;
            }
        }
        d
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let p = random_problem(15, 3);
        let d: Vec<f64> = (0..15).map(|i| 0.01 * i as f64).collect();
        let mut g = vec![0.0; 15];
        p.value_grad(&d, &mut g);
        let mut tmp = vec![0.0; 15];
        for i in 0..15 {
            let h = 1e-6;
            let mut dp = d.clone();
            dp[i] += h;
            let mut dm = d.clone();
            dm[i] -= h;
            let fd = (p.value_grad(&dp, &mut tmp) - p.value_grad(&dm, &mut tmp)) / (2.0 * h);
            assert!(
                (fd - g[i]).abs() < 1e-5 * g[i].abs().max(1.0),
                "{i}: {fd} vs {}",
                g[i]
            );
        }
    }

    #[test]
    fn solve_matches_reference_on_small_problems() {
        for seed in 0..12 {
            let n = 10 + 3 * seed as usize;
            let p = random_problem(n, seed);
            let rep = p.solve(&Settings::default(), seed % 2 == 0).unwrap();
            assert!(
                rep.termination.converged(),
                "seed {seed}: {:?}",
                rep.termination
            );
            let xr = reference(&p);
            let mut g = vec![0.0; n];
            let fr = p.value_grad(&xr, &mut g);
            assert!(
                rep.f <= fr + 1e-10,
                "seed {seed}: f {} vs reference {}",
                rep.f,
                fr
            );
            for (i, (&x, &r)) in rep.x.iter().zip(&xr).enumerate() {
                assert!((x - r).abs() < 1e-5, "seed {seed} d[{i}] = {x} vs {r}");
                assert!(x >= 0.0 && x <= p.upper[i]);
            }
        }
    }
}
