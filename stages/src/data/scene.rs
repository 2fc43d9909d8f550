//! `scene.json`: what a capture knows about its subject (metric scale, eyes, parts).

use std::collections::BTreeMap;

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Per-part facts. For synthetic scenes these are ground truth; for real
/// captures a user may give reference values (all optional except `fur`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PartInfo {
    pub fur: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mean_length_cm: Option<f32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub density_per_cm2: Option<f32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mean_thickness_cm: Option<f32>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneInfo {
    /// Centimetres per scene unit: a synthetic scene's ground truth, read only by the
    /// metrics (through `gt_scene`, `evaluation::gt_scale_cm`). A capture leaves it out:
    /// the method takes its scale from the eyes (`lengths`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub s_cm: Option<f32>,
    /// The two eye centres in scene units.
    pub eyes: [Vec3; 2],
    /// Eye separation in cm assumed by the metric-scale step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eye_separation_cm: Option<f32>,
    pub parts: BTreeMap<String, PartInfo>,
}
