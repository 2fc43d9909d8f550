//! Codec strand learning (FurE) and the dense baseline (method.md sections 7
//! and 8): stages `codec_strands` and `dense_strands`.
//!
//! # Design
//!
//! Both stages share one loop ([`train`]) and differ only in the strand model
//! ([`model::Model`]):
//! - **codec**: `z_i = E_theta(gamma(r_i), one-hot part, rho_i, l_i / l_max)`
//!   ([`mlp`]: NeRF positional encoding with `pe_frequencies` octaves over the
//!   box of M_outer, an MLP with SiLU hidden layers and a linear output, all
//!   gradients hand-written and checked against finite differences); decoder
//!   `D_psi(z) = mean + sum_k z_k C_k`, initialised from the `basis` input and
//!   fine-tuned (`psi` = mean and components, own learning rate); placement
//!   `s_ik = r_i + len_i T_i (s^_ik - s^_i1) / (a_i + eps)` ([`placement`]),
//!   so every strand has exactly its target length whatever theta and psi do.
//! - **dense**: the `L - 1` non-root points of every strand are free
//!   parameters (in the root's canonical frame), initialised to exactly the
//!   codec's initial strands (the encoder's output layer starts at zero, so
//!   every initial strand is the decoder mean placed on its root), and placed
//!   by the same equation, so every strand keeps its length as in NeuralFur
//!   (whose decoded strands are normalised to unit arc length and scaled to
//!   the part length). With world-space points and no length constraint
//!   (the first version) the dense strands stretched toward the envelope
//!   (mean 8.1 cm for 3.8 cm targets after 1,200 iterations) and its F-score
//!   peaked at ~30 s and then declined as precision fell.
//!
//! Each iteration samples `strands_per_iteration` strands (seeded), renders
//! them as segment Gaussians together with fixed body occluders ([`image`]),
//! evaluates L_rgb, L_sil, L_ori, L_mask against the training views and
//! L_chm, L_sdf against distance grids ([`geomloss`]), back-propagates to the
//! points, then to the model, and takes one Adam step.
//!
//! # Choices where the paper is vague
//! - L_chm is a one-sided chamfer from strand tips to M_outer; L_sdf a hinge on
//!   the signed distance to M_root; both normalised by the mean strand length
//!   (see [`geomloss`]).
//! - Loss weights. NeuralFur's run script uses orientation 1000, mask 0.1,
//!   chamfer 20, sdf 1 on its own loss normalisations. Ours are
//!   dimensionless means (the orientation term is a mean angle error in radians
//!   over confident fur pixels, the others mean absolute differences or
//!   normalised distances), so the raw numbers do not carry over. The defaults
//!   (rgb 1, sil 0.1, ori 0.1, chm 0.1, sdf 1, mask 0.1) were chosen on the
//!   synthetic tiger: at 256 px the Gabor maps respond to the tiger's stripes
//!   as much as to strands, and the visual hull overestimates the envelope in
//!   concave regions, so heavy orientation or chamfer weights pulled strands
//!   away from the ground truth there while lowering the losses.
//! - Subset rendering: only the sampled strands are rendered (as in NeuralFur);
//!   widths are the roots' widths, unscaled.
//! - Appearance: one RGB colour per strand (lazy Adam on sampled strands) and
//!   one per body occluder, the same for both methods; reported separately
//!   from the geometry parameters (`optimised_parameters`).
//! - Dense optimiser: lazy Adam (per-strand step counts, only sampled strands
//!   move), learning rate `lr_points` in strand lengths (the canonical points
//!   of a strand have unit arc length at the start). Training budget: 3,600
//!   iterations by default, 12x the codec's 300, as the paper trains its dense
//!   baseline 12x longer (10.5 h vs 52 min); one iteration costs about the same
//!   for both methods here (rendering dominates). Each strand is then sampled
//!   ~270 times (4,000 of ~52,500 per iteration). `lr_points` sweep on the
//!   synthetic tiger at that budget (final strands, F-score at 2/3/4 cm):
//!   0.003: 40.8 / 60.9 / 77.0; 0.01: 40.8 / 58.9 / 73.8; 0.03: 37.1 / 55.3 /
//!   70.9. The default is the best final F-score, 0.003. Every rate peaks
//!   early (3 cm F 74.6 at iteration 175, 75.4 at 39, 76.5 at 12) and then
//!   drifts down: the losses' optimum is not the GT fur (the README's
//!   speed-accuracy section), so more budget does not help the baseline.
//! - Ablations (`length_mode`): `defurred` = per-root lengths from the roots
//!   input on M_root (full method); `fixed` = one length for every fur root,
//!   `fixed_length_cm` or by default the mean over fur parts of each part's
//!   mean root length; `shape_prior` = no defurred mesh: roots snapped to
//!   their closest points on M_outer with frames re-orthonormalised around
//!   M_outer's normals, M_outer also serving as the body for L_sdf and the
//!   occluders, lengths from the roots input (the part lengths, which the
//!   method estimates independently of defurring).
//!
//! # Determinism
//! Seeded initialisation, subset and view sampling; fixed-chunk parallel
//! reductions combined in chunk order; the final strands do not depend on
//! timing. Snapshots are taken at 0 s and then at geometrically spaced
//! training wall times (`snapshot_first_seconds` x `snapshot_growth`^k, clock
//! paused while writing; see [`train`]), so which iterations they show varies
//! with the machine: the one documented exception.

pub mod geomloss;
pub mod image;
pub mod mlp;
pub mod model;
pub mod placement;
pub mod stage;
pub mod train;

pub use stage::{CodecStrands, DenseStrands};
