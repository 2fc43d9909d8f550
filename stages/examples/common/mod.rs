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
