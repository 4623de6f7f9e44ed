//! Process-wide allocator tuning for speed (never results).

/// Keep freed memory in the process instead of returning it to the
/// operating system (glibc only): the fields and the rasterizer allocate and
/// free buffers of tens of MB every pass, and fresh pages from the kernel
/// cost a page fault each (measured: more than half the time of a 20000×64
/// by 64×512 product). Large blocks come from the heap (no `mmap`), and the
/// heap is never trimmed.
///
/// Threads other than the main one allocate from heaps of at most 64 MB
/// each; glibc unmaps such a heap as soon as it is entirely free, whatever
/// the trim threshold, unless the heap before it lacks room for the top
/// padding. So the padding is set to 64 MB: a worker whose buffers outgrow
/// its first heap keeps its second one. Without it, training the `swing`
/// fixture scene for 1,000 iterations took 1.1 million page faults on one
/// thread (a second heap mapped and unmapped every iteration) and 18,000
/// with it. The padding is address space: pages still cost memory only
/// once written, except under strict overcommit accounting
/// (`vm.overcommit_memory = 2`), where each thread's first heap and each
/// 64 MB step of the main heap count in full against the commit limit.
/// Changes speed only, never results. Call it first thing in `main` (the
/// command-line tool and the benchmarks do).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn keep_freed_memory() {
    extern "C" {
        fn mallopt(param: i32, value: i32) -> i32;
    }
    const M_TRIM_THRESHOLD: i32 = -1;
    const M_TOP_PAD: i32 = -2;
    const M_MMAP_MAX: i32 = -4;
    // SAFETY: glibc's mallopt takes two integers and only changes the
    // allocator's tuning under the allocator's own lock, which is sound at
    // any time; it is meant to be called first in `main` so that it
    // applies to every allocation.
    unsafe {
        mallopt(M_MMAP_MAX, 0);
        mallopt(M_TRIM_THRESHOLD, i32::MAX);
        mallopt(M_TOP_PAD, 64 << 20);
    }
}
/// Keep freed memory in the process: nothing to tune outside glibc.
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn keep_freed_memory() {}

#[cfg(all(
    test,
    target_os = "linux",
    target_env = "gnu",
    target_pointer_width = "64"
))]
mod tests {
    /// Minor page faults of the calling thread so far.
    fn minor_faults() -> i64 {
        // SAFETY: `getrusage` writes one `rusage` into the zeroed value.
        unsafe {
            let mut u: libc::rusage = std::mem::zeroed();
            assert_eq!(libc::getrusage(libc::RUSAGE_THREAD, &mut u), 0);
            u.ru_minflt as i64
        }
    }

    /// A zeroed buffer of `len` bytes, every page written.
    fn written(len: usize) -> Vec<u8> {
        let mut v = vec![0u8; len];
        for i in (0..len).step_by(4096) {
            v[i] = 1;
        }
        std::hint::black_box(v)
    }

    #[test]
    fn a_threads_second_heap_is_kept_when_freed() {
        // (This sets the allocator's tuning for the whole test process, as
        // `main` does for the tool: speed only.)
        super::keep_freed_memory();
        // On a thread of its own (so, with fewer threads than glibc's
        // arena limit, an arena of its own, not the main one): most of a
        // first 64 MB heap held, then a buffer that needs a second heap
        // taken and freed twice. The second time its pages must still be
        // there: without the top padding glibc unmapped the second heap
        // when it was freed, and the second buffer faulted in every one
        // of its 8,192 pages again.
        let (first, again) = std::thread::spawn(|| {
            let held = written(48 << 20);
            let before = minor_faults();
            drop(written(32 << 20));
            let first = minor_faults() - before;
            let before = minor_faults();
            drop(written(32 << 20));
            let again = minor_faults() - before;
            drop(held);
            (first, again)
        })
        .join()
        .unwrap();
        // Where fresh pages come in larger pieces than 4 KB (transparent
        // huge pages always on), the two cases cannot be told apart.
        if first < 4000 {
            eprintln!("{first} page faults for a fresh 32 MB buffer: nothing to tell apart");
            return;
        }
        assert!(
            again < 1000,
            "{again} page faults for a reused 32 MB buffer ({first} fresh)"
        );
    }
}
