//! A projected limited-memory BFGS for box-constrained smooth minimisation,
//! stopping by L-BFGS-B's rules.
//!
//! The paper solves the defurring problem with SciPy's L-BFGS-B
//! (`ftol = 1e-13`, `gtol = 1e-7`, `maxcor = 8`, at most 2,500 iterations).
//! No mature pure-Rust L-BFGS-B exists (see prior-art.md), so this module
//! implements the simpler projected variant and keeps L-BFGS-B's stopping
//! rules exactly:
//!
//! - **gtol**: stop when the infinity norm of the projected gradient
//!   `P(x - g) - x` is at most `gtol` (L-BFGS-B's `pgtol`).
//! - **ftol**: stop when the relative reduction
//!   `(f_k - f_{k+1}) / max(|f_k|, |f_{k+1}|, 1)` is at most `ftol`
//!   (SciPy passes `factr = ftol / eps` and the Fortran code tests
//!   `factr * eps`, i.e. exactly this).
//! - at most `max_iterations` iterations.
//!
//! Each iteration:
//! 1. The *free set*: every variable except those at a bound whose gradient
//!    pushes them outward, and those with equal bounds (fixed).
//! 2. A quasi-Newton direction from the two-loop recursion over the last
//!    `memory` pairs `(s, y)`, with all inner products restricted to the free
//!    set (the active variables are held, as in Kim, Sra and Dhillon's
//!    projected quasi-Newton method); the initial Hessian scale is
//!    `s.y / y.y` of the newest pair. Non-free components are zeroed. If the
//!    result is not a descent direction the memory is dropped and the
//!    (free) steepest descent direction is used.
//! 3. A backtracking line search along the projected path
//!    `x(a) = P(x + a d)` with the Armijo condition
//!    `f(x(a)) <= f(x) + 1e-4 g.(x(a) - x)`, starting from `a = 1`
//!    (`1 / ||d||_2` on the first iteration, as L-BFGS-B does), shrinking
//!    by safeguarded quadratic interpolation, at most 20 trials (SciPy's
//!    `maxls`).
//! 4. The pair `(s, y)` is stored only when `s.y > eps y.y` (L-BFGS-B's
//!    curvature test), so the inverse Hessian approximation stays positive
//!    definite.
//!
//! The solver is single-threaded and deterministic: the same inputs give the
//! same iterates bit for bit. The objective callback may itself be parallel
//! as long as its own reductions are ordered.

use std::collections::VecDeque;

/// Solver settings. The defaults are the paper's.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// Number of stored correction pairs (`maxcor`).
    pub memory: usize,
    /// Iteration limit.
    pub max_iterations: usize,
    /// Relative function reduction tolerance.
    pub ftol: f64,
    /// Projected gradient infinity-norm tolerance.
    pub gtol: f64,
    /// Maximum function evaluations per line search (`maxls`).
    pub max_line_search: usize,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            memory: 8,
            max_iterations: 2500,
            ftol: 1e-13,
            gtol: 1e-7,
            max_line_search: 20,
        }
    }
}

/// Why the solver stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Termination {
    /// Projected gradient infinity norm at most `gtol`.
    ProjectedGradient,
    /// Relative reduction at most `ftol`.
    RelativeReduction,
    /// Iteration limit reached.
    MaxIterations,
    /// No sufficient decrease along steepest descent (numerically converged
    /// or the objective is inconsistent with its gradient).
    LineSearchFailed,
}

impl Termination {
    pub fn as_str(self) -> &'static str {
        match self {
            Termination::ProjectedGradient => "projected_gradient_below_gtol",
            Termination::RelativeReduction => "relative_reduction_below_ftol",
            Termination::MaxIterations => "max_iterations",
            Termination::LineSearchFailed => "line_search_failed",
        }
    }
    /// Whether the stop is one of the two convergence tests.
    pub fn converged(self) -> bool {
        matches!(
            self,
            Termination::ProjectedGradient | Termination::RelativeReduction
        )
    }
}

/// The result of a solve.
#[derive(Debug, Clone)]
pub struct Report {
    pub x: Vec<f64>,
    pub f: f64,
    pub iterations: usize,
    pub evaluations: usize,
    pub termination: Termination,
    /// Infinity norm of the projected gradient at `x`.
    pub projected_gradient: f64,
}

/// Bad solver input.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SolverError {
    #[error("{what} has length {found}, expected {expected}")]
    Length {
        what: &'static str,
        found: usize,
        expected: usize,
    },
    #[error(
        "bounds of variable {index} are invalid: lower {lower} > upper {upper} or not numbers"
    )]
    Bounds {
        index: usize,
        lower: f64,
        upper: f64,
    },
    #[error("invalid settings: {0}")]
    Settings(&'static str),
    #[error("preconditioner entry {index} is not a positive finite number")]
    Preconditioner { index: usize },
    #[error("objective or gradient is not finite at iteration {iteration}")]
    NonFinite { iteration: usize },
}

fn project(x: &mut [f64], lower: &[f64], upper: &[f64]) {
    for ((xi, &l), &u) in x.iter_mut().zip(lower).zip(upper) {
        *xi = xi.clamp(l, u);
    }
}

fn projected_gradient_norm(x: &[f64], g: &[f64], lower: &[f64], upper: &[f64]) -> f64 {
    let mut m = 0.0f64;
    for i in 0..x.len() {
        let p = (x[i] - g[i]).clamp(lower[i], upper[i]) - x[i];
        m = m.max(p.abs());
    }
    m
}

/// Sum of `a_i b_i m_i` (`m` is the 0/1 free mask); branch-free so it vectorises.
fn masked_dot(a: &[f64], b: &[f64], m: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (ac, bc, mc) = (a.chunks_exact(4), b.chunks_exact(4), m.chunks_exact(4));
    let (ar, br, mr) = (ac.remainder(), bc.remainder(), mc.remainder());
    for ((x, y), z) in ac.zip(bc).zip(mc) {
        for k in 0..4 {
            acc[k] += x[k] * y[k] * z[k];
        }
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for ((x, y), z) in ar.iter().zip(br).zip(mr) {
        s += x * y * z;
    }
    s
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn all_finite(v: &[f64]) -> bool {
    v.iter().all(|x| x.is_finite())
}

/// Minimises `f` over the box `lower <= x <= upper` starting from `x0`
/// (projected onto the box first). `f(x, g)` returns the objective and
/// writes its gradient into `g`. Infinite bounds are allowed.
pub fn minimize<F>(
    f: F,
    x0: &[f64],
    lower: &[f64],
    upper: &[f64],
    settings: &Settings,
) -> Result<Report, SolverError>
where
    F: FnMut(&[f64], &mut [f64]) -> f64,
{
    minimize_preconditioned(f, x0, lower, upper, None, settings)
}

/// The start point `x0` projected onto the box, with its gradient and
/// objective value (one evaluation); non-finite values are an error.
fn evaluate_start<F>(
    f: &mut F,
    x0: &[f64],
    lower: &[f64],
    upper: &[f64],
) -> Result<(Vec<f64>, Vec<f64>, f64), SolverError>
where
    F: FnMut(&[f64], &mut [f64]) -> f64,
{
    if !all_finite(x0) {
        return Err(SolverError::NonFinite { iteration: 0 });
    }
    let mut x = x0.to_vec();
    project(&mut x, lower, upper);
    let mut g = vec![0.0; x0.len()];
    let fx = f(&x, &mut g);
    if !fx.is_finite() || !all_finite(&g) {
        return Err(SolverError::NonFinite { iteration: 0 });
    }
    Ok((x, g, fx))
}

/// [`minimize`] with an optional diagonal preconditioner `h0`: positive
/// per-variable scales used as the initial inverse Hessian of the two-loop
/// recursion (`H0 = gamma diag(h0)`, `gamma = s.y / (y.diag(h0).y)`), and
/// for the first (steepest descent) step. This is L-BFGS on the variables
/// `x_i / sqrt(h0_i)`; a diagonal change of variables keeps the feasible set
/// a box, so projections, the free set and the stopping tests (which are
/// evaluated on the original variables) are unchanged. `h0 = 1 / Hessian
/// diagonal` (Jacobi) removes the dependence on edge-weight scales.
pub fn minimize_preconditioned<F>(
    mut f: F,
    x0: &[f64],
    lower: &[f64],
    upper: &[f64],
    h0: Option<&[f64]>,
    settings: &Settings,
) -> Result<Report, SolverError>
where
    F: FnMut(&[f64], &mut [f64]) -> f64,
{
    let n = x0.len();
    let h0 = check_inputs(x0, lower, upper, h0, settings)?;
    let preconditioned = h0.iter().any(|&v| v != 1.0);
    let (mut x, mut g, mut fx) = evaluate_start(&mut f, x0, lower, upper)?;
    let mut evaluations = 1usize;

    // Correction pairs (s, y), newest last.
    let mut pairs: VecDeque<(Vec<f64>, Vec<f64>)> = VecDeque::with_capacity(settings.memory);
    let mut free = vec![1.0f64; n];
    // Restricted curvature `s.y` of each pair over the current free set,
    // recomputed only when the free set changes (NaN: needs recomputing).
    let mut curv: VecDeque<f64> = VecDeque::with_capacity(settings.memory);
    let mut d = vec![0.0; n];
    let mut alphas = vec![0.0; settings.memory];
    let mut rhos = vec![0.0; settings.memory];
    let mut xn = vec![0.0; n];
    let mut gn = vec![0.0; n];
    let mut iterations = 0usize;

    let finish = |x: Vec<f64>, f: f64, g: &[f64], it: usize, ev: usize, t: Termination| Report {
        projected_gradient: projected_gradient_norm(&x, g, lower, upper),
        x,
        f,
        iterations: it,
        evaluations: ev,
        termination: t,
    };

    loop {
        if projected_gradient_norm(&x, &g, lower, upper) <= settings.gtol {
            let t = Termination::ProjectedGradient;
            return Ok(finish(x, fx, &g, iterations, evaluations, t));
        }
        if iterations >= settings.max_iterations {
            let t = Termination::MaxIterations;
            return Ok(finish(x, fx, &g, iterations, evaluations, t));
        }

        update_free_set(&x, &g, lower, upper, &mut free, &mut curv, &pairs);

        // Direction and line search; retried once with steepest descent.
        let mut accepted: Option<f64> = None;
        for attempt in 0..2 {
            let use_memory = attempt == 0 && !pairs.is_empty();
            for i in 0..n {
                d[i] = -g[i] * free[i];
            }
            if !(use_memory && two_loop(&mut d, &pairs, &curv, &free, &h0, &mut alphas, &mut rhos))
            {
                // No memory, or curvature lost on the free set: (scaled) steepest descent.
                steepest_descent(&mut d, &g, &free, &h0);
            }
            let gd = dot(&g, &d);
            let dnorm = dot(&d, &d).sqrt();
            if !(gd < 0.0) || dnorm == 0.0 {
                if use_memory {
                    pairs.clear();
                    curv.clear();
                    continue;
                }
                break;
            }
            let step = if pairs.is_empty() && !preconditioned {
                (1.0 / dnorm).min(1.0)
            } else {
                1.0
            };
            accepted = line_search(
                &mut f,
                (&x, &g, fx),
                (&d, step),
                (lower, upper),
                (&mut xn, &mut gn),
                settings.max_line_search,
                &mut evaluations,
            );
            if accepted.is_some() || !use_memory {
                break;
            }
            pairs.clear();
            curv.clear();
        }
        let Some(fnew) = accepted else {
            // No decrease even along projected steepest descent: converged to
            // rounding or the gradient is inconsistent with the objective.
            let t = Termination::LineSearchFailed;
            return Ok(finish(x, fx, &g, iterations, evaluations, t));
        };

        push_pair(&mut pairs, &mut curv, (&x, &xn), (&g, &gn), settings.memory);
        iterations += 1;
        let rel = (fx - fnew) / fx.abs().max(fnew.abs()).max(1.0);
        std::mem::swap(&mut x, &mut xn);
        std::mem::swap(&mut g, &mut gn);
        fx = fnew;
        if rel <= settings.ftol {
            let t = Termination::RelativeReduction;
            return Ok(finish(x, fx, &g, iterations, evaluations, t));
        }
    }
}

/// The correction pair `(x_new - x, g_new - g)` when its curvature is
/// positive, reusing the oldest pair's storage when the memory is full.
fn push_pair(
    pairs: &mut VecDeque<(Vec<f64>, Vec<f64>)>,
    curv: &mut VecDeque<f64>,
    (x, xn): (&[f64], &[f64]),
    (g, gn): (&[f64], &[f64]),
    memory: usize,
) {
    let n = x.len();
    let (mut s, mut y) = if pairs.len() == memory {
        curv.pop_front();
        pairs
            .pop_front()
            .unwrap_or_else(|| (vec![0.0; n], vec![0.0; n]))
    } else {
        (vec![0.0; n], vec![0.0; n])
    };
    for i in 0..n {
        s[i] = xn[i] - x[i];
        y[i] = gn[i] - g[i];
    }
    if dot(&s, &y) > f64::EPSILON * dot(&y, &y) {
        pairs.push_back((s, y));
        curv.push_back(f64::NAN);
    }
}

/// `d = -g h0` on the free set, zero elsewhere.
fn steepest_descent(d: &mut [f64], g: &[f64], free: &[f64], h0: &[f64]) {
    for i in 0..d.len() {
        d[i] = -g[i] * free[i] * h0[i];
    }
}

/// Checks lengths, bounds and settings; the preconditioner (ones without one).
fn check_inputs(
    x0: &[f64],
    lower: &[f64],
    upper: &[f64],
    h0: Option<&[f64]>,
    settings: &Settings,
) -> Result<Vec<f64>, SolverError> {
    let n = x0.len();
    let mut lens = vec![("lower bounds", lower.len()), ("upper bounds", upper.len())];
    if let Some(h) = h0 {
        lens.push(("preconditioner", h.len()));
    }
    for (what, len) in lens {
        if len != n {
            return Err(SolverError::Length {
                what,
                found: len,
                expected: n,
            });
        }
    }
    for i in 0..n {
        let (l, u) = (lower[i], upper[i]);
        if l.is_nan() || u.is_nan() || l > u {
            return Err(SolverError::Bounds {
                index: i,
                lower: l,
                upper: u,
            });
        }
    }
    if settings.memory == 0 {
        return Err(SolverError::Settings("memory must be at least 1"));
    }
    if settings.max_line_search == 0 {
        return Err(SolverError::Settings("max_line_search must be at least 1"));
    }
    if !(settings.ftol >= 0.0 && settings.gtol >= 0.0) {
        return Err(SolverError::Settings("tolerances must be non-negative"));
    }
    Ok(match h0 {
        Some(h) => {
            if let Some(i) = h.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
                return Err(SolverError::Preconditioner { index: i });
            }
            h.to_vec()
        }
        None => vec![1.0; n],
    })
}

/// The free set (variables not held at a bound by the gradient) as a 0/1
/// mask, and the pairs' restricted curvature when it changed.
fn update_free_set(
    x: &[f64],
    g: &[f64],
    lower: &[f64],
    upper: &[f64],
    free: &mut [f64],
    curv: &mut VecDeque<f64>,
    pairs: &VecDeque<(Vec<f64>, Vec<f64>)>,
) {
    let n = x.len();
    let mut changed = false;
    for i in 0..n {
        let at_lower = x[i] <= lower[i] && g[i] > 0.0;
        let at_upper = x[i] >= upper[i] && g[i] < 0.0;
        let is_free = lower[i] < upper[i] && !at_lower && !at_upper;
        let m = if is_free { 1.0 } else { 0.0 };
        changed |= free[i] != m;
        free[i] = m;
    }
    for (c, (s, y)) in curv.iter_mut().zip(pairs) {
        if changed || c.is_nan() {
            let sy = masked_dot(s, y, free);
            *c = if sy > f64::EPSILON * masked_dot(y, y, free) {
                sy
            } else {
                -1.0
            };
        }
    }
}

/// Backtracking along the projected path `P(x + a d)` from step `step`
/// (the direction and first step):
/// the first point with sufficient decrease (Armijo on the path, `1e-4`),
/// written into `xn`/`gn`, and its objective; `None` after `max_steps`
/// evaluations without one.
fn line_search<F>(
    f: &mut F,
    (x, g, fx): (&[f64], &[f64], f64),
    (d, mut step): (&[f64], f64),
    (lower, upper): (&[f64], &[f64]),
    (xn, gn): (&mut [f64], &mut [f64]),
    max_steps: usize,
    evaluations: &mut usize,
) -> Option<f64>
where
    F: FnMut(&[f64], &mut [f64]) -> f64,
{
    let n = x.len();
    for _ in 0..max_steps {
        for i in 0..n {
            xn[i] = (x[i] + step * d[i]).clamp(lower[i], upper[i]);
        }
        let fnew = f(xn, gn);
        *evaluations += 1;
        let mut dec = 0.0;
        for i in 0..n {
            dec += g[i] * (xn[i] - x[i]);
        }
        if fnew.is_finite() && all_finite(gn) && dec < 0.0 && fnew <= fx + 1e-4 * dec {
            return Some(fnew);
        }
        // Safeguarded quadratic interpolation of phi(a) along the path.
        let slope = dec / step;
        let denom = 2.0 * (fnew - fx - slope * step);
        let next = if fnew.is_finite() && denom > 0.0 && slope < 0.0 {
            -slope * step * step / denom
        } else {
            0.5 * step
        };
        step = next.clamp(0.1 * step, 0.5 * step);
    }
    None
}

/// The two-loop recursion on `d` (holding the masked negative gradient),
/// with inner products over the free set and initial inverse Hessian
/// `gamma diag(h0)`. False when a stored pair has no positive curvature on
/// the free set.
fn two_loop(
    d: &mut [f64],
    pairs: &VecDeque<(Vec<f64>, Vec<f64>)>,
    curv: &VecDeque<f64>,
    free: &[f64],
    h0: &[f64],
    alphas: &mut [f64],
    rhos: &mut [f64],
) -> bool {
    let n = d.len();
    for (j, &sy) in curv.iter().enumerate() {
        if !(sy > 0.0) {
            return false;
        }
        rhos[j] = 1.0 / sy;
    }
    for (j, (s, y)) in pairs.iter().enumerate().rev() {
        let a = rhos[j] * masked_dot(s, d, free);
        alphas[j] = a;
        for i in 0..n {
            d[i] -= a * y[i] * free[i];
        }
    }
    let y = &pairs[pairs.len() - 1].1;
    let mut yhy = 0.0;
    for i in 0..n {
        yhy += y[i] * y[i] * h0[i] * free[i];
    }
    if !(yhy > 0.0) {
        return false;
    }

    let gamma = curv[curv.len() - 1] / yhy;
    for i in 0..n {
        d[i] *= gamma * h0[i];
    }
    for (j, (s, y)) in pairs.iter().enumerate() {
        let c = alphas[j] - rhos[j] * masked_dot(y, d, free);
        for i in 0..n {
            d[i] += c * s[i] * free[i];
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A random strictly convex box QP: f = 0.5 x'Qx - r'x.
    struct Qp {
        q: Vec<Vec<f64>>,
        r: Vec<f64>,
        lower: Vec<f64>,
        upper: Vec<f64>,
    }

    fn random_qp(n: usize, seed: u64) -> Qp {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let a: Vec<Vec<f64>> = (0..n)
            .map(|_| (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect())
            .collect();
        let mut q = vec![vec![0.0; n]; n];
        for i in 0..n {
            for j in 0..n {
                q[i][j] = (0..n).map(|k| a[k][i] * a[k][j]).sum::<f64>();
            }
            q[i][i] += 0.05;
        }
        let r = (0..n).map(|_| rng.gen_range(-3.0..3.0)).collect();
        let lower: Vec<f64> = (0..n).map(|_| rng.gen_range(-1.0..0.0)).collect();
        let upper: Vec<f64> = lower.iter().map(|l| l + rng.gen_range(0.0..1.5)).collect();
        Qp { q, r, lower, upper }
    }

    fn qp_eval(p: &Qp, x: &[f64], g: &mut [f64]) -> f64 {
        let n = x.len();
        let mut f = 0.0;
        for i in 0..n {
            let qx: f64 = (0..n).map(|j| p.q[i][j] * x[j]).sum();
            g[i] = qx - p.r[i];
            f += 0.5 * x[i] * qx - p.r[i] * x[i];
        }
        f
    }

    /// Reference: projected Gauss-Seidel, exact for strictly convex box QPs.
    fn reference_pgs(p: &Qp) -> Vec<f64> {
        let n = p.r.len();
        let mut x = vec![0.0; n];
        for _ in 0..200_000 {
            let mut change = 0.0f64;
            for i in 0..n {
                let off: f64 = (0..n).filter(|&j| j != i).map(|j| p.q[i][j] * x[j]).sum();
                let xi = ((p.r[i] - off) / p.q[i][i]).clamp(p.lower[i], p.upper[i]);
                change = change.max((xi - x[i]).abs());
                x[i] = xi;
            }
            if change < 1e-15 {
                break;
            }
        }
        x
    }

    #[test]
    fn matches_reference_on_random_box_qps() {
        for seed in 0..20 {
            let n = 3 + (seed as usize % 10);
            let p = random_qp(n, seed);
            let x0 = vec![0.0; n];
            let rep = minimize(
                |x, g| qp_eval(&p, x, g),
                &x0,
                &p.lower,
                &p.upper,
                &Settings::default(),
            )
            .unwrap();
            assert!(
                rep.termination.converged(),
                "seed {seed}: {:?}",
                rep.termination
            );
            let xr = reference_pgs(&p);
            let mut g = vec![0.0; n];
            let fr = qp_eval(&p, &xr, &mut g);
            assert!(
                rep.f <= fr + 1e-9 * fr.abs().max(1.0),
                "seed {seed}: {} vs {}",
                rep.f,
                fr
            );
            for (i, (&x, &r)) in rep.x.iter().zip(&xr).enumerate() {
                assert!((x - r).abs() < 1e-4, "seed {seed} x[{i}] {x} vs {r}");
                assert!(x >= p.lower[i] && x <= p.upper[i]);
            }
        }
    }

    #[test]
    fn bounded_rosenbrock_satisfies_kkt() {
        let rosen = |x: &[f64], g: &mut [f64]| {
            let (a, b) = (x[0], x[1]);
            g[0] = -2.0 * (1.0 - a) - 400.0 * a * (b - a * a);
            g[1] = 200.0 * (b - a * a);
            (1.0 - a).powi(2) + 100.0 * (b - a * a).powi(2)
        };
        // The unconstrained minimum (1, 1) is cut off by x <= 0.5.
        let lower = [-2.0, -1.0];
        let upper = [0.5, 3.0];
        let rep = minimize(rosen, &[-1.5, 2.0], &lower, &upper, &Settings::default()).unwrap();
        assert!(rep.termination.converged(), "{:?}", rep.termination);
        // KKT: x0 at its upper bound with negative gradient, b = a^2.
        assert!((rep.x[0] - 0.5).abs() < 1e-9, "{:?}", rep.x);
        assert!((rep.x[1] - 0.25).abs() < 1e-5, "{:?}", rep.x);
        let mut g = [0.0; 2];
        rosen(&rep.x, &mut g);
        assert!(g[0] < 0.0 && g[1].abs() < 1e-5, "{g:?}");
    }

    #[test]
    fn fixed_variables_stay_and_unbounded_problems_converge() {
        let p = random_qp(6, 99);
        let mut lower = vec![f64::NEG_INFINITY; 6];
        let mut upper = vec![f64::INFINITY; 6];
        lower[2] = 0.3;
        upper[2] = 0.3;
        let rep = minimize(
            |x, g| qp_eval(&p, x, g),
            &[0.0; 6],
            &lower,
            &upper,
            &Settings::default(),
        )
        .unwrap();
        assert_eq!(rep.x[2], 0.3);
        let mut g = vec![0.0; 6];
        qp_eval(&p, &rep.x, &mut g);
        for i in [0, 1, 3, 4, 5] {
            assert!(g[i].abs() < 1e-6, "g[{i}] = {}", g[i]);
        }
    }

    #[test]
    fn deterministic_and_respects_iteration_limit() {
        let p = random_qp(10, 7);
        let s = Settings {
            max_iterations: 3,
            ..Settings::default()
        };
        let a = minimize(|x, g| qp_eval(&p, x, g), &[0.0; 10], &p.lower, &p.upper, &s).unwrap();
        let b = minimize(|x, g| qp_eval(&p, x, g), &[0.0; 10], &p.lower, &p.upper, &s).unwrap();
        assert_eq!(a.x, b.x);
        assert!(a.iterations <= 3);
    }

    #[test]
    fn rejects_bad_input() {
        let f = |_: &[f64], g: &mut [f64]| {
            g.fill(0.0);
            0.0
        };
        assert!(matches!(
            minimize(
                f,
                &[0.0, 0.0],
                &[0.0, 1.0],
                &[1.0, 0.0],
                &Settings::default()
            ),
            Err(SolverError::Bounds { index: 1, .. })
        ));
        assert!(matches!(
            minimize(f, &[0.0, 0.0], &[0.0], &[1.0, 1.0], &Settings::default()),
            Err(SolverError::Length { .. })
        ));
        let nan = |_: &[f64], g: &mut [f64]| {
            g.fill(0.0);
            f64::NAN
        };
        assert!(matches!(
            minimize(nan, &[0.0], &[0.0], &[1.0], &Settings::default()),
            Err(SolverError::NonFinite { .. })
        ));
    }
}
