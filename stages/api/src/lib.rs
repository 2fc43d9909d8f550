//! The stage contract: the only thing the engine and the stages share.
//!
//! A stage is a pure function from declared input artifacts and typed
//! parameters to declared output artifacts. It has a `kind` (the name used in
//! pipeline files), an implementation `version` (bumped whenever its outputs
//! could change for the same inputs), parameter specifications with defaults,
//! and named input and output ports. Each port is one artifact: a file (with
//! a fixed extension) or a directory.
//!
//! Invariants every stage keeps:
//! - It reads only its declared inputs (paths given by [`StageContext::input`])
//!   and writes only its declared outputs ([`StageContext::output`]); the
//!   engine stores, hashes and caches those, and nothing else survives a run.
//! - Same inputs and parameters give the same bytes (seeded randomness, fixed
//!   reduction orders).
//! - It knows nothing of caching, keys or where the cache lives.
//! - It reports failure as a [`StageError`] naming the parameter, port or
//!   file at fault; it never panics on bad input and never writes NaN.

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

pub mod declare;
mod params;
pub use declare::FromParam;
pub use params::{ParamSpec, ParamType, Params, Value};

/// Errors a stage reports. The engine adds the stage name.
#[derive(Debug, thiserror::Error)]
pub enum StageError {
    /// A parameter has a wrong or out-of-range value.
    #[error("parameter `{name}`: {message}")]
    Param { name: String, message: String },
    /// An input artifact is missing, malformed or unusable.
    #[error("input `{port}` ({path}): {message}")]
    Input {
        port: String,
        path: PathBuf,
        message: String,
    },
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A computed quantity is NaN or infinite.
    #[error("non-finite values in {what}")]
    NonFinite { what: String },
    /// Anything else that makes the stage fail, with a human explanation.
    #[error("{0}")]
    Failed(String),
    /// The run was interrupted (SIGINT, SIGTERM or SIGHUP to fure) and the
    /// stage stopped between two steps ([`Progress::check_interrupted`]).
    #[error("stopped: the run was interrupted")]
    Interrupted,
}

impl StageError {
    pub fn param(name: impl Into<String>, message: impl Into<String>) -> Self {
        StageError::Param {
            name: name.into(),
            message: message.into(),
        }
    }
    pub fn input(port: impl Into<String>, path: &Path, message: impl fmt::Display) -> Self {
        StageError::Input {
            port: port.into(),
            path: path.to_path_buf(),
            message: message.to_string(),
        }
    }
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        StageError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
    pub fn failed(message: impl fmt::Display) -> Self {
        StageError::Failed(message.to_string())
    }
}

/// What a port holds on disk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PortKind {
    /// One file; the engine names it `<port>.<ext>`.
    File { ext: &'static str },
    /// A directory tree, created empty by the engine before `run`.
    Dir,
}

/// A named input or output of a stage.
#[derive(Debug, Clone)]
pub struct PortSpec {
    pub name: String,
    pub kind: PortKind,
    /// Inputs only: whether the pipeline must connect it.
    pub required: bool,
    pub doc: &'static str,
}

impl PortSpec {
    pub fn file(name: &str, ext: &'static str, doc: &'static str) -> Self {
        PortSpec {
            name: name.to_string(),
            kind: PortKind::File { ext },
            required: true,
            doc,
        }
    }
    pub fn dir(name: &str, doc: &'static str) -> Self {
        PortSpec {
            name: name.to_string(),
            kind: PortKind::Dir,
            required: true,
            doc,
        }
    }
    /// Marks an input port as optional.
    pub fn optional(mut self) -> Self {
        self.required = false;
        self
    }
    /// The file or directory name the engine gives this port's artifact.
    pub fn file_name(&self) -> String {
        match self.kind {
            PortKind::File { ext } if !ext.is_empty() => format!("{}.{}", self.name, ext),
            _ => self.name.clone(),
        }
    }
}

/// Progress reporting, fed by the stage, shown by the engine.
pub trait Progress: Send + Sync {
    /// Declares how many units of work the stage will report (replaces any previous total).
    fn set_total(&self, total: u64);
    /// Reports that `delta` more units are done.
    fn advance(&self, delta: u64);
    /// A short status message (the current phase).
    fn message(&self, text: &str);
    /// A line for the run log that stays after the stage ends (what the stage chose, say).
    fn note(&self, text: &str);
    /// Whether the run was interrupted. A stage that computes for long checks it between
    /// steps (through [`Progress::check_interrupted`]): the engine cannot stop a stage that
    /// runs in its own process, so without the check fure waits for the stage to end.
    fn interrupted(&self) -> bool {
        false
    }
    /// `Err(StageError::Interrupted)` once the run was interrupted: `?` it between steps.
    fn check_interrupted(&self) -> Result<(), StageError> {
        if self.interrupted() {
            Err(StageError::Interrupted)
        } else {
            Ok(())
        }
    }
}

/// A progress sink that discards everything (for tests and library use).
pub struct NoProgress;
impl Progress for NoProgress {
    fn set_total(&self, _: u64) {}
    fn advance(&self, _: u64) {}
    fn message(&self, _: &str) {}
    fn note(&self, _: &str) {}
}

/// Everything a running stage may touch.
pub struct StageContext<'a> {
    /// The stage's name in the pipeline (for messages only).
    pub name: &'a str,
    /// Parameters with defaults filled in and types checked.
    pub params: &'a Params,
    /// Connected inputs: port -> path of the artifact (read-only).
    pub inputs: BTreeMap<String, PathBuf>,
    /// Outputs: port -> path where the stage must write the artifact.
    pub outputs: BTreeMap<String, PathBuf>,
    pub progress: &'a dyn Progress,
}

impl<'a> StageContext<'a> {
    /// Path of a connected input; an error if the port is not connected.
    pub fn input(&self, port: &str) -> Result<&Path, StageError> {
        self.inputs
            .get(port)
            .map(PathBuf::as_path)
            .ok_or_else(|| StageError::failed(format!("input `{port}` is not connected")))
    }
    /// Path of an optional input, `None` when the pipeline left it out.
    pub fn input_opt(&self, port: &str) -> Option<&Path> {
        self.inputs.get(port).map(PathBuf::as_path)
    }
    /// Where to write an output; directories already exist.
    pub fn output(&self, port: &str) -> Result<&Path, StageError> {
        self.outputs
            .get(port)
            .map(PathBuf::as_path)
            .ok_or_else(|| StageError::failed(format!("stage has no output `{port}`")))
    }
}

/// The contract every stage implements.
pub trait Stage: Send + Sync {
    /// The name used as `kind = "..."` in pipeline files.
    fn kind(&self) -> &'static str;
    /// Implementation version: bump it whenever outputs may change for equal inputs.
    fn version(&self) -> u32;
    /// One paragraph for `fure stages` and error messages.
    fn doc(&self) -> &'static str;
    /// Parameters, their types and defaults.
    fn params(&self) -> Vec<ParamSpec>;
    /// Input ports; may depend on parameters (e.g. a command stage's `deps`).
    fn inputs(&self, params: &Params) -> Vec<PortSpec>;
    /// Output ports; may depend on parameters.
    fn outputs(&self, params: &Params) -> Vec<PortSpec>;
    /// Checks parameter values beyond their types before anything runs.
    fn validate(&self, _params: &Params) -> Result<(), StageError> {
        Ok(())
    }
    /// Does the work. The engine runs it inside a rayon pool sized for it.
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError>;
}

/// Checks that every value is finite, naming `what` otherwise.
pub fn ensure_finite<I: IntoIterator<Item = f32>>(what: &str, values: I) -> Result<(), StageError> {
    if values.into_iter().all(f32::is_finite) {
        Ok(())
    } else {
        Err(StageError::NonFinite {
            what: what.to_string(),
        })
    }
}
