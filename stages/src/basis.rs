//! Strand basis (PCA in a root-local canonical frame): stage `strand_basis` and the PERM loader.
//!
//! (Being written: the struct and its decoding are fixed; corpus and fitting follow.)

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// A linear strand model: `mean + sum_k z_k components[k]`, `points` points per strand
/// (root included, at the origin), in the canonical root-local frame
/// (x = tangent T, y = bitangent B, z = outward normal N), unit arc length.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StrandBasis {
    /// L, points per strand including the root.
    pub points: usize,
    /// The mean strand, L points.
    pub mean: Vec<Vec3>,
    /// K components, each L points.
    pub components: Vec<Vec<Vec3>>,
    /// Explained variance ratio per component (non-increasing).
    pub variance: Vec<f32>,
}

impl StrandBasis {
    /// Number of components K.
    pub fn k(&self) -> usize {
        self.components.len()
    }

    /// Decodes coefficients: mean + sum z_k C_k. Extra coefficients beyond K are ignored;
    /// missing ones count as zero.
    pub fn decode(&self, z: &[f32]) -> Vec<Vec3> {
        let mut out = self.mean.clone();
        for (c, &zk) in self.components.iter().zip(z) {
            for (o, p) in out.iter_mut().zip(c) {
                *o += zk * *p;
            }
        }
        out
    }
}
