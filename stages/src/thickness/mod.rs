//! Phase 2 of the method: how thick the fur is. Gaussian Frosting's shell widths (the cue), the
//! bounded defurring solve that turns them into the root surface M_root (and NeuralFur's
//! defurring for comparison), and the per-part strand lengths with the metric scale.

pub mod defur;
pub mod frosting;
pub mod lengths;
