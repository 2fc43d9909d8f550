//! `scene.json`: what a capture knows about its subject (metric scale, eyes, parts).

use std::collections::BTreeMap;

use fure_stage_api::{StageContext, StageError};
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
    /// metrics (through `gt_scene`, [`gt_scale_cm`]). A capture leaves it out: the method
    /// takes its scale from the eyes (`lengths`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub s_cm: Option<f32>,
    /// The two eye centres in scene units.
    pub eyes: [Vec3; 2],
    /// Eye separation in cm assumed by the metric-scale step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eye_separation_cm: Option<f32>,
    pub parts: BTreeMap<String, PartInfo>,
}

/// Centimetres per scene unit of the `gt_scene` input: present, positive and finite, or an
/// error naming the file and the field.
pub fn gt_scale_cm(ctx: &StageContext<'_>) -> Result<f32, StageError> {
    let path = ctx.input("gt_scene")?;
    let scene: SceneInfo = crate::formats::json::read_json(path)?;
    match scene.s_cm {
        Some(s) if s > 0.0 && s.is_finite() => Ok(s),
        Some(s) => Err(StageError::input(
            "gt_scene",
            path,
            format!("field `s_cm`: expected a positive number, found {s}"),
        )),
        None => Err(StageError::input(
            "gt_scene",
            path,
            "field `s_cm` (centimetres per scene unit) is missing: the metrics measure the \
             ground truth in centimetres",
        )),
    }
}
