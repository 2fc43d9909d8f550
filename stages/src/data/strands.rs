//! Strand sets: polylines grown from roots, stored flat for speed.

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// A set of strands. Strand `s` owns `points[starts[s]..starts[s + 1]]`, root
/// first. Per strand: part index into `part_names`, render width (scene
/// units) and linear RGB colour in [0, 1].
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Strands {
    pub points: Vec<Vec3>,
    pub starts: Vec<u32>,
    pub part: Vec<u16>,
    pub width: Vec<f32>,
    pub color: Vec<[f32; 3]>,
    pub part_names: Vec<String>,
}

impl Strands {
    pub fn new() -> Self {
        Strands {
            starts: vec![0],
            ..Default::default()
        }
    }
    pub fn len(&self) -> usize {
        self.starts.len().saturating_sub(1)
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Appends one strand.
    pub fn push(&mut self, points: &[Vec3], part: u16, width: f32, color: [f32; 3]) {
        if self.starts.is_empty() {
            self.starts.push(0);
        }
        self.points.extend_from_slice(points);
        self.starts.push(self.points.len() as u32);
        self.part.push(part);
        self.width.push(width);
        self.color.push(color);
    }
    /// The points of strand `s`, root first.
    pub fn strand(&self, s: usize) -> &[Vec3] {
        &self.points[self.starts[s] as usize..self.starts[s + 1] as usize]
    }
    /// Arc length of strand `s`.
    pub fn length(&self, s: usize) -> f32 {
        self.strand(s)
            .windows(2)
            .map(|w| (w[1] - w[0]).length())
            .sum()
    }
    /// Total number of segments.
    pub fn segment_count(&self) -> usize {
        self.points.len() - self.len()
    }
}
