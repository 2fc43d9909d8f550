//! The fure engine: a declarative dataflow build system with a
//! content-addressed stage cache.
//!
//! The engine knows nothing about fur. It gets its stage kinds as
//! `Vec<Box<dyn Stage>>` (the contract in `fure_stage_api`), adds the built-in
//! `command` kind, and then:
//!
//! 1. [`pipeline`] parses TOML pipelines (with `extends`, `[sweep]`, `--set`),
//!    keeping file:line:column for every value;
//! 2. [`plan`] checks kinds, parameters and ports and orders the DAG;
//! 3. [`exec`] keys each stage ([`key`]), looks it up in the [`cache`], runs
//!    what is missing in parallel, stores outputs content-addressed and
//!    materialises them under `out/<pipeline>/<stage>/`;
//! 4. [`sweep`] and [`bench`](mod@bench) run many variants or repeats of a pipeline;
//!    [`slurm`] computes the stages that must run as Slurm jobs instead;
//!    [`shard`] splits a sweep over machines that share no cache and merges it;
//!    [`publish`] copies a sweep's report out of `out/` (e.g. into `docs/`);
//! 5. [`cli`] is the `fure` command line.
//!
//! See ARCHITECTURE.md for the invariants.

pub mod bench;
pub mod cache;
pub mod cli;
pub mod command;
pub mod exec;
pub mod key;
pub mod load;
pub mod pipeline;
pub mod plan;
pub mod publish;
pub mod shard;
pub mod signals;
pub mod slurm;
pub mod sweep;
pub mod ui;

use std::path::Path;

use fure_stage_api::Stage;

pub use exec::{RunOptions, RunReport, Status};
pub use pipeline::{Pipeline, PipelineError, PipelineErrors};
pub use plan::{Plan, Registry};

/// The engine: the registry of stage kinds and the entry points.
#[derive(Clone)]
pub struct Engine {
    pub registry: Registry,
}

impl Engine {
    /// An engine for these stage kinds (plus `command`).
    pub fn new(stages: Vec<Box<dyn Stage>>) -> Result<Engine, String> {
        Ok(Engine {
            registry: Registry::new(stages)?,
        })
    }

    /// Loads a pipeline file and applies `--set` overrides.
    pub fn load(&self, path: &Path, sets: &[String]) -> Result<Pipeline, PipelineErrors> {
        let mut p = Pipeline::load(path)?;
        let mut errors = Vec::new();
        for s in sets {
            if let Err(e) = p.apply_set(s, "--set") {
                errors.push(e);
            }
        }
        if errors.is_empty() {
            Ok(p)
        } else {
            Err(PipelineErrors(errors))
        }
    }

    /// Checks and orders a pipeline.
    pub fn plan(&self, pipeline: &Pipeline) -> Result<Plan, PipelineErrors> {
        plan::plan(pipeline, &self.registry)
    }
}
