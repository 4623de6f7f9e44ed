//! The `liquid-splat` command-line tool: [`liquid_splat::cli::run`] on the
//! process's arguments.

use std::process::ExitCode;

fn main() -> ExitCode {
    // Writing to a closed pipe (`liquid-splat case compare A B | head -1`)
    // ends the process quietly, as it does other tools', instead of failing
    // the write (Rust ignores SIGPIPE by default, and `println!` then panics).
    #[cfg(target_os = "linux")]
    // SAFETY: restores the default disposition of one signal before any
    // other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    liquid_splat::memory::keep_freed_memory();
    ExitCode::from(liquid_splat::cli::run(std::env::args_os()))
}
