//! The one integration-test binary of fure: each area adds a module here.
//! Tests drive the built `fure` binary on temporary directories.

mod bad_input;
mod basis;
mod capture;
mod engine;
mod engine_trust;
mod fit_template;
mod groom;
mod method;
mod slurm;
mod sweep;
