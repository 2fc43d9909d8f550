//! The encoder: positional encoding of the root and a small MLP with a
//! hand-written backward pass.
//!
//! Layout: every parameter lives in one flat `Vec<f32>` so that one Adam state
//! covers the whole network. Layer `l` maps `sizes[l]` inputs to
//! `sizes[l + 1]` outputs and stores its weight matrix row-major (`out x in`)
//! followed by its bias. Hidden layers use SiLU (`x * sigmoid(x)`): smooth, so
//! the gradients can be checked against finite differences, and unlike ReLU it
//! has no dead units when the inputs are high-frequency sinusoids. The output
//! layer is linear.
//!
//! Speed. Each layer is one matrix product per chunk of rows
//! (`Z = X W^T + b`; backward `dW += G^T X`, `dX = G W`) through `gemm`, a
//! portable product with a fixed summation order (the same bits on every
//! machine). The caller (`model`) runs fixed chunks of
//! `model::CHUNK` rows in parallel with rayon and sums the per-chunk weight
//! gradients in chunk order, so the result does not depend on the thread
//! count either (tested bit for bit with 1 and 2 threads). The SiLU keeps its
//! sigmoid on the tape and uses a polynomial `exp` (below) that vectorises.
//! `gemm`'s kernels keep blocks of the result in registers (several columns
//! of a dot product, or several rows of a row update) and are compiled twice,
//! portable and for AVX2 (picked at run time); neither changes the order in
//! which any one element sums its products, and no FMA is used, so every
//! build gives the same bits (tested against the unblocked definition).
//! Measured at the synthetic tiger's sizes (4,000 sampled strands, 71
//! inputs, 64 x 3 hidden, 21 codes; an ignored timing test then, `cargo bench
//! --bench learn` now, shared 2-core machine): the codec's forward + backward took 27-29 ms with
//! the first per-row version, 7-9 ms through `matrixmultiply::sgemm`, about
//! 18 ms with the first `gemm` and 14-15 ms with the blocked one. In the
//! codec stage an iteration went from 0.080 to 0.071 s (dense: 0.061 s;
//! rendering dominates both).
//!
//! Initialisation: hidden layers use He-uniform weights drawn from a seeded
//! ChaCha stream and zero biases; the output layer starts at exactly zero, so
//! every initial code is `z = 0` and every initial strand is the basis mean.
//! The dense baseline starts from exactly those strands (fair comparison).
//! Hidden layers still learn from the first step on: the output layer's
//! gradient is non-zero at once and the hidden layers' from the second step.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// NeRF-style positional encoding of a point normalised to the scene's box:
/// `[x, sin(2^f pi x), cos(2^f pi x)]` for `f = 0..F` and each coordinate.
#[derive(Debug, Clone, PartialEq)]
pub struct PositionalEncoding {
    pub frequencies: usize,
    /// Centre of the normalisation box.
    pub center: [f32; 3],
    /// One over the half extent of the box's largest side (maps it to [-1, 1]).
    pub inv_half_extent: f32,
}

impl PositionalEncoding {
    /// Encoding for points inside the box `[lo, hi]`.
    pub fn new(frequencies: usize, lo: [f32; 3], hi: [f32; 3]) -> Self {
        let center = [0, 1, 2].map(|i| 0.5 * (lo[i] + hi[i]));
        let half = (0..3)
            .map(|i| 0.5 * (hi[i] - lo[i]))
            .fold(0.0f32, f32::max)
            .max(1e-12);
        PositionalEncoding {
            frequencies,
            center,
            inv_half_extent: 1.0 / half,
        }
    }
    /// Number of features written by [`encode`](Self::encode).
    pub fn dim(&self) -> usize {
        3 + 6 * self.frequencies
    }
    /// Writes the encoding of `p` into `out[..self.dim()]`.
    pub fn encode(&self, p: [f32; 3], out: &mut [f32]) {
        let x = [0, 1, 2].map(|i| (p[i] - self.center[i]) * self.inv_half_extent);
        out[..3].copy_from_slice(&x);
        let mut k = 3;
        for f in 0..self.frequencies {
            let w = std::f32::consts::PI * (1u64 << f.min(40)) as f32;
            for xi in x {
                let (s, c) = (w * xi).sin_cos();
                out[k] = s;
                out[k + 1] = c;
                k += 2;
            }
        }
    }
}

/// A fully connected network with SiLU hidden activations and a linear output.
#[derive(Debug, Clone, PartialEq)]
pub struct Mlp {
    /// Layer widths, input first, output last.
    pub sizes: Vec<usize>,
    /// All weights and biases, layer by layer (see the module docs).
    pub params: Vec<f32>,
}

/// Values kept by the forward pass for the backward pass (one batch).
#[derive(Debug, Clone)]
pub struct MlpTape {
    batch: usize,
    /// Per layer input activations (`acts[0]` = the network input).
    acts: Vec<Vec<f32>>,
    /// Per hidden layer pre-activations.
    pre: Vec<Vec<f32>>,
    /// Per hidden layer `sigmoid(pre)`, kept so that the backward pass does
    /// not evaluate the exponentials a second time.
    sig: Vec<Vec<f32>>,
}

/// The logistic function on [`exp_approx`], for the SiLU gates (one per
/// activation, so it must vectorise); the other sigmoid of the crate
/// (Frosting's opacities, one per Gaussian per step) keeps the library `exp`.
#[inline]
fn sigmoid_fast(x: f32) -> f32 {
    1.0 / (1.0 + exp_approx(-x))
}

/// `e^x` for the SiLU without a library call, so that the loop over a layer's
/// activations vectorises (the library `expf` took about half of the
/// encoder's forward time at the tiger's sizes). Cody-Waite reduction
/// `x = n ln 2 + r`, `|r| <= ln 2 / 2`, a degree-6 Taylor polynomial for
/// `e^r` (truncation below 3e-8 relative) and `2^n` assembled in the exponent
/// bits; the input is clamped to `[-87, 88]` (results stay normal and finite;
/// the sigmoid saturates long before). Relative error about 2e-7 (tested).
/// Plain arithmetic in a fixed order: deterministic on every machine.
#[inline]
fn exp_approx(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    // ln 2 split into a part exact in f32 and a remainder.
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    // Adding and subtracting 1.5 * 2^23 rounds to the nearest integer.
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 88.0);
    let n = (x * LOG2E + ROUND) - ROUND;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    let scale = f32::from_bits(((n as i32 + 127) as u32) << 23);
    p * scale
}

/// Row and column strides of a matrix operand, in elements.
#[derive(Clone, Copy)]
struct Strides(usize, usize);

/// A read-only matrix operand: elements laid out by `strides`.
#[derive(Clone, Copy)]
struct MatRef<'a> {
    data: &'a [f32],
    strides: Strides,
}

/// A writable matrix operand: elements laid out by `strides`.
struct MatMut<'a> {
    data: &'a mut [f32],
    strides: Strides,
}

/// Largest element index touched by an `rows x cols` operand with strides `s`
/// plus one (0 for an empty operand).
fn extent(rows: usize, cols: usize, s: Strides) -> usize {
    if rows == 0 || cols == 0 {
        0
    } else {
        (rows - 1) * s.0 + (cols - 1) * s.1 + 1
    }
}

/// Columns of `C` that [`dot8_block`] computes at once.
const DOT_COLS: usize = 8;

/// Dot products of `a` with columns `j0 .. j0 + W` of `B`, given `B`
/// transposed (`bt`: `k x n`, row `p` holds `B[p, :]`), in the dot order of
/// [`gemm`]: lane `l` of column `q` accumulates `a[8c + l] B[8c + l, q]`
/// over the whole groups `c` in order, the products past them are summed in
/// order (the tail), and the result is the fixed tree
/// `((l0 + l4) + (l1 + l5)) + ((l2 + l6) + (l3 + l7)) + tail`.
/// Stored lane-major, the eight lanes of `W` columns are `8 x W` independent
/// sums updated by broadcasting one `a[p]` against a contiguous run of
/// `bt`'s row `p`, and the fold runs across columns, not within a register.
#[inline(always)]
fn dot8_block<const W: usize>(a: &[f32], bt: &[f32], n: usize, j0: usize) -> [f32; W] {
    let k = a.len();
    let whole = k - k % 8;
    let mut acc = [[0.0f32; W]; 8];
    for s in (0..whole).step_by(8) {
        let x: &[f32; 8] = a[s..s + 8].try_into().expect("eight lanes");
        let rows: &[f32] = &bt[s * n..(s + 8) * n];
        // Lanes unrolled by hand: written as a loop over `l`, the compiler
        // kept the accumulators on the stack and did not vectorise them.
        add_scaled_row(&mut acc[0], x[0], &rows[j0..]);
        add_scaled_row(&mut acc[1], x[1], &rows[n + j0..]);
        add_scaled_row(&mut acc[2], x[2], &rows[2 * n + j0..]);
        add_scaled_row(&mut acc[3], x[3], &rows[3 * n + j0..]);
        add_scaled_row(&mut acc[4], x[4], &rows[4 * n + j0..]);
        add_scaled_row(&mut acc[5], x[5], &rows[5 * n + j0..]);
        add_scaled_row(&mut acc[6], x[6], &rows[6 * n + j0..]);
        add_scaled_row(&mut acc[7], x[7], &rows[7 * n + j0..]);
    }
    let mut tail = [0.0f32; W];
    for p in whole..k {
        let x = a[p];
        let row = &bt[p * n + j0..p * n + j0 + W];
        for q in 0..W {
            tail[q] += x * row[q];
        }
    }
    // The tree per column, written across columns so that it vectorises.
    let mut out = [0.0f32; W];
    for q in 0..W {
        out[q] = ((acc[0][q] + acc[4][q]) + (acc[1][q] + acc[5][q]))
            + ((acc[2][q] + acc[6][q]) + (acc[3][q] + acc[7][q]))
            + tail[q];
    }
    out
}

/// `acc[q] += x row[q]` for the first `W` entries of `row`.
#[inline(always)]
fn add_scaled_row<const W: usize>(acc: &mut [f32; W], x: f32, row: &[f32]) {
    let row: &[f32; W] = row[..W].try_into().expect("a block of columns");
    for q in 0..W {
        acc[q] += x * row[q];
    }
}

/// Rows of `C` that [`axpy_block`] keeps in registers, and its widths.
const AXPY_ROWS: usize = 4;
const AXPY_COLS: usize = 16;
const AXPY_NARROW: usize = 4;

/// `C[i0 + r, j0 + q] += sum_p A[i0 + r, p] B[p, j0 + q]` for `R` rows and
/// `W` columns, `B` and `C` contiguous along their rows (their column
/// strides are not read). Each element adds its products in the order
/// `p = 0, 1, ...` onto its current value, exactly as one row update
/// `C[i, :] += A[i, p] B[p, :]` per `p` would; the block stays in registers
/// over the whole `p` loop instead of being loaded and stored once per `p`.
#[inline(always)]
fn axpy_block<const R: usize, const W: usize>(
    k: usize,
    a: MatRef,
    b: MatRef,
    c: &mut MatMut,
    i0: usize,
    j0: usize,
) {
    let (a, sa) = (a.data, a.strides);
    let (b, sb0) = (b.data, b.strides.0);
    let sc0 = c.strides.0;
    let c = &mut *c.data;
    let mut acc = [[0.0f32; W]; R];
    for (r, acc_r) in acc.iter_mut().enumerate() {
        acc_r.copy_from_slice(&c[(i0 + r) * sc0 + j0..(i0 + r) * sc0 + j0 + W]);
    }
    for p in 0..k {
        let b_p: &[f32; W] = b[p * sb0 + j0..p * sb0 + j0 + W]
            .try_into()
            .expect("a block of columns");
        for (r, acc_r) in acc.iter_mut().enumerate() {
            let a_rp = a[(i0 + r) * sa.0 + p * sa.1];
            for q in 0..W {
                acc_r[q] += a_rp * b_p[q];
            }
        }
    }
    for (r, acc_r) in acc.iter().enumerate() {
        c[(i0 + r) * sc0 + j0..(i0 + r) * sc0 + j0 + W].copy_from_slice(acc_r);
    }
}

/// Row updates of rows `i0 .. i0 + R`, all columns: blocks of
/// [`AXPY_COLS`], then of [`AXPY_NARROW`], then one column at a time.
#[inline(always)]
fn axpy_rows<const R: usize>(k: usize, n: usize, a: MatRef, b: MatRef, c: &mut MatMut, i0: usize) {
    let mut j = 0;
    while j + AXPY_COLS <= n {
        axpy_block::<R, AXPY_COLS>(k, a, b, c, i0, j);
        j += AXPY_COLS;
    }
    while j + AXPY_NARROW <= n {
        axpy_block::<R, AXPY_NARROW>(k, a, b, c, i0, j);
        j += AXPY_NARROW;
    }
    for j in j..n {
        axpy_block::<R, 1>(k, a, b, c, i0, j);
    }
}

/// `C = A B + beta C` with `A: m x k`, `B: k x n`, `C: m x n`. Portable
/// Rust with a fixed summation order, so the result depends only on the
/// operands and sizes: the same bits on every machine and thread count.
/// (`matrixmultiply::sgemm` was measured here too: its kernels are picked at
/// run time from the CPU's features, so bits could differ between machines.)
///
/// Every element of `C` sums its products in one documented order:
/// - when both operands run along `p` in memory (the forward's `X W^T`), as
///   eight lanes over groups of eight, a fixed tree, then the tail
///   ([`dot8_block`]);
/// - otherwise sequentially, `p = 0, 1, ...`, onto `beta C`.
///
/// Blocking (several columns or rows at once) changes which elements are
/// computed together, never the order within one element, so it is free
/// to tune for speed (`gemm_sums_in_the_documented_order` checks the bits
/// against the unblocked loops). No FMA contraction: Rust does not fuse
/// `a * b + c` unless asked.
///
/// The slices are checked against the strides first (a mismatch is a bug in
/// this module, hence a panic, not an input error).
fn gemm(m: usize, k: usize, n: usize, a: MatRef, b: MatRef, beta: f32, c: MatMut) {
    let run = || gemm_portable(m, k, n, a, b, beta, c);
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just above).
        unsafe { with_avx2(run) };
        return;
    }
    run()
}

/// Runs `f` compiled for AVX2: `f` and the `#[inline(always)]` kernels it
/// calls are inlined here, so they get wider vectors, the same operations in
/// the same order (no FMA is enabled), hence the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn with_avx2(f: impl FnOnce()) {
    f()
}

#[inline(always)]
fn gemm_portable(m: usize, k: usize, n: usize, a: MatRef, b: MatRef, beta: f32, mut c: MatMut) {
    let (sa, sb, sc) = (a.strides, b.strides, c.strides);
    assert!(a.data.len() >= extent(m, k, sa), "gemm: A too short");
    assert!(b.data.len() >= extent(k, n, sb), "gemm: B too short");
    assert!(c.data.len() >= extent(m, n, sc), "gemm: C too short");
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if beta == 0.0 {
            c.data.iter_mut().for_each(|v| *v = 0.0);
        }
        return;
    }
    if beta == 0.0 {
        // Not `beta * c`: `c` may hold anything, NaN included, and 0 x NaN is NaN.
        for i in 0..m {
            for j in 0..n {
                c.data[i * sc.0 + j * sc.1] = 0.0;
            }
        }
    } else if beta != 1.0 {
        for i in 0..m {
            for j in 0..n {
                c.data[i * sc.0 + j * sc.1] *= beta;
            }
        }
    }
    if sa.1 == 1 && sb.0 == 1 {
        // One dot product per element, DOT_COLS columns at a time from a
        // transposed copy of B (small: a layer's weights).
        let mut bt = vec![0.0f32; k * n];
        for j in 0..n {
            for p in 0..k {
                bt[p * n + j] = b.data[j * sb.1 + p];
            }
        }
        for i in 0..m {
            let a_row = &a.data[i * sa.0..i * sa.0 + k];
            let mut j = 0;
            while j + DOT_COLS <= n {
                let d = dot8_block::<DOT_COLS>(a_row, &bt, n, j);
                for (q, dq) in d.iter().enumerate() {
                    c.data[i * sc.0 + (j + q) * sc.1] += dq;
                }
                j += DOT_COLS;
            }
            for j in j..n {
                c.data[i * sc.0 + j * sc.1] += dot8_block::<1>(a_row, &bt, n, j)[0];
            }
        }
        return;
    }
    if sb.1 == 1 && sc.1 == 1 {
        let full_rows = m - m % AXPY_ROWS;
        for i in (0..full_rows).step_by(AXPY_ROWS) {
            axpy_rows::<AXPY_ROWS>(k, n, a, b, &mut c, i);
        }
        for i in full_rows..m {
            axpy_rows::<1>(k, n, a, b, &mut c, i);
        }
        return;
    }
    let (a, b, c) = (a.data, b.data, c.data);
    for i in 0..m {
        for p in 0..k {
            let a_ip = a[i * sa.0 + p * sa.1];
            for j in 0..n {
                c[i * sc.0 + j * sc.1] += a_ip * b[p * sb.0 + j * sb.1];
            }
        }
    }
}

impl Mlp {
    /// A network `input -> hidden x depth -> output`, initialised from `seed`.
    pub fn new(input: usize, hidden: usize, depth: usize, output: usize, seed: u64) -> Self {
        let mut sizes = vec![input];
        sizes.extend(std::iter::repeat_n(hidden, depth));
        sizes.push(output);
        let count: usize = sizes.windows(2).map(|w| w[0] * w[1] + w[1]).sum();
        let mut params = vec![0.0f32; count];
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let layers = sizes.len() - 1;
        let mut off = 0;
        for l in 0..layers {
            let (fan_in, fan_out) = (sizes[l], sizes[l + 1]);
            if l + 1 < layers {
                let bound = (6.0 / fan_in.max(1) as f32).sqrt();
                for w in &mut params[off..off + fan_in * fan_out] {
                    *w = rng.gen_range(-bound..bound);
                }
            }
            off += fan_in * fan_out + fan_out;
        }
        Mlp { sizes, params }
    }

    pub fn input_dim(&self) -> usize {
        self.sizes[0]
    }
    pub fn output_dim(&self) -> usize {
        *self.sizes.last().unwrap_or(&0)
    }
    pub fn param_count(&self) -> usize {
        self.params.len()
    }

    /// Offsets of each layer's weights in `params`.
    fn offsets(&self) -> Vec<usize> {
        let mut offs = Vec::with_capacity(self.sizes.len());
        let mut off = 0;
        for w in self.sizes.windows(2) {
            offs.push(off);
            off += w[0] * w[1] + w[1];
        }
        offs
    }

    /// Runs `batch` rows of `input` (row-major, `batch x input_dim`) through the
    /// network; returns the outputs (`batch x output_dim`) and the tape.
    ///
    /// Each layer is one matrix product `Z = X W^T + b` (see `gemm`); the
    /// caller splits large batches into fixed row chunks (`model::CHUNK`).
    pub fn forward(&self, input: &[f32], batch: usize) -> (Vec<f32>, MlpTape) {
        debug_assert_eq!(input.len(), batch * self.input_dim());
        let layers = self.sizes.len() - 1;
        let offs = self.offsets();
        let mut acts = vec![input.to_vec()];
        let mut pre = Vec::with_capacity(layers.saturating_sub(1));
        let mut sig = Vec::with_capacity(layers.saturating_sub(1));
        let mut out = Vec::new();
        for l in 0..layers {
            let (n_in, n_out) = (self.sizes[l], self.sizes[l + 1]);
            let w = &self.params[offs[l]..offs[l] + n_in * n_out];
            let b = &self.params[offs[l] + n_in * n_out..offs[l] + n_in * n_out + n_out];
            let x = &acts[l];
            let mut z = Vec::with_capacity(batch * n_out);
            for _ in 0..batch {
                z.extend_from_slice(b);
            }
            // Z (batch x n_out) += X (batch x n_in) W^T (n_in x n_out).
            gemm(
                batch,
                n_in,
                n_out,
                MatRef {
                    data: x,
                    strides: Strides(n_in, 1),
                },
                MatRef {
                    data: w,
                    strides: Strides(1, n_in),
                },
                1.0,
                MatMut {
                    data: &mut z,
                    strides: Strides(n_out, 1),
                },
            );
            if l + 1 < layers {
                let s: Vec<f32> = z.iter().map(|&v| sigmoid_fast(v)).collect();
                let a: Vec<f32> = z.iter().zip(&s).map(|(&v, &si)| v * si).collect();
                pre.push(z);
                sig.push(s);
                acts.push(a);
            } else {
                out = z;
            }
        }
        (
            out,
            MlpTape {
                batch,
                acts,
                pre,
                sig,
            },
        )
    }

    /// Backward pass: adds d loss / d params to `grad` (same layout as
    /// `params`) given `grad_out` = d loss / d outputs (`batch x output_dim`).
    ///
    /// Per layer: `dW += G^T X`, `db += column sums of G` (rows in order),
    /// `dX = G W`, then through SiLU; all products through `gemm`.
    pub fn backward(&self, tape: &MlpTape, grad_out: &[f32], grad: &mut [f32]) {
        let layers = self.sizes.len() - 1;
        let offs = self.offsets();
        let batch = tape.batch;
        let mut g = grad_out.to_vec();
        for l in (0..layers).rev() {
            let (n_in, n_out) = (self.sizes[l], self.sizes[l + 1]);
            let w_off = offs[l];
            let b_off = w_off + n_in * n_out;
            let x = &tape.acts[l];
            // Weight and bias gradients.
            {
                let (gw, gb) = grad[w_off..b_off + n_out].split_at_mut(n_in * n_out);
                // dW (n_out x n_in) += G^T (n_out x batch) X (batch x n_in).
                gemm(
                    n_out,
                    batch,
                    n_in,
                    MatRef {
                        data: &g,
                        strides: Strides(1, n_out),
                    },
                    MatRef {
                        data: x,
                        strides: Strides(n_in, 1),
                    },
                    1.0,
                    MatMut {
                        data: gw,
                        strides: Strides(n_in, 1),
                    },
                );
                for gr in g.chunks_exact(n_out) {
                    for (b, v) in gb.iter_mut().zip(gr) {
                        *b += v;
                    }
                }
            }
            if l == 0 {
                break;
            }
            // Gradient with respect to this layer's input, then through SiLU.
            let w = &self.params[w_off..b_off];
            let mut gx = vec![0.0f32; batch * n_in];
            // dX (batch x n_in) = G (batch x n_out) W (n_out x n_in).
            gemm(
                batch,
                n_out,
                n_in,
                MatRef {
                    data: &g,
                    strides: Strides(n_out, 1),
                },
                MatRef {
                    data: w,
                    strides: Strides(n_in, 1),
                },
                0.0,
                MatMut {
                    data: &mut gx,
                    strides: Strides(n_in, 1),
                },
            );
            let z = &tape.pre[l - 1];
            let sg = &tape.sig[l - 1];
            for ((gi, &zi), &s) in gx.iter_mut().zip(z).zip(sg) {
                *gi *= s * (1.0 + zi * (1.0 - s));
            }
            g = gx;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn loss(mlp: &Mlp, x: &[f32], batch: usize, target: &[f32]) -> f64 {
        let (y, _) = mlp.forward(x, batch);
        y.iter()
            .zip(target)
            .map(|(a, b)| 0.5 * ((a - b) as f64).powi(2))
            .sum()
    }

    /// The unblocked definition of `gemm`'s order for one element of `C`.
    fn reference_element(i: usize, j: usize, k: usize, a: MatRef, b: MatRef, c0: f32) -> f32 {
        let (a, sa, b, sb) = (a.data, a.strides, b.data, b.strides);
        let av = |p: usize| a[i * sa.0 + p * sa.1];
        let bv = |p: usize| b[p * sb.0 + j * sb.1];
        if sa.1 == 1 && sb.0 == 1 {
            let mut lanes = [0.0f32; 8];
            let whole = k - k % 8;
            for p in 0..whole {
                lanes[p % 8] += av(p) * bv(p);
            }
            let mut tail = 0.0f32;
            for p in whole..k {
                tail += av(p) * bv(p);
            }
            let folded = ((lanes[0] + lanes[4]) + (lanes[1] + lanes[5]))
                + ((lanes[2] + lanes[6]) + (lanes[3] + lanes[7]))
                + tail;
            c0 + folded
        } else {
            let mut acc = c0;
            for p in 0..k {
                acc += av(p) * bv(p);
            }
            acc
        }
    }

    /// Blocking must not change a single bit: every layout the MLP uses
    /// (`X W^T`, `G^T X`, `G W`) and a fully strided one, at sizes with
    /// ragged edges, against the element-by-element definition.
    #[test]
    fn gemm_sums_in_the_documented_order() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        for &(m, k, n) in &[
            (1, 1, 1),
            (3, 9, 5),
            (7, 77, 64),
            (128, 64, 21),
            (5, 130, 33),
        ] {
            for beta in [0.0f32, 1.0, 0.5] {
                let layouts = [
                    (Strides(k, 1), Strides(1, k), Strides(n, 1)),
                    (Strides(1, m), Strides(n, 1), Strides(n, 1)),
                    (Strides(k, 1), Strides(n, 1), Strides(n, 1)),
                    (Strides(1, m), Strides(1, k), Strides(1, m)),
                ];
                for (sa, sb, sc) in layouts {
                    let a: Vec<f32> = (0..m * k).map(|_| rng.gen_range(-1.0..1.0)).collect();
                    let b: Vec<f32> = (0..k * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
                    let c_in: Vec<f32> = (0..m * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
                    let mut c = c_in.clone();
                    let a = MatRef {
                        data: &a,
                        strides: sa,
                    };
                    let b = MatRef {
                        data: &b,
                        strides: sb,
                    };
                    let c_out = MatMut {
                        data: &mut c,
                        strides: sc,
                    };
                    gemm(m, k, n, a, b, beta, c_out);
                    for i in 0..m {
                        for j in 0..n {
                            let at = i * sc.0 + j * sc.1;
                            let c0 = if beta == 0.0 {
                                0.0
                            } else if beta == 1.0 {
                                c_in[at]
                            } else {
                                c_in[at] * beta
                            };
                            let want = reference_element(i, j, k, a, b, c0);
                            assert_eq!(
                                c[at].to_bits(),
                                want.to_bits(),
                                "m {m} k {k} n {n} beta {beta} element ({i}, {j})"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    // Finite differences perturb parameter i and read gradient i.
    #[allow(clippy::needless_range_loop)]
    fn gradients_match_finite_differences() {
        let mut mlp = Mlp::new(5, 7, 2, 3, 11);
        // Give the output layer non-zero weights so every layer is exercised.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let n = mlp.param_count();
        let out_block = 7 * 3 + 3;
        for w in &mut mlp.params[n - out_block..] {
            *w = rng.gen_range(-0.5..0.5);
        }
        let batch = 4;
        let x: Vec<f32> = (0..batch * 5).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let t: Vec<f32> = (0..batch * 3).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let (y, tape) = mlp.forward(&x, batch);
        let gout: Vec<f32> = y.iter().zip(&t).map(|(a, b)| a - b).collect();
        let mut grad = vec![0.0; n];
        mlp.backward(&tape, &gout, &mut grad);
        let h = 1e-3f32;
        let mut worst = 0.0f64;
        for i in 0..n {
            let orig = mlp.params[i];
            mlp.params[i] = orig + h;
            let lp = loss(&mlp, &x, batch, &t);
            mlp.params[i] = orig - h;
            let lm = loss(&mlp, &x, batch, &t);
            mlp.params[i] = orig;
            let fd = (lp - lm) / (2.0 * h as f64);
            let err = (fd - grad[i] as f64).abs() / (1e-2 + fd.abs());
            worst = worst.max(err);
        }
        assert!(worst < 2e-2, "worst relative gradient error {worst}");
    }

    #[test]
    fn initial_output_is_zero_and_seeded() {
        let a = Mlp::new(4, 8, 2, 3, 5);
        let b = Mlp::new(4, 8, 2, 3, 5);
        let c = Mlp::new(4, 8, 2, 3, 6);
        assert_eq!(a, b);
        assert_ne!(a, c);
        let (y, _) = a.forward(&[0.3, -0.2, 0.9, 0.1], 1);
        assert!(y.iter().all(|v| *v == 0.0));
    }

    #[test]
    fn exp_approx_matches_the_library() {
        let mut worst = 0.0f64;
        for i in -200_000..=200_000 {
            let x = (i as f32 * 4.4e-4).max(-87.0); // [-87, 88], the clamped range
            let e = (x as f64).exp();
            let a = exp_approx(x) as f64;
            assert!(a.is_finite() && a > 0.0, "exp_approx({x}) = {a}");
            worst = worst.max((a - e).abs() / e);
        }
        assert!(worst < 5e-7, "worst relative error {worst}");
        assert!(exp_approx(-1e4) > 0.0 && exp_approx(1e4).is_finite());
        assert!(sigmoid_fast(-1e4) >= 0.0 && sigmoid_fast(1e4) <= 1.0);
    }

    #[test]
    fn positional_encoding_is_bounded() {
        let pe = PositionalEncoding::new(4, [-2.0, 0.0, 0.0], [2.0, 1.0, 1.0]);
        assert_eq!(pe.dim(), 27);
        let mut out = vec![0.0; pe.dim()];
        pe.encode([2.0, 0.5, 1.0], &mut out);
        assert!((out[0] - 1.0).abs() < 1e-6);
        assert!(out[1].abs() < 1e-6);
        assert!(out.iter().all(|v| v.abs() <= 1.0 + 1e-6));
    }
}
