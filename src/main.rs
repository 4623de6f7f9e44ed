//! The `liquid-splat` command-line tool: [`liquid_splat::cli::run`] on the
//! process's arguments.

use std::process::ExitCode;

fn main() -> ExitCode {
    // Writing to a closed pipe (`liquid-splat case compare A B | head -1`)
    // ends the process quietly, as it does other tools', instead of failing
    // the write (Rust ignores SIGPIPE by default, and `println!` then panics).
    #[cfg(unix)]
    // SAFETY: restores the default disposition of one signal before any
    // other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    liquid_splat::memory::keep_freed_memory();
    // An output that cannot be written ends the command by an unwind (see
    // `cli::StdoutError`): a closed one (where no SIGPIPE ended the process)
    // exits 141 quietly, as a shell reports a process that SIGPIPE ended.
    match std::panic::catch_unwind(|| liquid_splat::cli::run(std::env::args_os())) {
        Ok(code) => ExitCode::from(code),
        Err(p) => match p.downcast::<liquid_splat::cli::StdoutError>() {
            Ok(e) if e.0.kind() == std::io::ErrorKind::BrokenPipe => ExitCode::from(141),
            Ok(e) => {
                eprintln!("error: cannot write the standard output: {}", e.0);
                ExitCode::from(liquid_splat::error::EXIT_UNUSABLE_INPUT)
            }
            Err(p) => std::panic::resume_unwind(p),
        },
    }
}
