//! The `liquid-splat` command-line tool: [`liquid_splat::cli::run`] on the
//! process's arguments.

use std::process::ExitCode;

fn main() -> ExitCode {
    liquid_splat::memory::keep_freed_memory();
    ExitCode::from(liquid_splat::cli::run(std::env::args_os()))
}
