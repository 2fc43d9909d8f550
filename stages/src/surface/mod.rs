//! Phase 1 of the method: the furry envelope M_outer from the views, its body parts and the
//! protected (bald) set, and, for a capture without labels, a fitted template that gives them.

pub mod fit_template;
pub mod outer_surface;
pub mod parts;
