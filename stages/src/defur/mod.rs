//! Frosting-calibrated defurring (in progress).

pub mod lbfgsb;
pub mod objective;
pub mod thickness;
