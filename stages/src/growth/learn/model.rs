//! The two strand models trained by the shared loop: the codec (encoder +
//! fine-tuned decoder + placement) and the dense baseline (every point free),
//! plus the prepared per-root data and the Adam optimisers they use.
//!
//! Both models expose the same three operations on a subset of strands:
//! `forward` (world points of each strand, root first), `backward` (parameter
//! gradients from point gradients) and `step` (Adam). Work is split into fixed
//! chunks of [`CHUNK`] strands processed in parallel; per-chunk gradients are
//! summed in chunk order, so results do not depend on the thread count.
//!
//! Optimisers. The codec's parameters are all touched by every iteration, so
//! it uses plain Adam. The dense baseline's parameters belong to single
//! strands and only the sampled subset has gradients in an iteration; it uses
//! "lazy" Adam: each strand keeps its own step count and only sampled strands
//! are updated (unsampled strands do not drift on stale momentum). Per-strand
//! colours, shared by both models, use the same lazy Adam. (The renderer's
//! Adam updates whole tensors; this per-row variant is specific to strand
//! subsets, hence kept here.)

use glam::{Mat3, Vec3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use super::mlp::{Mlp, MlpTape, PositionalEncoding};
use super::placement::{self, Decoder};
use crate::maths::stats::standard_normal;

/// One chunk's codec gradient sums, added up in chunk order: encoder, decoder, part log
/// length scales, log style scale, the chunk's style-code rows.
type ChunkGrads = (Vec<f32>, Vec<f32>, Vec<f32>, f32, Vec<f32>);

/// Strands per parallel work item.
pub const CHUNK: usize = 128;

/// Per-root data, prepared once: root, frame, length (scene units), encoder
/// features `[gamma(r), one-hot part, rho, l / lmax]`.
#[derive(Debug, Clone)]
pub struct Prepared {
    pub points: usize,
    pub roots: Vec<Vec3>,
    pub frames: Vec<Mat3>,
    pub lengths: Vec<f32>,
    /// Part index per root (below `part_count`).
    pub parts: Vec<u16>,
    pub part_count: usize,
    pub features: Vec<f32>,
    pub feature_dim: usize,
}

/// What [`Prepared::new`] is built from, one entry per root.
#[derive(Debug, Clone)]
pub struct RootInputs {
    pub positions: Vec<Vec3>,
    pub frames: Vec<Mat3>,
    /// Target strand lengths (scene units).
    pub lengths: Vec<f32>,
    /// Part indices (below the `part_count` given to [`Prepared::new`]).
    pub parts: Vec<u16>,
    pub rho: Vec<f32>,
}

impl Prepared {
    /// Builds the features of strands with `points` points each; the part
    /// one-hot has `part_count` entries.
    pub fn new(
        points: usize,
        inputs: RootInputs,
        part_count: usize,
        pe: &PositionalEncoding,
    ) -> Self {
        let RootInputs {
            positions: roots,
            frames,
            lengths,
            parts,
            rho,
        } = inputs;
        let lmax = lengths.iter().copied().fold(0.0f32, f32::max).max(1e-12);
        let feature_dim = pe.dim() + part_count + 2;
        let mut features = vec![0.0f32; roots.len() * feature_dim];
        for (i, row) in features.chunks_mut(feature_dim).enumerate() {
            pe.encode(roots[i].to_array(), &mut row[..pe.dim()]);
            let p = parts.get(i).copied().unwrap_or(0) as usize;
            if p < part_count {
                row[pe.dim() + p] = 1.0;
            }
            row[feature_dim - 2] = rho.get(i).copied().unwrap_or(0.0);
            row[feature_dim - 1] = lengths[i] / lmax;
        }
        Prepared {
            points,
            roots,
            frames,
            lengths,
            parts,
            part_count,
            features,
            feature_dim,
        }
    }
    pub fn len(&self) -> usize {
        self.roots.len()
    }
    pub fn is_empty(&self) -> bool {
        self.roots.is_empty()
    }
    /// How many roots each of the `part_count` parts has.
    pub fn strands_per_part(&self) -> Vec<usize> {
        let mut n = vec![0usize; self.part_count];
        for &p in &self.parts {
            if let Some(c) = n.get_mut(p as usize) {
                *c += 1;
            }
        }
        n
    }

    /// Mean target length (the `lbar` of the geometric losses).
    pub fn mean_length(&self) -> f32 {
        if self.lengths.is_empty() {
            return 0.0;
        }
        (self.lengths.iter().map(|&l| l as f64).sum::<f64>() / self.lengths.len() as f64) as f32
    }
}

/// Adam over one flat parameter vector.
#[derive(Debug, Clone)]
pub struct Adam {
    m: Vec<f32>,
    v: Vec<f32>,
    t: i32,
}

pub const BETA1: f32 = 0.9;
pub const BETA2: f32 = 0.999;
pub const ADAM_EPS: f32 = 1e-8;

impl Adam {
    pub fn new(n: usize) -> Self {
        Adam {
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
        }
    }
    pub fn step(&mut self, p: &mut [f32], g: &[f32], lr: f32) {
        self.t += 1;
        let c1 = 1.0 - BETA1.powi(self.t);
        let c2 = 1.0 - BETA2.powi(self.t);
        for i in 0..p.len() {
            self.m[i] = BETA1 * self.m[i] + (1.0 - BETA1) * g[i];
            self.v[i] = BETA2 * self.v[i] + (1.0 - BETA2) * g[i] * g[i];
            p[i] -= lr * (self.m[i] / c1) / ((self.v[i] / c2).sqrt() + ADAM_EPS);
        }
    }
}

/// Lazy Adam over rows of equal length; only the rows given are updated.
#[derive(Debug, Clone)]
pub struct RowAdam {
    row: usize,
    m: Vec<f32>,
    v: Vec<f32>,
    t: Vec<i32>,
}

impl RowAdam {
    pub fn new(rows: usize, row: usize) -> Self {
        RowAdam {
            row,
            m: vec![0.0; rows * row],
            v: vec![0.0; rows * row],
            t: vec![0; rows],
        }
    }
    /// `g` holds one row per entry of `rows`, in that order.
    pub fn step(&mut self, p: &mut [f32], g: &[f32], rows: &[u32], lr: f32) {
        let n = self.row;
        for (k, &r) in rows.iter().enumerate() {
            let r = r as usize;
            self.t[r] += 1;
            let c1 = 1.0 - BETA1.powi(self.t[r]);
            let c2 = 1.0 - BETA2.powi(self.t[r]);
            for j in 0..n {
                let i = r * n + j;
                let gi = g[k * n + j];
                self.m[i] = BETA1 * self.m[i] + (1.0 - BETA1) * gi;
                self.v[i] = BETA2 * self.v[i] + (1.0 - BETA2) * gi * gi;
                p[i] -= lr * (self.m[i] / c1) / ((self.v[i] / c2).sqrt() + ADAM_EPS);
            }
        }
    }
}

/// Learning rates. Dense point steps are in units of the strand length (the
/// canonical strands are normalised to unit arc length by the placement).
#[derive(Debug, Clone, Copy)]
pub struct Rates {
    pub encoder: f32,
    pub decoder: f32,
    pub points: f32,
    /// The codec's per-part log length scales (`Codec::with_part_lengths`).
    pub length: f32,
    /// The codec's log style scale (`Codec::with_style_scale`).
    pub style: f32,
    /// The codec's per-strand style codes (`Codec::with_learned_style_codes`).
    pub style_codes: f32,
}

/// The codec: encoder E_theta and fine-tuned decoder D_psi.
///
/// With `rotation`, the encoder has one more output, an angle
/// `theta_i = angle_scale * out_K` that turns strand `i`'s root frame about
/// its normal before placement: the in-plane growth direction becomes a
/// learned field (zero at the start, as the output layer starts at zero)
/// instead of being fixed by the roots' tangents, which the basis can bend
/// only as far as its corpus leans (about 25 degrees either way).
///
/// With `tilt`, one more output `beta_i = tilt_scale * out` turns the frame
/// about its own bitangent first (positive lays the strand toward the
/// skin): the elevation becomes a learned field too, instead of the
/// corpus' mean lift, which the codes move only slowly. The frame is
/// `F_i = base_i Rz(theta_i) Ry(beta_i)`.
#[derive(Debug, Clone)]
pub struct Codec {
    pub mlp: Mlp,
    pub decoder: Decoder,
    pub finetune_decoder: bool,
    pub rotation: bool,
    pub tilt: bool,
    /// Radians per unit of the encoder's angle output ([`ANGLE_SCALE`] unless set).
    pub angle_scale: f32,
    /// Radians per unit of the encoder's tilt output ([`ANGLE_SCALE`] unless set).
    pub tilt_scale: f32,
    /// Fixed per-strand style codes added to the encoder's K coefficients
    /// (`n * K`, strand-major; empty = none): see [`style_codes`].
    pub style: Vec<f32>,
    /// How many leading basis components the encoder outputs codes for
    /// (at most the decoder's K): the ones the views resolve. The others
    /// decode from the style codes alone ([`Codec::with_trained_components`]).
    pub trained: usize,
    /// Learned length scales per part (`None` = lengths as given).
    pub part_lengths: Option<Box<PartLengths>>,
    /// A learned scale on every style code (`None` = the codes as given).
    pub style_scale: Option<Box<StyleScale>>,
    /// Learned style codes (`None` = fixed as drawn).
    pub style_rows: Option<Box<StyleRows>>,
    adam_theta: Adam,
    adam_psi: Adam,
}

/// One learned length scale per part that keeps the coat's overall length:
/// strand `i` is placed at `length_i exp(log_scale[part_i])`, and after each
/// Adam step (which moves every part by about its rate, signed by how
/// consistently its strands pull) the mean step, weighted by each part's
/// share of the strands, is taken back. Left free, the image terms shorten
/// every part alike (learn module doc), so only the split of length between
/// parts is theirs to move.
#[derive(Debug, Clone)]
pub struct PartLengths {
    pub log_scale: Vec<f32>,
    shares: Vec<f32>,
    adam: Adam,
}

impl PartLengths {
    /// Scales of 1 for parts with `strands_per_part` strands each.
    pub fn new(strands_per_part: &[usize]) -> Self {
        let total = strands_per_part.iter().sum::<usize>() as f32;
        PartLengths {
            log_scale: vec![0.0; strands_per_part.len()],
            shares: strands_per_part
                .iter()
                .map(|&w| if total > 0.0 { w as f32 / total } else { 0.0 })
                .collect(),
            adam: Adam::new(strands_per_part.len()),
        }
    }

    /// Part `p`'s length scale (1 for a part it does not know).
    pub fn scale(&self, p: usize) -> f32 {
        self.log_scale.get(p).map_or(1.0, |s| s.exp())
    }

    /// One Adam step on `grad` (d loss / d log scale per part), then the
    /// coat's mean step taken back.
    fn step(&mut self, grad: &[f32], rate: f32) {
        self.adam.step(&mut self.log_scale, grad, rate);
        let mean: f32 = self
            .log_scale
            .iter()
            .zip(&self.shares)
            .map(|(l, w)| l * w)
            .sum();
        for l in self.log_scale.iter_mut() {
            *l -= mean;
        }
    }
}

/// One learned scale on all the style codes, 1 at the start and never below: the views may
/// ask every strand to depart further from the guide field's local mean shape than the basis
/// corpus' own spread (a coat that curls more than the corpus does), not less. The image
/// terms, fitting detail they do not resolve, pull toward the local mean shape wherever the
/// detail is not larger than the corpus', which costs F-score on the straight coats (learn
/// module doc), so a step below 1 is taken back.
#[derive(Debug, Clone)]
pub struct StyleScale {
    /// The log of the scale (a one-element vector, as Adam steps slices).
    pub log_scale: Vec<f32>,
    adam: Adam,
}

impl StyleScale {
    fn new() -> Self {
        StyleScale {
            log_scale: vec![0.0],
            adam: Adam::new(1),
        }
    }

    /// The scale on the style codes.
    pub fn scale(&self) -> f32 {
        self.log_scale[0].exp()
    }

    /// One Adam step on `grad` (d loss / d log scale), kept at or above a scale of 1.
    fn step(&mut self, grad: &[f32], rate: f32) {
        self.adam.step(&mut self.log_scale, grad, rate);
        self.log_scale[0] = self.log_scale[0].max(0.0);
    }
}

/// The style codes as parameters: each strand's styled components move with lazy Adam when the
/// strand is sampled, so the views may give a strand its own departure from the guide field's
/// local mean shape (the paper's style map, trained) rather than the one drawn for it.
#[derive(Debug, Clone)]
pub struct StyleRows {
    /// The components that move (the styled ones, [`styled_components`]).
    pub styled: std::ops::Range<usize>,
    adam: RowAdam,
}

/// Per-strand style codes (the paper's optional style map, as codes): strand
/// `i` gets `scale * e_i`, `e_i` a standard normal K-vector from ChaCha8
/// seeded with `seed` on stream `i`, with its first `from` entries set to
/// zero; strand `i`'s code depends neither on the thread count, nor on how
/// many strands there are, nor on `from`.
///
/// Why: the encoder is a smooth field of the root position, so every strand
/// near another decodes to nearly the same shape. In views whose pixels are
/// wider than a strand, the images constrain that local mean shape but not
/// how each strand departs from it; the style codes give each strand a
/// departure drawn from the basis' own (unit-variance) distribution, fixed
/// during training, so the guide field learns the mean around them. The
/// leading components (the largest-variance ones: a strand's overall lean
/// and bend) are what the views do resolve, so `from` leaves them to the
/// guide field alone; the offsets then only add the fine waves and curls.
///
/// `to` ends the styled components (exclusive; 0 or anything above `k` means `k`): the trailing
/// components of a corpus basis are its vertex-scale wiggles, which no pixel shows, and an
/// offset there kinks every strand.
pub fn style_codes(n: usize, k: usize, from: usize, to: usize, scale: f32, seed: u64) -> Vec<f32> {
    let styled = styled_components(k, from, to, scale);
    if styled.is_empty() {
        return Vec::new();
    }
    let mut out = Vec::with_capacity(n * k);
    for i in 0..n {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(i as u64);
        out.extend((0..k).map(|j| {
            let e = standard_normal(&mut rng);
            if styled.contains(&j) {
                scale * e
            } else {
                0.0
            }
        }));
    }
    out
}

/// The components [`style_codes`] offsets among `k`: `from..to` (`to` 0 or above `k` means
/// `k`), none when `scale` is 0.
pub fn styled_components(k: usize, from: usize, to: usize, scale: f32) -> std::ops::Range<usize> {
    let to = if to == 0 { k } else { to.min(k) };
    if scale == 0.0 || to <= from {
        return 0..0;
    }
    from..to
}

/// Radians per unit of the encoder's rotation output of a new [`Codec`] (the stage sets its own).
pub const ANGLE_SCALE: f32 = 1.0;

/// The dense baseline: the L - 1 non-root points of every strand, free, in
/// the strand's canonical root frame (the root point is the origin). They go
/// through the same placement equation as the codec's decoded strands, so
/// every strand keeps exactly its length, as in NeuralFur (whose strands are
/// normalised to unit arc length and scaled to the part length): without it
/// the free points stretch strands to reach the envelope and the images
/// (measured on the synthetic tiger: mean length 8.1 cm for 3.8 cm targets
/// after 1,200 iterations, precision falling all along).
#[derive(Debug, Clone)]
pub struct Dense {
    pub points: Vec<f32>,
    adam: RowAdam,
}

/// Either model.
#[derive(Debug, Clone)]
pub enum Model {
    Codec(Codec),
    Dense(Dense),
}

/// What a forward pass keeps for its backward pass.
pub enum Cache {
    Codec(Vec<CodecChunk>),
    Dense,
}

pub struct CodecChunk {
    tape: MlpTape,
    /// The encoder's outputs (stride [`Codec::stride`]).
    z: Vec<f32>,
    /// The decoder's coefficients (K per strand, style included).
    codes: Vec<f32>,
    local: Vec<Vec3>,
}

/// Parameter gradients of one iteration.
pub enum Grads {
    Codec {
        theta: Vec<f32>,
        psi: Vec<f32>,
        /// Per part, d loss / d log length scale (empty without learned lengths).
        length: Vec<f32>,
        /// d loss / d log style scale (empty without a learned style scale).
        style: Vec<f32>,
        /// d loss / d style code, one K-row per subset strand, zero off the styled
        /// components (empty without learned style codes).
        style_codes: Vec<f32>,
    },
    Dense {
        rows: Vec<f32>,
    },
}

impl Grads {
    /// Adds `other` (the same model's gradients for the same subset), all but
    /// its style-scale part: the shape terms (learn::geomloss::turning) shape
    /// what the encoder outputs and leave the style map's scale to the views.
    pub fn add_without_style(&mut self, other: &Grads) {
        match (self, other) {
            (
                Grads::Codec {
                    theta, psi, length, ..
                },
                Grads::Codec {
                    theta: t2,
                    psi: p2,
                    length: l2,
                    ..
                },
            ) => {
                for (a, b) in theta
                    .iter_mut()
                    .chain(psi.iter_mut())
                    .chain(length.iter_mut())
                    .zip(t2.iter().chain(p2).chain(l2))
                {
                    *a += b;
                }
            }
            (Grads::Dense { rows }, Grads::Dense { rows: r2 }) => {
                for (a, b) in rows.iter_mut().zip(r2) {
                    *a += b;
                }
            }
            _ => unreachable!("gradients of two different models"),
        }
    }
}

impl Codec {
    /// `mlp` must have `decoder.k` outputs (or as many as
    /// [`Codec::with_trained_components`] sets), one more with `rotation`.
    pub fn new(mlp: Mlp, decoder: Decoder, finetune_decoder: bool, rotation: bool) -> Self {
        let (nt, np) = (mlp.param_count(), decoder.params.len());
        let trained = decoder.k;
        Codec {
            trained,
            mlp,
            decoder,
            finetune_decoder,
            rotation,
            tilt: false,
            angle_scale: ANGLE_SCALE,
            tilt_scale: ANGLE_SCALE,
            style: Vec::new(),
            part_lengths: None,
            style_scale: None,
            style_rows: None,
            adam_theta: Adam::new(nt),
            adam_psi: Adam::new(np),
        }
    }

    /// The same codec with one learned length scale per part (1 at the
    /// start, [`PartLengths`]), so the views can correct each part's length:
    /// the length estimate is one reading per part, and a part read long or
    /// short is long or short over every one of its strands.
    pub fn with_part_lengths(mut self, strands_per_part: &[usize]) -> Self {
        self.part_lengths = Some(Box::new(PartLengths::new(strands_per_part)));
        self
    }

    /// Strand `i`'s placed length: its target, times its part's learned scale.
    pub fn length(&self, prep: &Prepared, i: usize) -> f32 {
        match &self.part_lengths {
            Some(p) => prep.lengths[i] * p.scale(prep.parts[i] as usize),
            None => prep.lengths[i],
        }
    }

    /// The same codec with `angle_scale` radians per unit of its angle output.
    pub fn with_angle_scale(mut self, angle_scale: f32) -> Self {
        self.angle_scale = angle_scale;
        self
    }

    /// The same codec with a learned tilt about each frame's bitangent (one
    /// more encoder output, after the angle; `mlp` must have it), `scale`
    /// radians per unit of it.
    pub fn with_tilt(mut self, tilt: bool, scale: f32) -> Self {
        self.tilt = tilt;
        self.tilt_scale = scale;
        self
    }

    /// The same codec with per-strand style codes (`n * K`, see [`style_codes`]).
    pub fn with_style(mut self, style: Vec<f32>) -> Self {
        self.style = style;
        self
    }

    /// The same codec with one learned scale on its style codes (1 at the start,
    /// [`StyleScale`]); without style codes there is nothing to scale.
    pub fn with_style_scale(mut self) -> Self {
        if !self.style.is_empty() {
            self.style_scale = Some(Box::new(StyleScale::new()));
        }
        self
    }

    /// The same codec whose style codes' `styled` components are trained per strand
    /// ([`StyleRows`]); without style codes or styled components there is nothing to train.
    pub fn with_learned_style_codes(mut self, styled: std::ops::Range<usize>) -> Self {
        let k = self.decoder.k;
        if !self.style.is_empty() && !styled.is_empty() && styled.end <= k {
            let n = self.style.len() / k;
            self.style_rows = Some(Box::new(StyleRows {
                styled,
                adam: RowAdam::new(n, k),
            }));
        }
        self
    }

    /// The root mean square of the learned style codes over their styled components
    /// (`None` unless [`Codec::with_learned_style_codes`]).
    pub fn learned_style_rms(&self) -> Option<f32> {
        let rows = self.style_rows.as_ref()?;
        let k = self.decoder.k;
        let (mut sum, mut count) = (0.0f64, 0usize);
        for code in self.style.chunks_exact(k) {
            for &v in &code[rows.styled.clone()] {
                sum += (v as f64) * (v as f64);
                count += 1;
            }
        }
        (count > 0).then(|| (sum / count as f64).sqrt() as f32)
    }

    /// The factor on the style codes (1 unless learned).
    fn style_factor(&self) -> f32 {
        self.style_scale.as_ref().map_or(1.0, |s| s.scale())
    }

    /// The same codec whose encoder outputs codes for the first `trained`
    /// components only (clamped to the decoder's K; `mlp` must have that
    /// many outputs before the angles): the trailing components decode from
    /// the style codes alone, so training cannot put weight on shapes the
    /// views do not resolve.
    pub fn with_trained_components(mut self, trained: usize) -> Self {
        self.trained = trained.min(self.decoder.k);
        self
    }

    /// Encoder outputs per strand: the trained coefficients, then the angle
    /// and the tilt if any.
    fn stride(&self) -> usize {
        self.trained + self.rotation as usize + self.tilt as usize
    }

    /// Strand `j`'s K decoder coefficients: its encoder outputs on the
    /// trained components, plus its style codes (a constant offset, so
    /// d code / d encoder output is 1).
    fn codes(&self, out: &[f32], j: usize, strand: usize, codes: &mut [f32]) {
        let (k, t, st) = (self.decoder.k, self.trained, self.stride());
        codes[..t].copy_from_slice(&out[j * st..j * st + t]);
        codes[t..].fill(0.0);
        if !self.style.is_empty() {
            let factor = self.style_factor();
            for (a, b) in codes
                .iter_mut()
                .zip(&self.style[strand * k..(strand + 1) * k])
            {
                *a += factor * b;
            }
        }
    }

    /// Strand `j`'s in-plane turn `Rz(theta_j)` and tilt `Ry(beta_j)`
    /// (identities when not learned).
    fn turns(&self, out: &[f32], j: usize) -> (Mat3, Mat3) {
        let row = &out[j * self.stride() + self.trained..(j + 1) * self.stride()];
        let turn = match self.rotation {
            true => Mat3::from_rotation_z(self.angle_scale * row[0]),
            false => Mat3::IDENTITY,
        };
        let tilt = match self.tilt {
            true => Mat3::from_rotation_y(self.tilt_scale * row[self.rotation as usize]),
            false => Mat3::IDENTITY,
        };
        (turn, tilt)
    }

    /// Strand `j`'s frame: the root's, turned by its learned angles.
    fn frame(&self, base: Mat3, out: &[f32], j: usize) -> Mat3 {
        let (turn, tilt) = self.turns(out, j);
        base * turn * tilt
    }
}

impl Dense {
    /// Every one of `n` strands starts as the canonical strand `local` (`L`
    /// points, root first; e.g. the decoder's mean, the codec's initial
    /// strand), taken relative to its root.
    pub fn from_local(local: &[Vec3], n: usize) -> Self {
        let l = local.len();
        let mut p = Vec::with_capacity(n * (l - 1) * 3);
        for _ in 0..n {
            for q in &local[1..] {
                p.extend_from_slice(&(*q - local[0]).to_array());
            }
        }
        Dense {
            points: p,
            adam: RowAdam::new(n, (l - 1) * 3),
        }
    }

    /// Strand `i`'s canonical points (`l`, root at the origin) into `out`.
    fn local(&self, i: usize, l: usize, out: &mut [Vec3]) {
        let row = (l - 1) * 3;
        let r = &self.points[i * row..(i + 1) * row];
        out[0] = Vec3::ZERO;
        for (o, c) in out[1..].iter_mut().zip(r.chunks_exact(3)) {
            *o = Vec3::new(c[0], c[1], c[2]);
        }
    }
}

impl Model {
    /// The codec's learned scale on its style codes (`None`: dense, or a fixed scale).
    pub fn learned_style_scale(&self) -> Option<f32> {
        match self {
            Model::Codec(c) => c.style_scale.as_ref().map(|s| s.scale()),
            Model::Dense(_) => None,
        }
    }

    /// Number of optimised geometry parameters.
    pub fn parameter_count(&self) -> usize {
        match self {
            Model::Codec(c) => {
                c.mlp.param_count()
                    + if c.finetune_decoder {
                        c.decoder.params.len()
                    } else {
                        0
                    }
                    + c.part_lengths.as_ref().map_or(0, |p| p.log_scale.len())
                    + c.style_scale.is_some() as usize
                    + c.style_rows
                        .as_ref()
                        .map_or(0, |r| r.styled.len() * c.style.len() / c.decoder.k.max(1))
            }
            Model::Dense(d) => d.points.len(),
        }
    }

    /// World points of the strands in `subset` (`subset.len() * L`, root first).
    pub fn forward(&self, prep: &Prepared, subset: &[u32]) -> (Vec<Vec3>, Cache) {
        let l = prep.points;
        match self {
            Model::Codec(c) => {
                let dim = prep.feature_dim;
                let k = c.decoder.k;
                let parts: Vec<(Vec<Vec3>, CodecChunk)> = subset
                    .par_chunks(CHUNK)
                    .map(|ids| {
                        let mut x = Vec::with_capacity(ids.len() * dim);
                        for &i in ids {
                            let i = i as usize;
                            x.extend_from_slice(&prep.features[i * dim..(i + 1) * dim]);
                        }
                        let (z, tape) = c.mlp.forward(&x, ids.len());
                        let mut codes = vec![0.0f32; ids.len() * k];
                        let mut local = vec![Vec3::ZERO; ids.len() * l];
                        let mut world = vec![Vec3::ZERO; ids.len() * l];
                        for (j, &i) in ids.iter().enumerate() {
                            let i = i as usize;
                            let code = &mut codes[j * k..(j + 1) * k];
                            c.codes(&z, j, i, code);
                            let loc = &mut local[j * l..(j + 1) * l];
                            c.decoder.decode(code, loc);
                            placement::place(
                                loc,
                                prep.roots[i],
                                c.frame(prep.frames[i], &z, j),
                                c.length(prep, i),
                                &mut world[j * l..(j + 1) * l],
                            );
                        }
                        (
                            world,
                            CodecChunk {
                                tape,
                                z,
                                codes,
                                local,
                            },
                        )
                    })
                    .collect();
                let mut world = Vec::with_capacity(subset.len() * l);
                let mut chunks = Vec::with_capacity(parts.len());
                for (w, ch) in parts {
                    world.extend(w);
                    chunks.push(ch);
                }
                (world, Cache::Codec(chunks))
            }
            Model::Dense(d) => {
                let mut world = vec![Vec3::ZERO; subset.len() * l];
                let mut local = vec![Vec3::ZERO; l];
                for (j, &i) in subset.iter().enumerate() {
                    let i = i as usize;
                    d.local(i, l, &mut local);
                    placement::place(
                        &local,
                        prep.roots[i],
                        prep.frames[i],
                        prep.lengths[i],
                        &mut world[j * l..(j + 1) * l],
                    );
                }
                (world, Cache::Dense)
            }
        }
    }

    /// Parameter gradients from `grad` = d loss / d world points.
    pub fn backward(&self, prep: &Prepared, subset: &[u32], cache: &Cache, grad: &[Vec3]) -> Grads {
        let l = prep.points;
        match (self, cache) {
            (Model::Codec(c), Cache::Codec(chunks)) => {
                let (k, t, st) = (c.decoder.k, c.trained, c.stride());
                let nt = c.mlp.param_count();
                let np = c.decoder.params.len();
                let nparts = c.part_lengths.as_ref().map_or(0, |p| p.log_scale.len());
                let style_factor = c.style_scale.as_ref().map(|s| s.scale());
                let styled_rows = c.style_rows.as_ref().map(|r| r.styled.clone());
                let per_chunk: Vec<ChunkGrads> = subset
                    .par_chunks(CHUNK)
                    .zip(chunks.par_iter())
                    .zip(grad.par_chunks(CHUNK * l))
                    .map(|((ids, ch), g)| {
                        let mut gz = vec![0.0f32; ids.len() * st];
                        let mut gpsi = vec![0.0f32; np];
                        let mut glen = vec![0.0f32; nparts];
                        let mut gl = vec![Vec3::ZERO; l];
                        let mut gcode = vec![0.0f32; k];
                        let mut gstyle = 0.0f32;
                        let mut grows =
                            vec![0.0f32; styled_rows.as_ref().map_or(0, |_| ids.len() * k)];
                        for (j, &i) in ids.iter().enumerate() {
                            let i = i as usize;
                            let loc = &ch.local[j * l..(j + 1) * l];
                            let (turn, tilt) = c.turns(&ch.z, j);
                            let turned = prep.frames[i] * turn;
                            let f = turned * tilt;
                            let gj = &g[j * l..(j + 1) * l];
                            let length = c.length(prep, i);
                            placement::place_backward(loc, f, length, gj, &mut gl);
                            let scale =
                                length / (placement::arc_length(loc) + placement::PLACEMENT_EPS);
                            let part = (prep.parts[i] as usize).min(nparts);
                            let turns = c.rotation || c.tilt;
                            if part < nparts || turns {
                                // With q_k the local offset, scaled as placement scales it,
                                // world_k - root = F q_k: d world_k / d log length scale =
                                // F q_k; with F = base Rz Ry, d world_k / d theta =
                                // base Rz (e_z x Ry q_k), d world_k / d beta = F (e_y x q_k).
                                let (mut dlen, mut dtheta, mut dbeta) = (0.0f32, 0.0f32, 0.0f32);
                                for (q, gk) in loc.iter().zip(gj) {
                                    let q = scale * (*q - loc[0]);
                                    dlen += gk.dot(f * q);
                                    if turns {
                                        dtheta += gk.dot(turned * Vec3::Z.cross(tilt * q));
                                        dbeta += gk.dot(f * Vec3::Y.cross(q));
                                    }
                                }
                                if let Some(gp) = glen.get_mut(part) {
                                    *gp += dlen;
                                }
                                let at = j * st + t;
                                if c.rotation {
                                    gz[at] = c.angle_scale * dtheta;
                                }
                                if c.tilt {
                                    gz[at + c.rotation as usize] = c.tilt_scale * dbeta;
                                }
                            }
                            c.decoder.backward(
                                &ch.codes[j * k..(j + 1) * k],
                                &gl,
                                &mut gcode,
                                c.finetune_decoder.then_some(&mut gpsi[..]),
                            );
                            gz[j * st..j * st + t].copy_from_slice(&gcode[..t]);
                            if let Some(factor) = style_factor {
                                // code = encoder output + factor * style: d code / d log
                                // factor = factor * style.
                                let style = &c.style[i * k..(i + 1) * k];
                                gstyle += factor
                                    * gcode.iter().zip(style).map(|(g, e)| g * e).sum::<f32>();
                            }
                            if let Some(styled) = &styled_rows {
                                // code = encoder output + factor * style: d code / d style =
                                // factor, on the styled components only.
                                let factor = style_factor.unwrap_or(1.0);
                                let row = &mut grows[j * k..(j + 1) * k];
                                for m in styled.clone() {
                                    row[m] = factor * gcode[m];
                                }
                            }
                        }
                        let mut gt = vec![0.0f32; nt];
                        c.mlp.backward(&ch.tape, &gz, &mut gt);
                        (gt, gpsi, glen, gstyle, grows)
                    })
                    .collect();
                let mut theta = vec![0.0f32; nt];
                let mut psi = vec![0.0f32; np];
                let mut length = vec![0.0f32; nparts];
                let mut style = vec![0.0f32; style_factor.is_some() as usize];
                let mut style_codes = Vec::new();
                for (gt, gp, gl, gs, gr) in per_chunk {
                    style_codes.extend(gr);
                    for (a, b) in theta.iter_mut().zip(&gt) {
                        *a += b;
                    }
                    for (a, b) in psi.iter_mut().zip(&gp) {
                        *a += b;
                    }
                    for (a, b) in length.iter_mut().zip(&gl) {
                        *a += b;
                    }
                    if let Some(a) = style.first_mut() {
                        *a += gs;
                    }
                }
                Grads::Codec {
                    theta,
                    psi,
                    length,
                    style,
                    style_codes,
                }
            }
            (Model::Dense(d), _) => {
                let mut rows = Vec::with_capacity(subset.len() * (l - 1) * 3);
                let mut local = vec![Vec3::ZERO; l];
                let mut gl = vec![Vec3::ZERO; l];
                for (s, &i) in subset.iter().enumerate() {
                    let i = i as usize;
                    d.local(i, l, &mut local);
                    placement::place_backward(
                        &local,
                        prep.frames[i],
                        prep.lengths[i],
                        &grad[s * l..(s + 1) * l],
                        &mut gl,
                    );
                    for q in &gl[1..] {
                        rows.extend_from_slice(&q.to_array());
                    }
                }
                Grads::Dense { rows }
            }
            (Model::Codec(_), Cache::Dense) => Grads::Codec {
                theta: Vec::new(),
                psi: Vec::new(),
                length: Vec::new(),
                style: Vec::new(),
                style_codes: Vec::new(),
            },
        }
    }

    /// One Adam step.
    pub fn step(&mut self, grads: &Grads, subset: &[u32], rates: Rates) {
        match (self, grads) {
            (
                Model::Codec(c),
                Grads::Codec {
                    theta,
                    psi,
                    length,
                    style,
                    style_codes,
                },
            ) => {
                c.adam_theta.step(&mut c.mlp.params, theta, rates.encoder);
                if c.finetune_decoder {
                    c.adam_psi.step(&mut c.decoder.params, psi, rates.decoder);
                }
                if let Some(p) = c.part_lengths.as_mut() {
                    p.step(length, rates.length);
                }
                if let Some(s) = c.style_scale.as_mut() {
                    s.step(style, rates.style);
                }
                if let Some(r) = c.style_rows.as_mut() {
                    r.adam
                        .step(&mut c.style, style_codes, subset, rates.style_codes);
                }
            }
            (Model::Dense(d), Grads::Dense { rows }) => {
                d.adam.step(&mut d.points, rows, subset, rates.points);
            }
            _ => {}
        }
    }

    /// All strands (`n * L` points), computed in chunks without keeping tapes.
    pub fn all_points(&self, prep: &Prepared) -> Vec<Vec3> {
        let n = prep.len() as u32;
        let mut out = Vec::with_capacity(prep.len() * prep.points);
        let ids: Vec<u32> = (0..n).collect();
        for block in ids.chunks(CHUNK * 32) {
            out.extend(self.forward(prep, block).0);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codec_backward_matches_finite_differences() {
        check_codec_gradients(false, false, 0.0);
    }

    #[test]
    fn codec_backward_with_learned_rotation_matches_finite_differences() {
        check_codec_gradients(true, false, 0.0);
    }

    #[test]
    fn a_positive_tilt_lays_the_strand_toward_the_skin_in_its_own_plane() {
        let l = 5;
        let mean: Vec<Vec3> = (0..l)
            .map(|i| Vec3::new(0.3, 0.0, 0.9) * i as f32 / 4.0)
            .collect();
        let comps = vec![(0..l).map(|i| Vec3::Y * i as f32 * 0.1).collect::<Vec<_>>()];
        let pe = PositionalEncoding::new(1, [-1.0; 3], [1.0; 3]);
        let inputs = RootInputs {
            positions: vec![Vec3::ZERO],
            frames: vec![Mat3::IDENTITY],
            lengths: vec![1.0],
            parts: vec![0],
            rho: vec![0.5],
        };
        let prep = Prepared::new(l, inputs, 1, &pe);
        let elevation = |tilt_out: f32| -> f32 {
            // Outputs: one code, then the tilt; the output layer's last
            // bias is the tilt's.
            let mut mlp = Mlp::new(prep.feature_dim, 4, 1, 2, 3);
            *mlp.params.last_mut().unwrap() = tilt_out;
            let m = Model::Codec(
                Codec::new(mlp, Decoder::new(&mean, &comps), false, false).with_tilt(true, 2.0),
            );
            let (p, _) = m.forward(&prep, &[0]);
            let tip = p[l - 1] - p[0];
            assert!(
                tip.y.abs() < 1e-6,
                "the tilt leaves the strand in its plane: {tip}"
            );
            tip.z.atan2(tip.x)
        };
        let (before, after) = (elevation(0.0), elevation(0.25));
        // 0.25 units at 2 radians per unit: half a radian lower.
        assert!((before - 0.9f32.atan2(0.3)).abs() < 1e-5, "{before}");
        assert!((before - after - 0.5).abs() < 1e-5, "{before} -> {after}");
    }

    #[test]
    fn codec_backward_with_learned_rotation_and_tilt_matches_finite_differences() {
        check_codec_gradients(true, true, 0.0);
        check_codec_gradients(false, true, 0.0);
    }

    #[test]
    fn codec_backward_with_style_codes_matches_finite_differences() {
        // The decoder's gradient depends on the code it decoded: the styled one.
        check_codec_gradients(true, true, 0.7);
    }

    #[test]
    fn style_codes_are_per_strand_streams_with_the_asked_spread() {
        assert!(style_codes(10, 4, 0, 0, 0.0, 1).is_empty());
        assert!(style_codes(10, 4, 4, 0, 0.5, 1).is_empty());
        assert!(style_codes(10, 4, 2, 2, 0.5, 1).is_empty());
        let a = style_codes(5000, 3, 0, 0, 0.5, 7);
        let b = style_codes(20, 3, 0, 0, 0.5, 7);
        // Strand i's code does not depend on how many strands there are.
        assert_eq!(&a[..60], &b[..]);
        assert_ne!(style_codes(20, 3, 0, 0, 0.5, 8), b);
        assert_eq!(
            style_codes(20, 3, 0, 3, 0.5, 7),
            b,
            "to = k styles every component"
        );
        // Skipping the leading components zeroes them and keeps the others.
        let skipped = style_codes(20, 3, 2, 0, 0.5, 7);
        for (j, (&s, &full)) in skipped.iter().zip(&b).enumerate() {
            assert_eq!(s, if j % 3 < 2 { 0.0 } else { full }, "entry {j}");
        }
        // Ending them early zeroes the trailing ones and keeps the same draws in between.
        let band = style_codes(20, 3, 1, 2, 0.5, 7);
        for (j, (&s, &full)) in band.iter().zip(&b).enumerate() {
            assert_eq!(s, if j % 3 == 1 { full } else { 0.0 }, "entry {j}");
        }
        let n = a.len() as f64;
        let mean = a.iter().map(|&x| x as f64).sum::<f64>() / n;
        let sd = (a.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / n).sqrt();
        assert!(mean.abs() < 0.02 && (sd - 0.5).abs() < 0.02, "{mean} {sd}");
    }

    fn check_codec_gradients(rotation: bool, tilt: bool, style: f32) {
        check_codec_gradients_with(rotation, tilt, style, false);
    }

    #[test]
    fn codec_backward_with_learned_part_lengths_matches_finite_differences() {
        check_codec_gradients_with(true, false, 0.5, true);
    }

    #[test]
    fn added_gradients_skip_only_the_style_scale() {
        let codec = |v: f32| Grads::Codec {
            theta: vec![v; 3],
            psi: vec![2.0 * v; 2],
            length: vec![3.0 * v; 2],
            style: vec![4.0 * v],
            style_codes: vec![5.0 * v; 2],
        };
        let mut g = codec(1.0);
        g.add_without_style(&codec(10.0));
        let Grads::Codec {
            theta,
            psi,
            length,
            style,
            style_codes,
        } = g
        else {
            unreachable!()
        };
        assert_eq!(
            (theta, psi, length, style, style_codes),
            (
                vec![11.0; 3],
                vec![22.0; 2],
                vec![33.0; 2],
                vec![4.0],
                vec![5.0; 2]
            )
        );
        let mut d = Grads::Dense {
            rows: vec![1.0, 2.0],
        };
        d.add_without_style(&Grads::Dense {
            rows: vec![3.0, 4.0],
        });
        assert!(matches!(d, Grads::Dense { rows } if rows == vec![4.0, 6.0]));
    }

    #[test]
    fn codec_backward_with_learned_style_scale_matches_finite_differences() {
        check_codec_gradients_full(true, false, 0.7, false, 2, true, false);
    }

    #[test]
    fn codec_backward_with_learned_style_codes_matches_finite_differences() {
        // One trained component, the second styled and learned per strand, under a learned
        // style scale: every factor of the style codes' gradient is exercised.
        check_codec_gradients_full(true, false, 0.7, false, 1, true, true);
    }

    #[test]
    fn learned_style_codes_move_only_the_sampled_strands_styled_components() {
        let l = 3;
        let mean: Vec<Vec3> = (0..l).map(|i| Vec3::Z * i as f32).collect();
        let comps: Vec<Vec<Vec3>> = (1..=3)
            .map(|c| (0..l).map(|i| Vec3::X * (i * c) as f32 * 0.1).collect())
            .collect();
        let pe = PositionalEncoding::new(1, [-1.0; 3], [1.0; 3]);
        let n = 4;
        let prep = Prepared::new(l, roots_in_a_row(vec![0; n]), 1, &pe);
        let mlp = Mlp::new(prep.feature_dim, 4, 1, 3, 3);
        let codec = Codec::new(mlp, Decoder::new(&mean, &comps), false, false)
            .with_style(style_codes(n, 3, 1, 0, 1.0, 5))
            .with_learned_style_codes(1..3);
        let before = codec.style.clone();
        let mut model = Model::Codec(codec);
        let subset = [1u32, 3];
        let (_, cache) = model.forward(&prep, &subset);
        let pull = vec![Vec3::X; subset.len() * l];
        let grads = model.backward(&prep, &subset, &cache, &pull);
        let rates = Rates {
            style_codes: 0.1,
            ..rates_for_test()
        };
        model.step(&grads, &subset, rates);
        let Model::Codec(c) = &model else {
            unreachable!()
        };
        for i in 0..n {
            for m in 0..3 {
                let moved = c.style[i * 3 + m] != before[i * 3 + m];
                let should = subset.contains(&(i as u32)) && m >= 1;
                assert_eq!(moved, should, "strand {i}, component {m}");
            }
        }
        assert!(model.parameter_count() >= n * 2);
        let rms = c
            .learned_style_rms()
            .expect("learned codes report their spread");
        assert!(rms.is_finite() && rms > 0.0);
        // Without style codes there is nothing to learn.
        let plain = Codec::new(
            Mlp::new(prep.feature_dim, 4, 1, 3, 3),
            Decoder::new(&mean, &comps),
            false,
            false,
        )
        .with_learned_style_codes(1..3);
        assert!(plain.style_rows.is_none());
    }

    #[test]
    fn codec_backward_with_untrained_trailing_components_matches_finite_differences() {
        check_codec_gradients_trained(true, true, 0.5, true, 1);
    }

    fn check_codec_gradients_with(rotation: bool, tilt: bool, style: f32, lengths: bool) {
        check_codec_gradients_trained(rotation, tilt, style, lengths, 2);
    }

    // Finite differences perturb parameter i and read gradient i. The codec's
    // basis has two components, the encoder outputs codes for `trained` of them.
    fn check_codec_gradients_trained(
        rotation: bool,
        tilt: bool,
        style: f32,
        lengths: bool,
        trained: usize,
    ) {
        check_codec_gradients_full(rotation, tilt, style, lengths, trained, false, false);
    }

    fn check_codec_gradients_full(
        rotation: bool,
        tilt: bool,
        style: f32,
        lengths: bool,
        trained: usize,
        style_scale: bool,
        learned_codes: bool,
    ) {
        // A tiny codec; loss = sum w . points over a subset.
        let l = 4;
        let mean: Vec<Vec3> = (0..l).map(|i| Vec3::Z * i as f32 / 3.0).collect();
        let comps = vec![
            (0..l)
                .map(|i| Vec3::X * (i * i) as f32 * 0.1)
                .collect::<Vec<_>>(),
            (0..l).map(|i| Vec3::Y * i as f32 * 0.2).collect(),
        ];
        let pe = PositionalEncoding::new(2, [-1.0; 3], [1.0; 3]);
        let roots = vec![
            Vec3::new(0.1, 0.2, 0.3),
            Vec3::new(-0.4, 0.5, 0.0),
            Vec3::ONE * 0.3,
        ];
        // Root frames that are not the identity, so the gradients' frame
        // products are checked too.
        let frames = vec![
            Mat3::IDENTITY,
            Mat3::from_rotation_x(0.4),
            Mat3::from_rotation_z(-0.9) * Mat3::from_rotation_y(0.3),
        ];
        let inputs = RootInputs {
            positions: roots,
            frames,
            lengths: vec![0.5, 0.7, 0.3],
            parts: vec![0, 1, 1],
            rho: vec![0.1, 0.5, 0.9],
        };
        let prep = Prepared::new(l, inputs, 2, &pe);
        let mut mlp = Mlp::new(
            prep.feature_dim,
            6,
            2,
            trained + rotation as usize + tilt as usize,
            9,
        );
        for (i, w) in mlp.params.iter_mut().enumerate().rev().take(21) {
            *w = ((i * 7919) % 13) as f32 / 13.0 - 0.5;
        }
        let mut codec = Codec::new(mlp, Decoder::new(&mean, &comps), true, rotation)
            .with_tilt(tilt, 1.7)
            .with_style(style_codes(3, 2, 0, 0, style, 4))
            .with_trained_components(trained);
        if lengths {
            codec = codec.with_part_lengths(&[1, 2]);
            codec.part_lengths.as_mut().unwrap().log_scale = vec![0.2, -0.3];
        }
        if style_scale {
            codec = codec.with_style_scale();
            codec.style_scale.as_mut().unwrap().log_scale = vec![0.4];
        }
        if learned_codes {
            codec = codec.with_learned_style_codes(1..2);
        }
        let mut model = Model::Codec(codec);
        let subset = [0u32, 2];
        let w: Vec<Vec3> = (0..subset.len() * l)
            .map(|i| Vec3::new((i % 3) as f32 - 1.0, 0.5, (i % 2) as f32))
            .collect();
        let f = |m: &Model| -> f64 {
            let (p, _) = m.forward(&prep, &subset);
            p.iter().zip(&w).map(|(a, b)| a.dot(*b) as f64).sum()
        };
        let (_, cache) = model.forward(&prep, &subset);
        let grads = model.backward(&prep, &subset, &cache, &w);
        let Grads::Codec {
            theta,
            psi,
            length,
            style: style_grad,
            style_codes: code_grad,
        } = grads
        else {
            panic!()
        };
        assert_eq!(length.len(), if lengths { 2 } else { 0 });
        assert_eq!(style_grad.len(), style_scale as usize);
        assert_eq!(
            code_grad.len(),
            if learned_codes { subset.len() * 2 } else { 0 }
        );
        let h = 1e-2f32;
        let Model::Codec(c) = &mut model else {
            panic!()
        };
        let nt = c.mlp.param_count();
        for i in (0..nt).step_by(5) {
            let o = c.mlp.params[i];
            c.mlp.params[i] = o + h;
            let fp = f(&Model::Codec(c.clone()));
            c.mlp.params[i] = o - h;
            let fm = f(&Model::Codec(c.clone()));
            c.mlp.params[i] = o;
            let fd = (fp - fm) / (2.0 * h as f64);
            assert!(
                (fd - theta[i] as f64).abs() < 1e-2 * (1.0 + fd.abs()),
                "theta {i}: {fd} vs {}",
                theta[i]
            );
        }
        for (i, &g) in psi.iter().enumerate() {
            let o = c.decoder.params[i];
            c.decoder.params[i] = o + h;
            let fp = f(&Model::Codec(c.clone()));
            c.decoder.params[i] = o - h;
            let fm = f(&Model::Codec(c.clone()));
            c.decoder.params[i] = o;
            let fd = (fp - fm) / (2.0 * h as f64);
            assert!(
                (fd - g as f64).abs() < 1e-2 * (1.0 + fd.abs()),
                "psi {i}: {fd} vs {g}"
            );
        }
        for (i, &g) in length.iter().enumerate() {
            let fd = central_difference(c, &f, h, |c| {
                &mut c.part_lengths.as_mut().unwrap().log_scale[i]
            });
            assert_scalar_gradient(&format!("part {i}"), fd, g);
        }
        if let Some(&g) = style_grad.first() {
            let fd = central_difference(c, &f, h, |c| {
                &mut c.style_scale.as_mut().unwrap().log_scale[0]
            });
            assert_scalar_gradient("style scale", fd, g);
        }
        for (j, &i) in subset.iter().enumerate().filter(|_| learned_codes) {
            // Component 1 is learned; component 0 stays as drawn (a zero row entry).
            assert_eq!(code_grad[j * 2], 0.0);
            let g = code_grad[j * 2 + 1];
            let fd = central_difference(c, &f, h, |c| &mut c.style[i as usize * 2 + 1]);
            assert_scalar_gradient(&format!("style code of strand {i}"), fd, g);
        }
    }

    fn rates_for_test() -> Rates {
        Rates {
            encoder: 0.0,
            decoder: 0.0,
            points: 0.0,
            length: 0.1,
            style: 0.0,
            style_codes: 0.0,
        }
    }

    /// Roots 0.1 apart along x with identity frames, unit lengths and the given parts.
    fn roots_in_a_row(parts: Vec<u16>) -> RootInputs {
        let n = parts.len();
        RootInputs {
            positions: (0..n).map(|i| Vec3::X * i as f32 * 0.1).collect(),
            frames: vec![Mat3::IDENTITY; n],
            lengths: vec![1.0; n],
            parts,
            rho: vec![0.5; n],
        }
    }

    #[test]
    fn learned_part_lengths_move_length_between_parts_not_the_coats_total() {
        let l = 3;
        let mean: Vec<Vec3> = (0..l).map(|i| Vec3::Z * i as f32).collect();
        let comps = vec![(0..l).map(|i| Vec3::X * i as f32 * 0.1).collect::<Vec<_>>()];
        let pe = PositionalEncoding::new(1, [-1.0; 3], [1.0; 3]);
        let n = 4;
        let prep = Prepared::new(l, roots_in_a_row(vec![0, 0, 0, 1]), 2, &pe);
        let mlp = Mlp::new(prep.feature_dim, 4, 1, 1, 3);
        let mut model = Model::Codec(
            Codec::new(mlp, Decoder::new(&mean, &comps), false, false).with_part_lengths(&[3, 1]),
        );
        // Pull every tip away from its root: left free, both parts would lengthen.
        let subset: Vec<u32> = (0..n as u32).collect();
        let (_, cache) = model.forward(&prep, &subset);
        let grad: Vec<Vec3> = (0..n * l).map(|k| -Vec3::Z * (k % l) as f32).collect();
        let grads = model.backward(&prep, &subset, &cache, &grad);
        let Grads::Codec { length, .. } = &grads else {
            panic!()
        };
        assert!(length.iter().all(|&g| g < 0.0), "{length:?}");
        // Every strand pulled alike: Adam steps every part alike, and removing the coat's mean
        // step leaves none moved.
        for _ in 0..5 {
            model.step(&grads, &subset, rates_for_test());
        }
        let Model::Codec(c) = &model else { panic!() };
        let s = &c.part_lengths.as_ref().unwrap().log_scale;
        assert!(s.iter().all(|s| s.abs() < 1e-6), "{s:?}");
        // Part 1's strand pulled the other way: it shortens, part 0 lengthens.
        let mut grad_1 = grad.clone();
        for g in &mut grad_1[3 * l..] {
            *g *= -1.0;
        }
        let grads = model.backward(&prep, &subset, &cache, &grad_1);
        for _ in 0..5 {
            model.step(&grads, &subset, rates_for_test());
        }
        let Model::Codec(c) = &model else { panic!() };
        let s = &c.part_lengths.as_ref().unwrap().log_scale;
        assert!((0.75 * s[0] + 0.25 * s[1]).abs() < 1e-6, "{s:?}");
        let lengths: Vec<f32> = (0..n).map(|i| c.length(&prep, i)).collect();
        assert!(lengths[3] < 1.0 && lengths[0] > 1.0, "{lengths:?}");
    }

    /// d f / d the parameter `at` points to, by central differences of step `h`.
    fn central_difference(
        c: &mut Codec,
        f: &impl Fn(&Model) -> f64,
        h: f32,
        at: impl Fn(&mut Codec) -> &mut f32,
    ) -> f64 {
        let o = *at(c);
        *at(c) = o + h;
        let fp = f(&Model::Codec(c.clone()));
        *at(c) = o - h;
        let fm = f(&Model::Codec(c.clone()));
        *at(c) = o;
        (fp - fm) / (2.0 * h as f64)
    }

    /// A scalar parameter's gradient `g` against its finite difference `fd`, which must not
    /// vanish (the check would pass on a zero gradient).
    fn assert_scalar_gradient(name: &str, fd: f64, g: f32) {
        assert!(fd.abs() > 1e-3, "{name}: the check needs a gradient");
        assert!(
            (fd - g as f64).abs() < 1e-2 * (1.0 + fd.abs()),
            "{name}: {fd} vs {g}"
        );
    }

    #[test]
    fn the_style_scale_rises_when_pulled_up_and_stays_at_one_when_pulled_down() {
        let mut s = StyleScale::new();
        for _ in 0..10 {
            s.step(&[1.0], 0.1);
        }
        assert_eq!(s.scale(), 1.0);
        // Adam's momentum first spends the ten steps down, then the scale climbs.
        for _ in 0..30 {
            s.step(&[-1.0], 0.1);
        }
        assert!(s.scale() > 1.5, "{}", s.scale());
    }

    #[test]
    fn lazy_adam_updates_only_sampled_rows() {
        let mut p = vec![1.0f32; 6];
        let mut a = RowAdam::new(3, 2);
        a.step(&mut p, &[1.0, -1.0], &[1], 0.1);
        assert_eq!(&p[0..2], &[1.0, 1.0]);
        assert!((p[2] - 0.9).abs() < 1e-6 && (p[3] - 1.1).abs() < 1e-6);
        assert_eq!(&p[4..6], &[1.0, 1.0]);
    }
}

#[cfg(test)]
mod sized {
    //! Tests at the tiger's sizes: 64 x 3 encoder, 10 frequencies, 6 parts,
    //! L = 8, 21 components.
    use super::*;

    /// A codec with non-zero output weights over `n` roots.
    fn tiger_sized(n: usize) -> (Prepared, Model) {
        let l = 8;
        let pe = PositionalEncoding::new(10, [-1.0; 3], [1.0; 3]);
        let roots: Vec<Vec3> = (0..n)
            .map(|i| {
                let t = i as f32 * 0.618;
                Vec3::new(t.sin(), (1.3 * t).cos(), (0.7 * t).sin())
            })
            .collect();
        let parts: Vec<u16> = (0..n).map(|i| (i % 6) as u16).collect();
        let rho: Vec<f32> = (0..n).map(|i| (i % 11) as f32 / 10.0).collect();
        let inputs = RootInputs {
            positions: roots,
            frames: vec![Mat3::IDENTITY; n],
            lengths: vec![0.04; n],
            parts,
            rho,
        };
        let prep = Prepared::new(l, inputs, 6, &pe);
        let mean: Vec<Vec3> = (0..l).map(|i| Vec3::Z * i as f32 / 7.0).collect();
        let comps: Vec<Vec<Vec3>> = (0..21)
            .map(|c| {
                (0..l)
                    .map(|i| Vec3::new((c + i) as f32 * 0.01, 0.02, 0.0))
                    .collect()
            })
            .collect();
        let mut mlp = Mlp::new(prep.feature_dim, 64, 3, 21, 1);
        for (i, w) in mlp.params.iter_mut().enumerate().rev().take(64 * 21) {
            *w = ((i * 7919) % 13) as f32 / 130.0 - 0.05;
        }
        let model = Model::Codec(Codec::new(mlp, Decoder::new(&mean, &comps), true, false));
        (prep, model)
    }

    fn point_grads(count: usize) -> Vec<Vec3> {
        (0..count)
            .map(|i| Vec3::new((i % 5) as f32 * 0.1 - 0.2, (i % 3) as f32 * 0.3, -0.1))
            .collect()
    }

    /// Forward and backward give the same bits on one and on two threads
    /// (fixed chunks, per-chunk gradients summed in chunk order).
    #[test]
    fn codec_results_do_not_depend_on_the_thread_count() {
        let (prep, model) = tiger_sized(1200);
        // Five chunks, the last one partial, in a scrambled order.
        let subset: Vec<u32> = (0..4 * CHUNK as u32 + 37).map(|i| (i * 7) % 1200).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let (p, cache) = model.forward(&prep, &subset);
                let g = point_grads(p.len());
                let Grads::Codec { theta, psi, .. } = model.backward(&prep, &subset, &cache, &g)
                else {
                    panic!("codec gradients expected")
                };
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>();
                let pts: Vec<f32> = p.iter().flat_map(|q| q.to_array()).collect();
                (bits(&pts), bits(&theta), bits(&psi))
            })
        };
        let one = run(1);
        let two = run(2);
        assert!(one.1.iter().any(|&b| f32::from_bits(b) != 0.0));
        assert!(one.2.iter().any(|&b| f32::from_bits(b) != 0.0));
        assert_eq!(one.0, two.0, "points differ between 1 and 2 threads");
        assert_eq!(
            one.1, two.1,
            "encoder gradients differ between 1 and 2 threads"
        );
        assert_eq!(
            one.2, two.2,
            "decoder gradients differ between 1 and 2 threads"
        );
    }
}
