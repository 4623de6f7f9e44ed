//! The `liquid-splat` command-line tool: [`liquid_splat::cli::run`] on the
//! process's arguments.

use std::process::ExitCode;

/// Keep freed memory in the process instead of returning it to the
/// operating system (glibc only): the fields and the rasterizer allocate and
/// free buffers of tens of MB every pass, and fresh pages from the kernel
/// cost a page fault each (measured: more than half the time of a 20000×64
/// by 64×512 product). Large blocks come from the heap (no `mmap`), and the
/// heap is never trimmed. Changes speed only, never results.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn keep_freed_memory() {
    extern "C" {
        fn mallopt(param: i32, value: i32) -> i32;
    }
    const M_TRIM_THRESHOLD: i32 = -1;
    const M_MMAP_MAX: i32 = -4;
    // SAFETY: mallopt only changes allocator tuning; called before any
    // thread is started.
    unsafe {
        mallopt(M_MMAP_MAX, 0);
        mallopt(M_TRIM_THRESHOLD, i32::MAX);
    }
}
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn keep_freed_memory() {}

fn main() -> ExitCode {
    keep_freed_memory();
    ExitCode::from(liquid_splat::cli::run(std::env::args_os()))
}
