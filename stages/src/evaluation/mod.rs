//! Measuring the result: per-run evaluation against ground truth (metrics only: ground truth
//! reaches nothing else), and the aggregate reports over sweeps (speed against accuracy, the
//! benchmark suite, stability under corrupted views) with their charts.

pub mod benchmark;
pub mod charts;
pub mod evaluate;
pub mod seams;
pub mod speed_accuracy;
pub mod stability;
pub mod targets;

/// Centimetres per scene unit of the `gt_scene` input: present, positive and finite, or an
/// error naming the file and the field.
pub(crate) fn gt_scale_cm(
    ctx: &fure_stage_api::StageContext<'_>,
) -> Result<f32, fure_stage_api::StageError> {
    let path = ctx.input("gt_scene")?;
    let scene: crate::data::scene::SceneInfo = crate::formats::json::read_json(path)?;
    match scene.s_cm {
        Some(s) if s > 0.0 && s.is_finite() => Ok(s),
        Some(s) => Err(fure_stage_api::StageError::input(
            "gt_scene",
            path,
            format!("field `s_cm`: expected a positive number, found {s}"),
        )),
        None => Err(fure_stage_api::StageError::input(
            "gt_scene",
            path,
            "field `s_cm` (centimetres per scene unit) is missing: the metrics measure the \
             ground truth in centimetres",
        )),
    }
}
