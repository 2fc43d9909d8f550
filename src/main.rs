//! The `fure` command line: the engine with fure's stage kinds.

fn main() -> std::process::ExitCode {
    fure::cli::main_with(fure_stages::registry())
}
