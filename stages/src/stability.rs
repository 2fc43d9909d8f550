//! The `stability_report` stage (work in progress).

use fure_stage_api::{ParamSpec, Params, PortSpec, Stage, StageContext, StageError};

/// Stage `stability_report`.
pub struct StabilityReport;

impl Stage for StabilityReport {
    fn kind(&self) -> &'static str {
        "stability_report"
    }
    fn version(&self) -> u32 {
        1
    }
    fn doc(&self) -> &'static str {
        "Stability sweep report (not yet implemented)."
    }
    fn params(&self) -> Vec<ParamSpec> {
        Vec::new()
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![PortSpec::file("sweep", "json", "the sweep record")]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        Vec::new()
    }
    fn run(&self, _ctx: &StageContext<'_>) -> Result<(), StageError> {
        Err(StageError::failed("not implemented yet"))
    }
}
