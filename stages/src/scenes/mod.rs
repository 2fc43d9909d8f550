//! Where the inputs come from in experiments: synthetic furry animals with ground truth, and
//! controlled damage to a capture's views for stability sweeps.

pub mod corrupt;
pub mod synthetic;
