//! The reconstruction stages of fure and the data they exchange.
//!
//! The modules follow the method: [`data`] (plain structs) and [`formats`] (their files),
//! shared [`maths`] and the differentiable [`render`]er, then the stages by phase:
//! [`surface`] (M_outer, parts), [`thickness`] (Frosting, defurring, lengths), [`growth`]
//! (roots, orientation, strand basis, learners, groom), [`evaluation`] (metrics and the
//! reports over sweeps), and [`scenes`] (synthetic animals, corrupted views) for experiments.
//! A stage module is named after its stage kind or the kind's noun (`groom` for `export_groom`);
//! its stage struct is the kind in CamelCase plus
//! `Stage`. The engine reaches this crate only through
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
        Box::new(demo::DemoConcatStage),
        Box::new(demo::DemoNumbersStage),
        Box::new(demo::DemoSleepStage),
        Box::new(demo::DemoSumStage),
        Box::new(evaluation::benchmark::BenchmarkReportStage),
        Box::new(evaluation::evaluate::EvaluateStage),
        Box::new(evaluation::speed_accuracy::SpeedAccuracyStage),
        Box::new(evaluation::stability::StabilityReportStage),
        Box::new(growth::groom::ExportGroomStage),
        Box::new(growth::learn::CodecStrandsStage),
        Box::new(growth::learn::DenseStrandsStage),
        Box::new(growth::orientation::OrientationMapsStage),
        Box::new(growth::roots::RootsStage),
        Box::new(growth::strand_basis::StrandBasisStage),
        Box::new(scenes::corrupt::CorruptViewsStage),
        Box::new(scenes::working_views::WorkingViewsStage),
        Box::new(scenes::synthetic::SyntheticSceneStage),
        Box::new(scenes::synthetic::blender::BlenderSceneStage),
        Box::new(surface::fit_template::FitTemplateStage),
        Box::new(surface::outer_surface::OuterSurfaceStage),
        Box::new(surface::parts::PartsStage),
        Box::new(thickness::defur::DefurStage),
        Box::new(thickness::defur::baseline::DefurBaselineStage),
        Box::new(thickness::frosting::FrostingStage),
        Box::new(thickness::lengths::LengthsStage),
    ]
}
