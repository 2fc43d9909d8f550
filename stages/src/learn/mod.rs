//! Codec strand learning (FurE) and the dense baseline (method.md section 7).

pub mod geomloss;
pub mod image;
pub mod mlp;
pub mod model;
pub mod placement;
pub mod stage;
pub mod train;

pub use stage::{CodecStrands, DenseStrands};
