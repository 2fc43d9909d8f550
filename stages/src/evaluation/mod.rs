//! Measuring the result: per-run evaluation against ground truth (metrics only: ground truth
//! reaches nothing else), and the aggregate reports over sweeps (speed against accuracy, the
//! benchmark suite, stability under corrupted views) with their charts.

pub mod benchmark;
pub mod charts;
pub mod evaluate;
pub mod seams;
pub mod speed_accuracy;
pub mod stability;
pub mod targets;
