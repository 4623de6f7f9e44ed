//! Process-wide allocator tuning for speed (never results).

/// Keep freed memory in the process instead of returning it to the
/// operating system (glibc only): the fields and the rasterizer allocate and
/// free buffers of tens of MB every pass, and fresh pages from the kernel
/// cost a page fault each (measured: more than half the time of a 20000×64
/// by 64×512 product). Large blocks come from the heap (no `mmap`), and the
/// heap is never trimmed. Changes speed only, never results. Call it first
/// thing in `main` (the command-line tool and the benchmarks do).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn keep_freed_memory() {
    extern "C" {
        fn mallopt(param: i32, value: i32) -> i32;
    }
    const M_TRIM_THRESHOLD: i32 = -1;
    const M_MMAP_MAX: i32 = -4;
    // SAFETY: glibc's mallopt takes two integers and only changes the
    // allocator's tuning under the allocator's own lock, which is sound at
    // any time; it is meant to be called first in `main` so that it
    // applies to every allocation.
    unsafe {
        mallopt(M_MMAP_MAX, 0);
        mallopt(M_TRIM_THRESHOLD, i32::MAX);
    }
}
/// Keep freed memory in the process: nothing to tune outside glibc.
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn keep_freed_memory() {}
