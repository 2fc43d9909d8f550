//! The reconstruction stages of fure and the data they exchange.
//!
//! The modules follow the method: [`data`] (plain structs) and [`formats`] (their files),
//! shared [`maths`] and the differentiable [`render`]er, then the stages by phase:
//! [`surface`] (M_outer, parts), [`thickness`] (Frosting, defurring, lengths), [`growth`]
//! (roots, orientation, strand basis, learners, groom), [`evaluation`] (metrics and the
//! reports over sweeps), and [`scenes`] (synthetic animals, corrupted views) for experiments.
//! A stage module is named after its stage kind. The engine reaches this crate only through
//! [`registry`] and the contract in `fure_stage_api`.

// `!(x > 0.0)` is this crate's idiom for "not a positive number": unlike
// `x <= 0.0` it also rejects NaN, which is the point of those checks.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod data;
pub mod formats;
pub mod maths;
pub mod render;

pub mod evaluation;
pub mod growth;
pub mod scenes;
pub mod surface;
pub mod thickness;

pub mod demo;

use fure_stage_api::Stage;

/// Every stage kind this crate provides.
pub fn registry() -> Vec<Box<dyn Stage>> {
    // One entry per stage kind, alphabetical by module path.
    vec![
        Box::new(demo::DemoConcat),
        Box::new(demo::DemoNumbers),
        Box::new(demo::DemoSleep),
        Box::new(demo::DemoSum),
        Box::new(evaluation::benchmark::BenchmarkReport),
        Box::new(evaluation::evaluate::Evaluate),
        Box::new(evaluation::speed_accuracy::SpeedAccuracy),
        Box::new(evaluation::stability::StabilityReport),
        Box::new(growth::groom::ExportGroom),
        Box::new(growth::learn::CodecStrands),
        Box::new(growth::learn::DenseStrands),
        Box::new(growth::orientation::OrientationMaps),
        Box::new(growth::roots::RootsStage),
        Box::new(growth::strand_basis::StrandBasisStage),
        Box::new(scenes::corrupt::CorruptViews),
        Box::new(scenes::synthetic::SyntheticScene),
        Box::new(surface::fit_template::FitTemplate),
        Box::new(surface::outer_surface::OuterSurfaceStage),
        Box::new(surface::parts::PartsStage),
        Box::new(thickness::defur::DefurStage),
        Box::new(thickness::defur::baseline::DefurBaselineStage),
        Box::new(thickness::frosting::FrostingStage),
        Box::new(thickness::lengths::LengthsStage),
    ]
}
