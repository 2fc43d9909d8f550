//! Codec strand learning (FurE) and the dense baseline (method.md section 7).

pub mod geomloss;
pub mod mlp;
pub mod placement;
