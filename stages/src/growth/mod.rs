//! Phase 3 of the method: growing the strands. Roots with local frames on M_root, Gabor
//! orientation maps from the views, the PCA strand basis, the learners (the FurE codec and the
//! dense per-strand baseline) and the groom export.

pub mod groom;
pub mod learn;
pub mod orientation;
pub mod roots;
pub mod strand_basis;
pub mod view_axes;
