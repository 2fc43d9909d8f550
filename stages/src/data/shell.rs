//! Frosting shell widths: the fur-thickness cue (method.md section 3).

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Per shell vertex: position y_k, unit normal nu_k and width w_k, all in
/// the outer mesh's frame and scene units. Written by `frosting` (or
/// imported), read by `defur`, `lengths` and `roots`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ShellWidths {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub widths: Vec<f32>,
}
