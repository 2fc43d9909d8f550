//! Strand roots on the defurred body with local frames (method.md section 6).

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Roots, structure of arrays. Frames are orthonormal: `bitangent = normal x tangent`.
/// `length` and `width` are in scene units (converted from cm with the scene's `s_cm`),
/// `rho` is the normalised shell width in [0, 1].
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Roots {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub tangents: Vec<Vec3>,
    pub bitangents: Vec<Vec3>,
    pub part: Vec<u16>,
    pub part_names: Vec<String>,
    pub length: Vec<f32>,
    pub width: Vec<f32>,
    pub rho: Vec<f32>,
    /// Centimetres per scene unit used to convert lengths.
    pub s_cm: f32,
}

impl Roots {
    pub fn len(&self) -> usize {
        self.positions.len()
    }
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }
}
