//! Worker pools for the command-line tool and the benchmarks, optionally
//! with each worker pinned to one CPU (`--pin-threads`).
//!
//! Why pinning exists: on a machine with few cores, Linux sometimes wakes a
//! pool's second worker on the CPU where the first is running, and short
//! parallel stages then run on one CPU. Measured on a 2-core machine with
//! `bench raster`, the 64×64 frame's forward at 2 threads: 0.43–0.86 ms
//! over six unpinned runs (the slow ones with every stage on one CPU),
//! 0.44–0.50 ms over five pinned runs.
//!
//! Pinned, worker `i` runs only on the `i`-th of the CPUs the process could
//! use when pinning was turned on (read once then, from the thread that
//! turned it on), wrapping around when there are more workers than CPUs.
//! Off by default: two pinned processes started side by side would share the
//! same CPUs. A pinned global pool stays pinned for the rest of the process
//! (in Python, for later calls of the command-line entry point too). Pinning
//! changes speed only, never results; where the operating system is not
//! Linux it does nothing.
//!
//! [`keep_awake`] keeps a pool's workers polling for work through the
//! short serial steps between the parallel stages of one call (the
//! rasterizer's binning between its per-Gaussian and per-pixel stages, for
//! example). A rayon worker that finds no work sleeps after a few dozen
//! polls, and waking it costs time: on a 2-core virtual machine, a parallel
//! stage of two 50 µs tasks that follows a serial step of 20–1000 µs took
//! 66–90 µs in the median and up to 0.19 ms (`cargo bench --bench wake`),
//! as long as a whole parallel stage of a small frame.

use std::cell::{Cell, RefCell, UnsafeCell};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use std::time::{Duration, Instant};

/// Whether pools built by [`pool`] pin their workers.
static PIN: AtomicBool = AtomicBool::new(false);

/// The CPUs the process could use when pinning was first turned on (a
/// pinned worker's own set is one CPU, so it is read once, beforehand).
#[cfg(target_os = "linux")]
static CPUS: std::sync::OnceLock<Vec<usize>> = std::sync::OnceLock::new();

/// Make every later [`pool`] pin its workers (`true`) or not. Call it from
/// a thread that is not pinned (the command-line tool does, first thing):
/// the CPUs to pin to are the ones the calling thread may use then.
pub fn set_pinning(on: bool) {
    #[cfg(target_os = "linux")]
    if on {
        CPUS.get_or_init(allowed_cpus);
    }
    PIN.store(on, Ordering::Relaxed);
}

/// Whether pinning is on and possible (Linux, and the CPUs could be read).
pub fn pinning() -> bool {
    #[cfg(target_os = "linux")]
    {
        PIN.load(Ordering::Relaxed) && CPUS.get().is_some_and(|c| !c.is_empty())
    }
    #[cfg(not(target_os = "linux"))]
    {
        false
    }
}

/// The logical CPUs this process may use: with [`pinning`] on, the ones read
/// when it was turned on (inside a pinned worker the system would report
/// that worker's single CPU); otherwise what the system reports now.
pub fn cores() -> usize {
    #[cfg(target_os = "linux")]
    if pinning() {
        if let Some(c) = CPUS.get() {
            return c.len();
        }
    }
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// How many of the current pool's workers can run at once: its threads,
/// but at most the CPUs this process may use (read once per process, or as
/// [`cores`] says while pinning is on). Work split into one fixed part per
/// worker uses this many parts: on a pool with more workers than CPUs
/// (`--threads 3` on two cores), one part per worker would leave a CPU
/// running two parts while the other's ends early (the 64×64 bench frame's
/// backward took 0.37 ms on 3 threads against 0.28 on 2 on a 2-core
/// machine, benches/README.md, "More workers than CPUs"). Speed only,
/// never results.
pub(crate) fn workers_with_a_cpu() -> usize {
    static CPUS_AT_START: OnceLock<usize> = OnceLock::new();
    let cpus = if pinning() {
        cores()
    } else {
        *CPUS_AT_START.get_or_init(cores)
    };
    rayon::current_num_threads().min(cpus.max(1))
}

/// Pin the calling thread to the `i`-th CPU (wrapping) when [`pinning`] is
/// on; otherwise do nothing. Best effort: a refusal leaves it unpinned.
pub fn pin_current_thread(i: usize) {
    if let Some(pin) = pinner() {
        pin(i);
    }
}

/// A start handler for a pool's workers.
type Pinner = Box<dyn Fn(usize) + Send + Sync>;

/// With [`pinning`] on, a start handler that pins worker `i` to the `i`-th
/// CPU (wrapping); the CPUs are captured now, so the workers pin themselves
/// even if pinning is turned off before they start.
fn pinner() -> Option<Pinner> {
    #[cfg(target_os = "linux")]
    if pinning() {
        let cpus = CPUS.get()?.clone();
        return Some(Box::new(move |i: usize| {
            pin_to(cpus[i % cpus.len()]);
        }));
    }
    None
}

/// A rayon pool of `threads` workers, worker `i` pinned to the `i`-th CPU
/// (wrapping) when [`pinning`] is on.
pub fn pool(threads: usize) -> Result<rayon::ThreadPool, rayon::ThreadPoolBuildError> {
    pool_from(threads, 0)
}

/// [`pool`] with worker `i` pinned to CPU `first + i` (wrapping) when
/// [`pinning`] is on: the benches time one thread on each CPU with it.
pub fn pool_from(
    threads: usize,
    first: usize,
) -> Result<rayon::ThreadPool, rayon::ThreadPoolBuildError> {
    let builder = rayon::ThreadPoolBuilder::new().num_threads(threads);
    match pinner() {
        Some(pin) => builder.start_handler(move |i| pin(first + i)).build(),
        None => builder.build(),
    }
}

/// When [`pinning`] is on, start rayon's global pool with `threads` workers
/// (`None`: rayon's default count), pinned as [`pool`] pins them. Returns
/// whether the global pool's workers are now pinned: false when pinning is
/// off or impossible, and when the global pool was already running (it is
/// left as it is).
pub fn pin_global_pool(threads: Option<usize>) -> bool {
    pinner().is_some_and(|pin| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads.unwrap_or(0))
            .start_handler(pin)
            .build_global()
            .is_ok()
    })
}

/// Whether the calling thread runs on one CPU only while [`pinning`] is on
/// and more than one could be used: a pinned worker.
pub fn current_thread_is_pinned() -> bool {
    #[cfg(target_os = "linux")]
    {
        pinning() && cores() > 1 && allowed_cpus().len() == 1
    }
    #[cfg(not(target_os = "linux"))]
    {
        false
    }
}

/// `work(part)` for every part of `parts`, on the workers of the current
/// pool: the caller runs the first part, then every part no other worker
/// has started, and then spins until the others end (as long as
/// [`spin_until`] does), instead of waiting in rayon at once, where a
/// waiting worker soon yields its CPU or sleeps and must then be woken.
/// For the short parallel steps of a small frame, whose parts end within a
/// few microseconds of each other: on the 2-core development machine, the
/// 64×64 bench frame's backward spent a median 4.5–5.0 µs between the end
/// of its per-tile step and the start of its per-Gaussian step on two
/// threads when the caller waited in rayon (1.1 µs on one thread). For a
/// few parts of about equal cost (see [`balanced_parts`]); a panic in any
/// part propagates once every part has ended.
pub(crate) fn run_parts<P: Send>(parts: Vec<P>, work: impl Fn(P) + Sync) {
    if parts.len() <= 1 || rayon::current_num_threads() < 2 {
        parts.into_iter().for_each(work);
        return;
    }
    // Each part is taken once, by whoever locks it first.
    let parts: Vec<Mutex<Option<P>>> = parts.into_iter().map(|p| Mutex::new(Some(p))).collect();
    let done: Vec<AtomicBool> = parts.iter().map(|_| AtomicBool::new(false)).collect();
    let run = |i: usize| {
        let part = parts[i]
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        if let Some(part) = part {
            let _done = SetOnDrop(&done[i]);
            work(part);
        }
    };
    rayon::scope(|s| {
        for i in 1..parts.len() {
            let run = &run;
            s.spawn(move |_| run(i));
        }
        (0..parts.len()).for_each(run);
        done[1..].iter().for_each(spin_until);
    });
}

/// `first(a)` for every part's first step, then `second(b)` for every
/// part's second step, on the workers of the current pool: as two calls of
/// [`run_parts`], except that between the steps no job goes back to the
/// pool. A worker that ends its first step waits for the others' by their
/// flags (running any first step nobody has started) and goes straight on
/// to its second step; the caller, once every first step has ended, runs
/// `between()` (other workers' second steps may have started by then), its
/// own second step and every second step no other worker has started, and
/// then spins until the others end (as long as [`spin_until`] does). No
/// `second` starts before every `first` has ended and its writes are seen.
/// If a first step panics, no second step runs, and the panic propagates
/// once every started step has ended.
///
/// Neither step may wait for other work of the pool (a rayon call inside
/// could take another part's job, which would then wait for the step that
/// called it). For the small frame's backward, whose two parallel steps
/// take tens of microseconds each: on the 64×64 bench frame on the 2-core
/// development machine, 0.0–0.3 µs faster than two calls of [`run_parts`]
/// (one binary switching by pass; benches/README.md, "The backward's steps
/// in fixed parts, step 2 started early").
pub(crate) fn run_parts_in_two_steps<A: Send, B: Send>(
    parts: Vec<(A, B)>,
    first: impl Fn(A) + Sync,
    between: impl FnOnce() + Send,
    second: impl Fn(B) + Sync,
) {
    if parts.len() <= 1 || rayon::current_num_threads() < 2 {
        let (a, b): (Vec<A>, Vec<B>) = parts.into_iter().unzip();
        a.into_iter().for_each(first);
        between();
        b.into_iter().for_each(second);
        return;
    }
    let parts: Vec<TwoSteps<A, B>> = parts
        .into_iter()
        .map(|(a, b)| TwoSteps {
            state: AtomicU8::new(NOT_STARTED),
            first: UnsafeCell::new(Some(a)),
            second: UnsafeCell::new(Some(b)),
        })
        .collect();
    let failed = AtomicBool::new(false);
    // Run part `i`'s first step if nobody has started it.
    let run_first = |i: usize| {
        let p = &parts[i];
        if p.take(NOT_STARTED, FIRST_STARTED) {
            // SAFETY: the state moved from `NOT_STARTED` on this thread
            // only, so nothing else reads or writes `first`.
            let step = unsafe { (*p.first.get()).take() };
            let _ended = Ended {
                state: &p.state,
                to: FIRST_ENDED,
                failed: &failed,
            };
            step.map(&first);
        }
    };
    // Run part `i`'s second step if nobody has started it.
    let run_second = |i: usize| {
        let p = &parts[i];
        if p.take(FIRST_ENDED, SECOND_STARTED) {
            // SAFETY: as in `run_first`, from `FIRST_ENDED`.
            let step = unsafe { (*p.second.get()).take() };
            let _ended = Ended {
                state: &p.state,
                to: SECOND_ENDED,
                failed: &failed,
            };
            step.map(&second);
        }
    };
    // Whether every first step has ended without a panic, running those
    // nobody has started and waiting for the rest.
    let firsts_ended = || {
        for (i, p) in parts.iter().enumerate() {
            run_first(i);
            wait_until(|| p.state.load(Ordering::Acquire) >= FIRST_ENDED);
        }
        !failed.load(Ordering::Acquire)
    };
    rayon::scope(|s| {
        for i in 1..parts.len() {
            let (run_first, run_second, firsts_ended) = (&run_first, &run_second, &firsts_ended);
            s.spawn(move |_| {
                run_first(i);
                if firsts_ended() {
                    run_second(i);
                }
            });
        }
        run_first(0);
        if firsts_ended() {
            between();
            (0..parts.len()).for_each(run_second);
            for p in &parts[1..] {
                spin_while(|| p.state.load(Ordering::Acquire) != SECOND_ENDED);
            }
        }
    });
}

/// A job run once, by whichever thread asks first ([`OneJob::run`]), so
/// that a job handed to the pool early can still be run by a thread that
/// needs its result before any worker has started it ([`OneJob::wait`]).
pub(crate) struct OneJob<F> {
    job: Mutex<Option<F>>,
    ended: AtomicBool,
}

impl<F: FnOnce()> OneJob<F> {
    pub(crate) fn new(job: F) -> Self {
        OneJob {
            job: Mutex::new(Some(job)),
            ended: AtomicBool::new(false),
        }
    }

    /// Run the job here, unless some thread has already started it.
    pub(crate) fn run(&self) {
        let job = self
            .job
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        if let Some(job) = job {
            let _ended = SetOnDrop(&self.ended);
            job();
        }
    }

    /// Run the job here if no thread has started it, else wait until it
    /// has ended (or its panic has unwound; [`wait_until`]).
    /// Its writes are seen once this returns.
    pub(crate) fn wait(&self) {
        self.run();
        wait_until(|| self.ended.load(Ordering::Acquire));
    }
}

/// The index of the current thread in its rayon pool (0 outside one).
pub(crate) fn worker_index() -> usize {
    rayon::current_thread_index().unwrap_or(0)
}

/// `work(&mut state, job)` for every job, on the workers of the current
/// pool, each job first offered to the worker named with it: each task
/// takes the jobs named for its own worker ([`worker_index`], modulo the
/// pool's size) in their order, then helps with the other workers' jobs,
/// which also go in their order; `state` is made once per task by `init`.
/// The thread that runs the scope (the caller, when it is a pool worker)
/// runs `beside` first, and its result is returned. For steps that
/// read what an earlier step wrote on a known worker: what one core wrote
/// is read fastest on that core, the more so when the machine's two CPUs
/// are far apart (benches/README.md, "The backward's tiles on the workers
/// that blended their rows"). Which worker runs a job changes no result;
/// a panic in any job or in `beside` propagates once every task has ended.
pub(crate) fn run_on_named_workers<J: Send, S, R: Send>(
    jobs: Vec<(usize, J)>,
    init: impl Fn() -> S + Sync,
    work: impl Fn(&mut S, J) + Sync,
    beside: impl FnOnce() -> R + Send,
) -> R {
    let threads = rayon::current_num_threads();
    if threads < 2 || jobs.is_empty() {
        let r = beside();
        let mut state = init();
        jobs.into_iter().for_each(|(_, j)| work(&mut state, j));
        return r;
    }
    let mut queues: Vec<Vec<UnsafeCell<Option<J>>>> = (0..threads).map(|_| Vec::new()).collect();
    for (w, j) in jobs {
        queues[w % threads].push(UnsafeCell::new(Some(j)));
    }
    let queues = Claimed(queues);
    let next: Vec<Padded<AtomicUsize>> =
        (0..threads).map(|_| Padded(AtomicUsize::new(0))).collect();
    let run = || {
        let me = worker_index() % threads;
        let mut state = init();
        for q in (0..threads).map(|k| (me + k) % threads) {
            loop {
                let k = next[q].0.fetch_add(1, Ordering::Relaxed);
                // SAFETY: the `fetch_add` hands each place of queue `q` to
                // one task only.
                let Some(job) = (unsafe { queues.take(q, k) }) else {
                    break;
                };
                job.into_iter().for_each(|j| work(&mut state, j));
            }
        }
    };
    rayon::scope(|s| {
        for _ in 1..threads {
            s.spawn(|_| run());
        }
        let r = beside();
        run();
        r
    })
}

/// The jobs of [`run_on_named_workers`], a queue per worker (the items of
/// [`from_both_ends`], one queue), each job taken by one task only.
struct Claimed<J>(Vec<Vec<UnsafeCell<Option<J>>>>);

// SAFETY: a job is taken (moved out) only by the task whose `fetch_add`
// (or compare-exchange, in `from_both_ends`) claimed its place, so no two
// threads touch one cell.
unsafe impl<J: Send> Sync for Claimed<J> {}

impl<J> Claimed<J> {
    /// Place `k` of queue `q`: `None` past the queue's end, else its job.
    ///
    /// # Safety
    /// No other thread takes place `k` of queue `q`, now or later.
    unsafe fn take(&self, q: usize, k: usize) -> Option<Option<J>> {
        // SAFETY: as the caller promises.
        self.0[q].get(k).map(|c| unsafe { (*c.get()).take() })
    }
}

/// A value on a cache line of its own.
#[repr(align(128))]
struct Padded<T>(T);

/// One part of [`run_parts_in_two_steps`], on a cache line of its own:
/// whoever moves `state` on from a step's start state owns that step.
#[repr(align(128))]
struct TwoSteps<A, B> {
    state: AtomicU8,
    first: UnsafeCell<Option<A>>,
    second: UnsafeCell<Option<B>>,
}

// SAFETY: each step is taken by one thread only, the one whose
// compare-exchange moved `state` on (`TwoSteps::take`).
unsafe impl<A: Send, B: Send> Sync for TwoSteps<A, B> {}

impl<A, B> TwoSteps<A, B> {
    /// Move `state` from `from` to `to`: whether this thread did.
    fn take(&self, from: u8, to: u8) -> bool {
        self.state.load(Ordering::Relaxed) == from
            && self
                .state
                .compare_exchange(from, to, Ordering::Acquire, Ordering::Relaxed)
                .is_ok()
    }
}

/// The states of a [`TwoSteps`], in the order they come.
const NOT_STARTED: u8 = 0;
const FIRST_STARTED: u8 = 1;
const FIRST_ENDED: u8 = 2;
const SECOND_STARTED: u8 = 3;
const SECOND_ENDED: u8 = 4;

/// Stores `to` in `state` when dropped: when a step ends, or while its
/// panic unwinds (then setting `failed` first).
struct Ended<'a> {
    state: &'a AtomicU8,
    to: u8,
    failed: &'a AtomicBool,
}

impl Drop for Ended<'_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.failed.store(true, Ordering::Release);
        }
        self.state.store(self.to, Ordering::Release);
    }
}

/// `work(&mut state, k, item)` for every item `k`, on two workers of the
/// current pool: the caller takes items from the front, in ascending
/// order, another worker from the back, in descending order, each a piece
/// at a time, until they meet. A piece is a quarter of the items left (at
/// least one, at most [`MOST_PER_PIECE`]), so the last pieces are single
/// items and the two end within about one item's time of each other, even
/// when one core runs slower than the other (on a shared machine it may),
/// while each works through one contiguous run of items: neighbouring
/// items that read the same data stay on one worker, but where the two
/// meet. The items one worker ran are consecutive: the front's from 0, the
/// back's up to the last.
///
/// Each side makes its state with `init(front)` (`front`: whether it takes
/// items from the front) and, once no item is left for it, hands the state
/// to `finish(state, front)` before waiting for the other side, so that
/// work on a side's own items can follow at once; the two results are
/// returned, the front's first. The caller waits for the other worker by
/// spinning, as [`run_parts`] does; if the other has not started by the
/// time the caller finds no item left, the caller runs the back's `init`
/// and `finish` itself. On one thread (and for fewer than two items or more
/// than `u32::MAX`) every item runs on the caller, as the front. Which
/// worker runs an item changes no result; a panic in any item propagates
/// once both workers have ended.
pub(crate) fn from_both_ends<I: Send, S, R: Send>(
    items: Vec<I>,
    init: impl Fn(bool) -> S + Sync,
    work: impl Fn(&mut S, usize, I) + Sync,
    finish: impl Fn(S, bool) -> R + Sync,
) -> (R, R) {
    let n = items.len();
    if rayon::current_num_threads() < 2 || n < 2 || n > u32::MAX as usize {
        let mut state = init(true);
        for (k, item) in items.into_iter().enumerate() {
            work(&mut state, k, item);
        }
        return (finish(state, true), finish(init(false), false));
    }
    // One queue of [`run_on_named_workers`]' kind.
    let items = Claimed(vec![items
        .into_iter()
        .map(|i| UnsafeCell::new(Some(i)))
        .collect()]);
    // The items left: `front..back`, front in the low 32 bits.
    let left = Padded(AtomicU64::new((n as u64) << 32));
    // A piece from the front (`true`) or the back, if any item is left.
    let take = |front: bool| -> Option<std::ops::Range<usize>> {
        let mut v = left.0.load(Ordering::Relaxed);
        loop {
            let (f, b) = (v & 0xffff_ffff, v >> 32);
            if f >= b {
                return None;
            }
            let p = ((b - f) / 4).clamp(1, MOST_PER_PIECE);
            let (piece, next) = if front {
                (f..f + p, (b << 32) | (f + p))
            } else {
                (b - p..b, ((b - p) << 32) | f)
            };
            match left
                .0
                .compare_exchange_weak(v, next, Ordering::Relaxed, Ordering::Relaxed)
            {
                Ok(_) => return Some(piece.start as usize..piece.end as usize),
                Err(now) => v = now,
            }
        }
    };
    // Run every piece one side can take, then `finish`.
    let side = |front: bool| {
        let mut state = init(front);
        while let Some(piece) = take(front) {
            let mut run = |k: usize| {
                // SAFETY: `take` hands each index to one worker only.
                if let Some(Some(item)) = unsafe { items.take(0, k) } {
                    work(&mut state, k, item);
                }
            };
            if front {
                piece.for_each(&mut run);
            } else {
                piece.rev().for_each(&mut run);
            }
        }
        finish(state, front)
    };
    // The other worker's side is taken once, by whoever sets `claimed`
    // first: the other worker (which then sets `done` when its side ends
    // or its panic unwinds), or the caller, once it finds no item left.
    let (claimed, done) = (Padded(AtomicBool::new(false)), AtomicBool::new(false));
    let back_result: Mutex<Option<R>> = Mutex::new(None);
    let front = rayon::scope(|s| {
        s.spawn(|_| {
            if !claimed.0.swap(true, Ordering::AcqRel) {
                let _done = SetOnDrop(&done);
                let r = side(false);
                *back_result.lock().unwrap_or_else(PoisonError::into_inner) = Some(r);
            }
        });
        let front = side(true);
        if claimed.0.swap(true, Ordering::AcqRel) {
            spin_until(&done);
        }
        front
    });
    // The scope has ended, so the other worker's task has too (a panic in
    // it has propagated from the scope); no result: it never ran its side.
    let back = back_result
        .into_inner()
        .unwrap_or_else(PoisonError::into_inner)
        .unwrap_or_else(|| finish(init(false), false));
    (front, back)
}

/// The most items in one piece of [`from_both_ends`].
const MOST_PER_PIECE: u64 = 16;

/// Split `jobs`, each with its estimated cost, into `parts` lists (at
/// least one) of close to equal total cost, each list in ascending `order`
/// of its jobs: the costliest job first, each to the list with the least
/// so far (the first such); then, for up to 16 rounds, the move of a job,
/// or swap of two, between the costliest and the cheapest list that lowers
/// the larger of their totals most. Only speed depends on the split.
pub(crate) fn balanced_parts<J>(
    mut jobs: Vec<(u64, J)>,
    parts: usize,
    order: impl Fn(&J) -> usize,
) -> Vec<Vec<J>> {
    jobs.sort_by_key(|j| std::cmp::Reverse(j.0));
    let mut lists: Vec<(u64, Vec<(u64, J)>)> = (0..parts.max(1))
        .map(|_| (0, Vec::with_capacity(jobs.len())))
        .collect();
    for j in jobs {
        let l = lists
            .iter_mut()
            .min_by_key(|l| l.0)
            .expect("at least one list");
        l.0 += j.0;
        l.1.push(j);
    }
    // Each round lowers the larger of the two lists' totals and raises the
    // smaller one, both staying between their old totals, or the loop stops.
    for _ in 0..16 {
        let hi = (0..lists.len()).max_by_key(|&i| (lists[i].0, std::cmp::Reverse(i)));
        let lo = (0..lists.len()).min_by_key(|&i| lists[i].0);
        let (Some(hi), Some(lo)) = (hi, lo) else {
            break;
        };
        let d = lists[hi].0 - lists[lo].0;
        // Moving cost `x` from `hi` to `lo` leaves the larger of the two
        // `max(d − x, x)` above `lo`'s old total instead of `d`.
        let gain = |x: u64| if x > 0 && x < d { d - x.max(d - x) } else { 0 };
        let mut best = (0, None, None);
        for (a, ja) in lists[hi].1.iter().enumerate() {
            if gain(ja.0) > best.0 {
                best = (gain(ja.0), Some(a), None);
            }
            for (b, jb) in lists[lo].1.iter().enumerate() {
                let g = ja.0.checked_sub(jb.0).map_or(0, gain);
                if g > best.0 {
                    best = (g, Some(a), Some(b));
                }
            }
        }
        let (_, Some(a), b) = best else { break };
        let ja = lists[hi].1.swap_remove(a);
        lists[hi].0 -= ja.0;
        lists[lo].0 += ja.0;
        if let Some(b) = b {
            let jb = lists[lo].1.swap_remove(b);
            lists[lo].0 -= jb.0;
            lists[hi].0 += jb.0;
            lists[hi].1.push(jb);
        }
        lists[lo].1.push(ja);
    }
    lists
        .into_iter()
        .map(|(_, mut l)| {
            l.sort_by_key(|j| order(&j.1));
            l.into_iter().map(|j| j.1).collect()
        })
        .collect()
}

/// Sets its flag when dropped: when a job ends, or while its panic unwinds.
struct SetOnDrop<'a>(&'a AtomicBool);

impl Drop for SetOnDrop<'_> {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Release);
    }
}

/// Spin until `flag` is set, for at most [`SPIN_LIMIT`] (the waits this
/// is for are a few microseconds). A longer wait is left to the end of the
/// rayon scope the caller is in, which waits for every job in it as rayon
/// does (and does not keep a CPU busy, when workers outnumber CPUs).
fn spin_until(flag: &AtomicBool) {
    spin_while(|| !flag.load(Ordering::Acquire));
}

/// Spin while `busy()`, for at most [`SPIN_LIMIT`].
fn spin_while(busy: impl Fn() -> bool) {
    let start = Instant::now();
    let mut spins = 0u32;
    while busy() {
        spins = spins.wrapping_add(1);
        if spins.is_multiple_of(64) && start.elapsed() >= SPIN_LIMIT {
            return;
        }
        std::hint::spin_loop();
    }
}

/// Wait until `done()`: spin as [`spin_while`] does, then yield the CPU
/// between checks, for as long as it takes.
pub(crate) fn wait_until(done: impl Fn() -> bool) {
    spin_while(|| !done());
    while !done() {
        std::thread::yield_now();
    }
}

/// How long [`spin_until`] spins at most.
const SPIN_LIMIT: Duration = Duration::from_micros(100);

/// The CPUs the calling thread may run on, ascending (empty if the system
/// does not say).
#[cfg(target_os = "linux")]
fn allowed_cpus() -> Vec<usize> {
    // SAFETY: `cpu_set_t` is plain data for which all-zero is the empty set;
    // `sched_getaffinity` writes at most `size_of::<cpu_set_t>()` bytes into
    // it, and `CPU_ISSET` reads it within bounds (`CPU_SETSIZE`).
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) != 0 {
            return Vec::new();
        }
        (0..libc::CPU_SETSIZE as usize)
            .filter(|&c| libc::CPU_ISSET(c, &set))
            .collect()
    }
}

/// Restrict the calling thread to `cpu`; returns whether the system
/// accepted (a refusal leaves it as it was, which changes only speed).
#[cfg(target_os = "linux")]
fn pin_to(cpu: usize) -> bool {
    // SAFETY: as in `allowed_cpus`; `cpu < CPU_SETSIZE` since it came from
    // that range, and pid 0 is the calling thread.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        libc::CPU_SET(cpu, &mut set);
        libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set) == 0
    }
}

/// How long a worker kept awake by [`keep_awake`] polls without finding
/// work, or after the call it polls for ended, before it returns to rayon's
/// own idling (a few polls, then sleep).
const AWAKE_IDLE_LIMIT: Duration = Duration::from_millis(1);

/// The longest one poll lasts, however many calls take it over: a worker
/// that took up polling while it waited inside a join returns to that join
/// after at most this long (plus the job it is running), even while other
/// threads' calls follow each other closely.
const AWAKE_MAX_POLL: Duration = Duration::from_millis(20);

/// One [`keep_awake`] call, as the workers polling for it see it.
struct Call {
    /// When the call ended; unset while it runs.
    end: OnceLock<Instant>,
}

impl Call {
    /// Whether the call ended over [`AWAKE_IDLE_LIMIT`] ago.
    fn over(&self) -> bool {
        self.end
            .get()
            .is_some_and(|e| e.elapsed() > AWAKE_IDLE_LIMIT)
    }
}

thread_local! {
    /// Whether this thread is running a [`keep_awake`] closure.
    static IN_CALL: Cell<bool> = const { Cell::new(false) };
    /// The call this thread polls for, while it polls: the latest whose
    /// workers it was asked to join.
    static POLL_FOR: RefCell<Option<Arc<Call>>> = const { RefCell::new(None) };
}

/// Run `f`, keeping the other workers of the current pool (the global pool
/// when called from outside any pool) polling for work instead of going to
/// sleep whenever `f` runs a serial step. A polling worker runs the jobs of
/// the pool that it finds, and stops polling once it has found none for
/// 1 ms, once the latest call it polls for ended 1 ms ago, or after 20 ms
/// of polling, whichever comes first (checked between jobs). So a serial
/// step longer than 1 ms lets it sleep until the next call starts (each
/// call asks every other worker once); a call that starts while a worker
/// still polls (the next pass, the next training step, within 1 ms) takes
/// over that poll, which then lasts until 1 ms after the new call ends,
/// under the same idle and length limits; and a worker that took up
/// polling while it waited inside a join returns to that join within about
/// 1 ms of the call's end and at most 20 ms after it began polling, plus
/// the job it is running, however busy the pool is. Changes speed only,
/// never results. A call inside another on this thread and a pool of one
/// thread just run `f`.
pub fn keep_awake<R>(f: impl FnOnce() -> R) -> R {
    if rayon::current_num_threads() < 2 || IN_CALL.with(Cell::get) {
        return f();
    }
    let call = Arc::new(Call {
        end: OnceLock::new(),
    });
    struct End(Arc<Call>);
    impl Drop for End {
        fn drop(&mut self) {
            IN_CALL.with(|a| a.set(false));
            let _ = self.0.end.set(Instant::now());
        }
    }
    IN_CALL.with(|a| a.set(true));
    let _end = End(call.clone());
    let owner = rayon::current_thread_index();
    rayon::spawn_broadcast(move |ctx| {
        // A worker running a call of its own is awake; one already polling
        // (this job then runs inside its poll) polls on for this call
        // rather than nesting another poll; a job that arrives after its
        // call is over neither starts a poll nor takes one over.
        if Some(ctx.index()) == owner || IN_CALL.with(Cell::get) || call.over() {
            return;
        }
        let was_polling = POLL_FOR.with(|p| p.borrow_mut().replace(call.clone()).is_some());
        if !was_polling {
            poll();
        }
    });
    f()
}

/// Run the pool's jobs as they come until none came for
/// [`AWAKE_IDLE_LIMIT`], until the call polled for is over
/// ([`Call::over`]), or for at most [`AWAKE_MAX_POLL`].
fn poll() {
    let start = Instant::now();
    let mut idle_since = start;
    loop {
        if start.elapsed() > AWAKE_MAX_POLL
            || POLL_FOR.with(|p| p.borrow().as_ref().is_none_or(|c| c.over()))
        {
            break;
        }
        match rayon::yield_now() {
            Some(rayon::Yield::Executed) => idle_since = Instant::now(),
            _ if idle_since.elapsed() > AWAKE_IDLE_LIMIT => break,
            // As rayon's own idle loop: a busy loop of polls (or of
            // `spin_loop` hints between them) made the rasterizer's forward
            // half as slow again in training on 2 cores.
            _ => std::thread::yield_now(),
        }
    }
    POLL_FOR.with(|p| p.borrow_mut().take());
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;

    #[test]
    fn pinned_workers_each_run_on_their_cpu() {
        let cpus = allowed_cpus();
        // Where the system refuses to pin (or there is one CPU), there is
        // nothing to observe.
        let accepted = std::thread::spawn({
            let c = cpus[0];
            move || pin_to(c)
        })
        .join()
        .unwrap();
        if cpus.len() < 2 || !accepted {
            return;
        }
        // Pinning is process-wide state: it is on only while the pool is
        // built (other tests build unpinned pools meanwhile, at worst
        // pinned ones, which changes only speed).
        set_pinning(true);
        let pinned = pool(3);
        let from_second = pool_from(2, 1);
        set_pinning(false);
        let got = pinned
            .unwrap()
            .broadcast(|ctx| (ctx.index(), allowed_cpus()));
        for (i, set) in got {
            assert_eq!(set, vec![cpus[i % cpus.len()]], "worker {i}");
        }
        let got = from_second
            .unwrap()
            .broadcast(|ctx| (ctx.index(), allowed_cpus()));
        for (i, set) in got {
            assert_eq!(
                set,
                vec![cpus[(1 + i) % cpus.len()]],
                "worker {i} from CPU 1"
            );
        }
    }
}

#[cfg(test)]
mod awake_tests {
    use super::*;
    use rayon::prelude::*;
    use std::sync::mpsc;

    fn in_pool<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
        pool(threads).unwrap().install(f)
    }

    /// `f()` on another thread, failing the test (instead of hanging it)
    /// if it has not returned within a minute.
    pub(super) fn within_a_minute<R: Send + 'static>(f: impl FnOnce() -> R + Send + 'static) -> R {
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(f());
        });
        rx.recv_timeout(Duration::from_secs(60))
            .expect("did not return within a minute")
    }

    fn squares(n: u64) -> u64 {
        (0..n).into_par_iter().map(|i| i * i).sum()
    }

    #[test]
    fn keep_awake_returns_the_result_and_nests() {
        let want = (0..10_000u64).map(|i| i * i).sum::<u64>();
        for threads in [1, 2, 3] {
            let got = in_pool(threads, || {
                let r = keep_awake(|| {
                    // Inside a call, a nested call leaves the flag set.
                    let inner = keep_awake(|| squares(10_000));
                    assert!(IN_CALL.with(Cell::get) || threads < 2);
                    inner + keep_awake(|| 0)
                });
                (r, IN_CALL.with(Cell::get))
            });
            assert_eq!(got, (want, false), "{threads} threads");
        }
        // Outside any pool: the global pool's workers.
        assert_eq!(keep_awake(|| squares(10_000)), want);
        assert!(!IN_CALL.with(Cell::get));
    }

    #[test]
    fn a_panic_inside_propagates_and_resets() {
        let (caught, after, flag) = in_pool(2, || {
            let caught = std::panic::catch_unwind(|| keep_awake(|| panic!("inside"))).is_err();
            (caught, squares(1_000), IN_CALL.with(Cell::get))
        });
        assert!(caught);
        assert_eq!(after, (0..1_000u64).map(|i| i * i).sum::<u64>());
        assert!(!flag);
    }

    #[test]
    fn calls_in_a_row_do_not_nest_their_polls() {
        // Each call's polls find the previous call's still going; nested,
        // 20,000 of them would overflow a worker's stack.
        let want = (0..64u64).map(|i| i * i).sum::<u64>();
        let got = within_a_minute(|| {
            in_pool(2, || (0..20_000).map(|_| keep_awake(|| squares(64))).max())
        });
        assert_eq!(got, Some(want));
    }

    #[test]
    fn parallel_calls_inside_parallel_work_finish() {
        // Each task of an outer parallel loop calls `keep_awake` around
        // parallel work of its own, so polling workers take jobs of other
        // calls and other calls' broadcasts reach workers that are busy.
        for threads in [2, 3, 4] {
            let got = within_a_minute(move || {
                in_pool(threads, || {
                    (0..32u64)
                        .into_par_iter()
                        .map(|k| keep_awake(|| squares(2_000 + k)))
                        .collect::<Vec<_>>()
                })
            });
            let want: Vec<u64> = (0..32u64)
                .map(|k| (0..2_000 + k).map(|i| i * i).sum())
                .collect();
            assert_eq!(got, want, "{threads} threads");
        }
    }

    /// Whether this thread is polling for [`keep_awake`].
    fn polling() -> bool {
        POLL_FOR.with(|p| p.borrow().is_some())
    }

    /// Busy-wait for `us` microseconds.
    pub(super) fn spin(us: u64) {
        let t = Instant::now();
        while t.elapsed() < Duration::from_micros(us) {}
    }

    #[test]
    fn a_polling_worker_makes_calls_of_its_own() {
        // A job that a polling worker runs and that calls `keep_awake` is a
        // call of its own (its closure flagged as one, and polling not
        // flagged as one), not a no-op.
        let seen = within_a_minute(|| {
            in_pool(2, || {
                (0..200).find_map(|_| {
                    keep_awake(|| {
                        (0..64)
                            .into_par_iter()
                            .filter_map(|_| {
                                spin(20);
                                polling().then(|| {
                                    let before = IN_CALL.with(Cell::get);
                                    !before && keep_awake(|| IN_CALL.with(Cell::get))
                                })
                            })
                            .reduce_with(|a, b| a && b)
                    })
                })
            })
        });
        assert_eq!(
            seen,
            Some(true),
            "None: no job ran on a polling worker in 200 tries"
        );
    }

    #[test]
    fn polls_end_after_the_last_call_however_busy_the_pool() {
        // After a call, a feeder keeps the pool's workers finding work; the
        // polls must still end about 1 ms after the call.
        let pool = Arc::new(pool(2).unwrap());
        let stop = Arc::new(AtomicBool::new(false));
        pool.install(|| keep_awake(|| squares(10_000)));
        let feeder = std::thread::spawn({
            let (pool, stop) = (pool.clone(), stop.clone());
            move || {
                while !stop.load(Ordering::Relaxed) {
                    pool.spawn(|| spin(20));
                    spin(40);
                }
            }
        });
        std::thread::sleep(Duration::from_millis(30));
        // A broadcast job runs inside a poll where one is still going.
        let polling = pool.broadcast(|_| polling());
        stop.store(true, Ordering::Relaxed);
        feeder.join().unwrap();
        assert_eq!(polling, [false, false]);
    }

    #[test]
    fn a_poll_lasts_at_most_its_cap_however_long_the_call() {
        // A call that lasts five caps and keeps the other worker finding
        // work: that worker's poll must end within the cap (checked before
        // each job), while it goes on running the call's jobs. A poll can
        // also end early, on the idle limit, if this thread is descheduled
        // for over 1 ms; the call is then tried again (up to 5 times) so
        // that the cap, not the idle limit, ends the poll checked.
        let pool = pool(2).unwrap();
        let call_len = 5 * AWAKE_MAX_POLL;
        for _ in 0..5 {
            let seen = std::sync::Mutex::new(Vec::new());
            pool.install(|| {
                keep_awake(|| {
                    let me = rayon::current_thread_index();
                    let t0 = Instant::now();
                    rayon::scope(|s| {
                        while t0.elapsed() < call_len {
                            s.spawn(|_| {
                                // When each job starts, on the other
                                // worker, and whether it is polling.
                                if rayon::current_thread_index() != me {
                                    seen.lock().unwrap().push((Instant::now(), polling()));
                                }
                                spin(20);
                            });
                            spin(40);
                        }
                    });
                })
            });
            let seen = seen.into_inner().unwrap();
            let polled: Vec<Instant> = seen.iter().filter(|s| s.1).map(|s| s.0).collect();
            let (Some(first), Some(last)) = (polled.first(), polled.last()) else {
                panic!("the other worker never polled ({} jobs)", seen.len());
            };
            // The jobs a poll runs start within its cap (plus a scheduling
            // margin: a job's clock is read after the check before it).
            let span = *last - *first;
            assert!(
                span < AWAKE_MAX_POLL + Duration::from_millis(10),
                "polled for {span:?}"
            );
            if span > AWAKE_MAX_POLL / 2 {
                return;
            }
        }
    }
}

#[cfg(test)]
mod parts_tests {
    use super::awake_tests::{spin, within_a_minute};
    use super::*;
    use std::panic::{catch_unwind, AssertUnwindSafe};

    fn totals(lists: &[Vec<(u64, usize)>]) -> Vec<u64> {
        lists.iter().map(|l| l.iter().map(|j| j.0).sum()).collect()
    }

    #[test]
    fn balanced_parts_swap_what_the_greedy_split_leaves_uneven() {
        // Greedy, costliest first: {5, 3} and {4, 3, 3}, totals 8 and 10;
        // swapping a 4 for a 3 makes 9 and 9.
        let jobs: Vec<(u64, (u64, usize))> = [5, 4, 3, 3, 3]
            .iter()
            .enumerate()
            .map(|(i, &c)| (c, (c, i)))
            .collect();
        let lists = balanced_parts(jobs, 2, |j| j.1);
        assert_eq!(totals(&lists), vec![9, 9]);
    }

    /// The largest total of the greedy split alone (costliest first, each
    /// to the first list with the least so far).
    fn greedy_max(mut costs: Vec<u64>, parts: usize) -> u64 {
        costs.sort_unstable_by(|a, b| b.cmp(a));
        let mut t = vec![0u64; parts];
        for c in costs {
            let i = (0..parts).min_by_key(|&i| t[i]).unwrap();
            t[i] += c;
        }
        t.into_iter().max().unwrap_or(0)
    }

    #[test]
    fn balanced_parts_keep_every_job_once_in_order() {
        let mut rng = crate::math::rng::Rng::new(7);
        for parts in 1..=4 {
            for n in [0, 1, 3, 17, 40] {
                let jobs: Vec<(u64, (u64, usize))> = (0..n)
                    .map(|i| {
                        let c = 1 + rng.next_u64() % 1000;
                        (c, (c, i))
                    })
                    .collect();
                let max_cost = jobs.iter().map(|j| j.0).max().unwrap_or(0);
                let greedy = greedy_max(jobs.iter().map(|j| j.0).collect(), parts);
                let lists = balanced_parts(jobs, parts, |j| j.1);
                assert_eq!(lists.len(), parts);
                let mut seen: Vec<usize> = lists.iter().flatten().map(|j| j.1).collect();
                for l in &lists {
                    assert!(
                        l.windows(2).all(|w| w[0].1 < w[1].1),
                        "{parts} parts, {n} jobs: order"
                    );
                }
                seen.sort_unstable();
                assert_eq!(seen, (0..n).collect::<Vec<_>>(), "{parts} parts, {n} jobs");
                let t = totals(&lists);
                let spread = t.iter().max().unwrap() - t.iter().min().unwrap();
                assert!(spread <= max_cost, "{parts} parts, {n} jobs: totals {t:?}");
                assert!(
                    *t.iter().max().unwrap() <= greedy,
                    "{parts} parts, {n} jobs: {t:?}"
                );
            }
        }
    }

    #[test]
    fn workers_with_a_cpu_are_the_pools_threads_up_to_the_cpus() {
        // (Unpinned: pinning is process-wide state that another test may
        // turn on; `cores` then reads the CPUs read when it was.)
        let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
        for threads in [1, 2, cpus, cpus + 1, cpus + 3] {
            let got = pool(threads).unwrap().install(workers_with_a_cpu);
            if !pinning() {
                assert_eq!(got, threads.min(cpus), "{threads} threads on {cpus} CPUs");
            }
            assert!((1..=threads).contains(&got), "{threads} threads: {got}");
        }
    }

    #[test]
    fn run_parts_runs_each_part_once_on_any_pool() {
        for threads in 1..=3 {
            let seen = within_a_minute(move || {
                pool(threads).unwrap().install(|| {
                    let seen = Mutex::new(Vec::new());
                    let parts: Vec<Vec<usize>> =
                        (0..5).map(|p| (10 * p..10 * p + 3).collect()).collect();
                    run_parts(parts, |part| seen.lock().unwrap().extend(part));
                    seen.into_inner().unwrap()
                })
            });
            let mut seen = seen;
            seen.sort_unstable();
            let want: Vec<usize> = (0..5).flat_map(|p| 10 * p..10 * p + 3).collect();
            assert_eq!(seen, want, "{threads} threads");
        }
    }

    #[test]
    fn named_workers_run_each_job_once_and_return_beside() {
        for threads in 1..=3 {
            let (seen, inits, r) = within_a_minute(move || {
                pool(threads).unwrap().install(|| {
                    let seen = Mutex::new(Vec::new());
                    let inits = AtomicUsize::new(0);
                    // Names beyond the pool's size wrap around.
                    let jobs: Vec<(usize, usize)> = (0..40).map(|j| (j % 5, j)).collect();
                    let r = run_on_named_workers(
                        jobs,
                        || inits.fetch_add(1, Ordering::Relaxed),
                        |_, j| seen.lock().unwrap().push(j),
                        || 7u32,
                    );
                    (seen.into_inner().unwrap(), inits.into_inner(), r)
                })
            });
            let mut seen = seen;
            seen.sort_unstable();
            assert_eq!(seen, (0..40).collect::<Vec<_>>(), "{threads} threads");
            assert_eq!(inits, threads, "one state per task, {threads} threads");
            assert_eq!(r, 7);
        }
    }

    #[test]
    fn named_workers_propagate_a_panic_without_hanging() {
        for threads in 1..=3 {
            let (job, beside, ran) = within_a_minute(move || {
                pool(threads).unwrap().install(|| {
                    let ran = AtomicUsize::new(0);
                    let jobs: Vec<(usize, usize)> = (0..12).map(|j| (j % 2, j)).collect();
                    let job = catch_unwind(AssertUnwindSafe(|| {
                        run_on_named_workers(
                            jobs,
                            || (),
                            |_, j| {
                                if j == 5 {
                                    panic!("job 5");
                                }
                                ran.fetch_add(1, Ordering::Relaxed);
                            },
                            || (),
                        )
                    }));
                    let jobs: Vec<(usize, usize)> = (0..12).map(|j| (j % 2, j)).collect();
                    let beside = catch_unwind(AssertUnwindSafe(|| {
                        run_on_named_workers(jobs, || (), |_, _| {}, || -> u32 { panic!("beside") })
                    }));
                    (job.is_err(), beside.is_err(), ran.into_inner())
                })
            });
            assert!(job && beside, "{threads} threads");
            // On one thread the jobs after the panicking one never start;
            // on more, only the panicking task stops: the others take
            // every job left.
            let want = if threads == 1 { 5 } else { 11 };
            assert_eq!(ran, want, "{threads} threads");
        }
    }

    #[test]
    fn named_workers_run_a_busy_workers_jobs() {
        // One worker spins until the call ends, so the other runs every
        // task, and the busy worker's jobs only by taking them from its
        // queue.
        let (seen, workers) = within_a_minute(|| {
            pool(2).unwrap().install(|| {
                let done = AtomicBool::new(false);
                let seen = Mutex::new(Vec::new());
                let workers = Mutex::new(Vec::new());
                rayon::join(
                    || wait_a_while_for(&done),
                    || {
                        let _done = SetOnDrop(&done);
                        let jobs: Vec<(usize, usize)> = (0..20).map(|j| (j % 2, j)).collect();
                        run_on_named_workers(
                            jobs,
                            || (),
                            |_, j| {
                                seen.lock().unwrap().push(j);
                                workers.lock().unwrap().push(worker_index());
                            },
                            || (),
                        );
                    },
                );
                (seen.into_inner().unwrap(), workers.into_inner().unwrap())
            })
        });
        let mut seen = seen;
        seen.sort_unstable();
        assert_eq!(seen, (0..20).collect::<Vec<_>>());
        // (Unless the spinning worker gave up after its second.)
        eprintln!("workers that ran the jobs: {workers:?}");
    }

    /// Wait until `flag` is set, or a second has passed (on one thread no
    /// other worker ever sets it).
    fn wait_a_while_for(flag: &AtomicBool) {
        let start = Instant::now();
        while !flag.load(Ordering::Acquire) && start.elapsed() < Duration::from_secs(1) {
            std::thread::yield_now();
        }
    }

    #[test]
    fn run_parts_and_from_both_ends_propagate_a_panic_without_hanging() {
        // The caller's own part (or first item) waits until another worker
        // has started the part (or item) that panics, so that on two or
        // more threads the caller waits for a panicking worker.
        for threads in 1..=3 {
            let (parts, join_b, join_a) = within_a_minute(move || {
                pool(threads).unwrap().install(|| {
                    let started = AtomicBool::new(false);
                    let parts = catch_unwind(AssertUnwindSafe(|| {
                        run_parts(vec![0, 1, 2], |p| match p {
                            0 => wait_a_while_for(&started),
                            1 => {
                                started.store(true, Ordering::Release);
                                panic!("part 1");
                            }
                            _ => {}
                        })
                    }));
                    let started = AtomicBool::new(false);
                    let join_b = catch_unwind(AssertUnwindSafe(|| {
                        from_both_ends(
                            (0..8).collect(),
                            |_| (),
                            |_, _, k| match k {
                                0 => wait_a_while_for(&started),
                                7 => {
                                    started.store(true, Ordering::Release);
                                    panic!("the back's first item")
                                }
                                _ => {}
                            },
                            |_, _| (),
                        )
                    }));
                    let join_a = catch_unwind(AssertUnwindSafe(|| {
                        from_both_ends(
                            (0..8).collect(),
                            |_| (),
                            |_, _, k: usize| assert_ne!(k, 0, "the front's first item"),
                            |_, _| (),
                        )
                    }));
                    (parts.is_err(), join_b.is_err(), join_a.is_err())
                })
            });
            assert!(parts && join_b && join_a, "{threads} threads");
        }
    }

    #[test]
    fn two_steps_run_each_step_once_every_first_before_any_second() {
        for threads in 1..=3 {
            for parts in [1, 2, 3, 5] {
                let (firsts, between, seconds) = within_a_minute(move || {
                    pool(threads).unwrap().install(|| {
                        let firsts = Mutex::new(Vec::new());
                        let between = Mutex::new(None);
                        let seconds = Mutex::new(Vec::new());
                        let ended = std::sync::atomic::AtomicUsize::new(0);
                        run_parts_in_two_steps(
                            (0..parts).map(|p| (p, 10 + p)).collect(),
                            |a| {
                                // Slow enough that a second step started
                                // too early would see it unfinished.
                                spin(20 * (a as u64 + 1));
                                firsts.lock().unwrap().push(a);
                                ended.fetch_add(1, Ordering::Release);
                            },
                            || *between.lock().unwrap() = Some(ended.load(Ordering::Acquire)),
                            |b| {
                                let seen = ended.load(Ordering::Acquire);
                                seconds.lock().unwrap().push((b, seen));
                            },
                        );
                        (
                            firsts.into_inner().unwrap(),
                            between.into_inner().unwrap(),
                            seconds.into_inner().unwrap(),
                        )
                    })
                });
                let what = format!("{threads} threads, {parts} parts");
                let mut firsts = firsts;
                firsts.sort_unstable();
                assert_eq!(firsts, (0..parts).collect::<Vec<_>>(), "{what}");
                assert_eq!(between, Some(parts), "{what}");
                let mut seconds = seconds;
                seconds.sort_unstable();
                let want: Vec<_> = (0..parts).map(|p| (10 + p, parts)).collect();
                assert_eq!(seconds, want, "{what}");
            }
        }
    }

    #[test]
    fn two_steps_propagate_a_panic_and_skip_the_second_steps() {
        for threads in 1..=3 {
            for panicking in [0, 1] {
                let (panicked, seconds) = within_a_minute(move || {
                    pool(threads).unwrap().install(|| {
                        let seconds = Mutex::new(0);
                        let r = catch_unwind(AssertUnwindSafe(|| {
                            run_parts_in_two_steps(
                                vec![(0, ()), (1, ()), (2, ())],
                                |a| {
                                    spin(50);
                                    assert!(a != panicking, "first step {a}");
                                },
                                || {},
                                |()| *seconds.lock().unwrap() += 1,
                            )
                        }));
                        (r.is_err(), seconds.into_inner().unwrap())
                    })
                });
                assert!(panicked, "{threads} threads, part {panicking}");
                assert_eq!(seconds, 0, "{threads} threads, part {panicking}");
            }
            let panicked = within_a_minute(move || {
                pool(threads).unwrap().install(|| {
                    catch_unwind(AssertUnwindSafe(|| {
                        run_parts_in_two_steps(
                            vec![((), 0), ((), 1)],
                            |()| {},
                            || {},
                            |b| assert!(b != 1, "second step 1"),
                        )
                    }))
                    .is_err()
                })
            });
            assert!(panicked, "{threads} threads, a second step");
        }
    }

    #[test]
    fn one_job_runs_once_whoever_asks_and_wait_sees_its_end() {
        for threads in 1..=3 {
            let runs = within_a_minute(move || {
                pool(threads).unwrap().install(|| {
                    let runs = std::sync::atomic::AtomicUsize::new(0);
                    let job = OneJob::new(|| {
                        std::thread::sleep(Duration::from_millis(5));
                        runs.fetch_add(1, Ordering::Relaxed);
                    });
                    rayon::scope(|s| {
                        s.spawn(|_| job.run());
                        job.wait();
                        // Ended, whoever ran it.
                        assert_eq!(runs.load(Ordering::Relaxed), 1);
                        job.run();
                        job.wait();
                    });
                    runs.into_inner()
                })
            });
            assert_eq!(runs, 1, "{threads} threads");
        }
        // A panicking job: `wait` returns once it has unwound.
        let job = OneJob::new(|| panic!("job"));
        let r = catch_unwind(AssertUnwindSafe(|| job.run()));
        assert!(r.is_err());
        job.wait();
    }

    #[test]
    fn from_both_ends_runs_each_item_once_in_two_consecutive_runs() {
        for threads in 1..=3 {
            for n in [0usize, 1, 2, 3, 5, 64, 1000] {
                let (front, back) = within_a_minute(move || {
                    pool(threads).unwrap().install(|| {
                        from_both_ends(
                            (0..n).map(|k| k * 10).collect(),
                            |front| (front, Vec::new()),
                            |(_, ran): &mut (bool, Vec<usize>), k, item| {
                                assert_eq!(item, k * 10, "item {k}");
                                ran.push(k);
                            },
                            |(side, ran), front| {
                                assert_eq!(side, front, "finish told the side init was");
                                (front, ran)
                            },
                        )
                    })
                });
                let tag = format!("{threads} threads, {n} items");
                assert!(front.0 && !back.0, "{tag}: front's result first");
                let m = front.1.len();
                assert_eq!(front.1, (0..m).collect::<Vec<_>>(), "{tag}: the front");
                assert_eq!(back.1, (m..n).rev().collect::<Vec<_>>(), "{tag}: the back");
                if threads == 1 {
                    assert_eq!(m, n, "{tag}: one thread runs every item from the front");
                }
            }
        }
    }
}
