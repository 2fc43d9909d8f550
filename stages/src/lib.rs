//! The reconstruction stages of fure and the data they exchange.
//!
//! Data types (`mesh`, `camera`, `strands`, `image`, `scene`) are plain
//! structs; `formats` reads and writes them; every other module is one stage
//! or one piece of mathematics the stages share. The engine reaches this
//! crate only through [`registry`] and the contract in `fure_stage_api`.

// `!(x > 0.0)` is this crate's idiom for "not a positive number": unlike
// `x <= 0.0` it also rejects NaN, which is the point of those checks.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

// Data types.
pub mod camera;
pub mod image;
pub mod mesh;
pub mod rootset;
pub mod scene;
pub mod shell;
pub mod strands;

// Reading and writing them.
pub mod formats;

// Shared mathematics.
pub mod geom;
pub mod render;
pub mod stats;

// Stages.
pub mod basis;
pub mod benchmark;
pub mod charts;
pub mod corrupt;
pub mod defur;
pub mod demo;
pub mod evaluate;
pub mod fit_template;
pub mod frosting;
pub mod groom;
pub mod learn;
pub mod lengths;
pub mod orientation;
pub mod outer_surface;
pub mod parts;
pub mod roots;
pub mod stability;
pub mod synthetic;

use fure_stage_api::Stage;

/// Every stage kind this crate provides.
pub fn registry() -> Vec<Box<dyn Stage>> {
    // One entry per stage kind, alphabetical by module.
    vec![
        Box::new(basis::StrandBasisStage),
        Box::new(benchmark::BenchmarkReport),
        Box::new(charts::SpeedAccuracy),
        Box::new(corrupt::CorruptViews),
        Box::new(defur::DefurStage),
        Box::new(defur::baseline::DefurBaselineStage),
        Box::new(demo::DemoConcat),
        Box::new(demo::DemoNumbers),
        Box::new(demo::DemoSleep),
        Box::new(demo::DemoSum),
        Box::new(evaluate::Evaluate),
        Box::new(fit_template::FitTemplate),
        Box::new(frosting::FrostingStage),
        Box::new(groom::ExportGroom),
        Box::new(learn::CodecStrands),
        Box::new(learn::DenseStrands),
        Box::new(lengths::LengthsStage),
        Box::new(orientation::OrientationMaps),
        Box::new(outer_surface::OuterSurfaceStage),
        Box::new(parts::PartsStage),
        Box::new(roots::RootsStage),
        Box::new(stability::StabilityReport),
        Box::new(synthetic::SyntheticScene),
    ]
}
