//! Frosting-calibrated defurring (in progress).

pub mod lbfgsb;
