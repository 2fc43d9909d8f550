//! Where the inputs come from: synthetic furry animals with ground truth, controlled damage to a
//! capture's views for stability sweeps, and a capture's views as the stages work on them (pinhole
//! cameras, a working resolution).

pub mod corrupt;
pub mod synthetic;
pub mod working_views;
