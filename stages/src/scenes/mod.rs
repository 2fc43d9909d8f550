//! Where the inputs come from: synthetic furry animals with ground truth, controlled damage to a
//! capture's views for stability sweeps, and a capture's views at the working resolution.

pub mod corrupt;
pub mod resize;
pub mod synthetic;
