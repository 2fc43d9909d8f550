//! What the diagnostics examples share.

use std::error::Error;
use std::process::ExitCode;

/// The exit code of an example's `run`, printing its error on stderr.
pub fn exit_code(result: Result<(), Box<dyn Error>>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// An example's error type.
pub type Res<T> = Result<T, Box<dyn Error>>;

// Not every example reads an output directory.
#[allow(dead_code)]
/// The command line of an example that reads a pipeline's output directory: that directory
/// (the first argument) and the arguments after it; `usage` when it is missing.
pub fn out_dir_and_args(usage: &str) -> Res<(std::path::PathBuf, Vec<String>)> {
    let mut args = std::env::args().skip(1);
    let dir = args.next().ok_or_else(|| format!("usage: {usage}"))?;
    Ok((dir.into(), args.collect()))
}
