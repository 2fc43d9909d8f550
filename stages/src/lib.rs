//! The reconstruction stages of fure and the data they exchange.
//!
//! Data types (`mesh`, `camera`, `strands`, `image`, `scene`) are plain
//! structs; `formats` reads and writes them; every other module is one stage
//! or one piece of mathematics the stages share. The engine reaches this
//! crate only through [`registry`] and the contract in `fure_stage_api`.

pub mod camera;
pub mod image;
pub mod mesh;
pub mod scene;
pub mod strands;

use fure_stage_api::Stage;

/// Every stage kind this crate provides.
pub fn registry() -> Vec<Box<dyn Stage>> {
    vec![]
}
