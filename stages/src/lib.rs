//! The reconstruction stages of fure and the data they exchange.
//!
//! Data types (`mesh`, `camera`, `strands`, `image`, `scene`) are plain
//! structs; `formats` reads and writes them; every other module is one stage
//! or one piece of mathematics the stages share. The engine reaches this
//! crate only through [`registry`] and the contract in `fure_stage_api`.

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

// Stages.
pub mod basis;
pub mod charts;
pub mod corrupt;
pub mod defur;
pub mod demo;
pub mod evaluate;
pub mod frosting;
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
    #[allow(unused_mut)]
    let mut stages: Vec<Box<dyn Stage>> = Vec::new();
    // One line per stage kind, alphabetical by module.
    stages.push(Box::new(basis::StrandBasisStage));
    stages.push(Box::new(charts::SpeedAccuracy));
    stages.push(Box::new(corrupt::CorruptViews));
    stages.push(Box::new(defur::DefurStage));
    stages.push(Box::new(defur::baseline::DefurBaselineStage));
    stages.push(Box::new(demo::DemoConcat));
    stages.push(Box::new(demo::DemoNumbers));
    stages.push(Box::new(demo::DemoSleep));
    stages.push(Box::new(demo::DemoSum));
    stages.push(Box::new(evaluate::Evaluate));
    stages.push(Box::new(frosting::FrostingStage));
    stages.push(Box::new(learn::CodecStrands));
    stages.push(Box::new(learn::DenseStrands));
    stages.push(Box::new(lengths::LengthsStage));
    stages.push(Box::new(orientation::OrientationMaps));
    stages.push(Box::new(outer_surface::OuterSurfaceStage));
    stages.push(Box::new(parts::PartsStage));
    stages.push(Box::new(roots::RootsStage));
    stages.push(Box::new(stability::StabilityReport));
    stages.push(Box::new(synthetic::SyntheticScene));
    stages
}
