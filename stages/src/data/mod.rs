//! The data the stages exchange: plain structs with no stage logic. Their files are read and
//! written by [`crate::formats`].

pub mod camera;
pub mod image;
pub mod lens;
pub mod mesh;
pub mod rootset;
pub mod scene;
pub mod sharpness;
pub mod shell;
pub mod strands;
