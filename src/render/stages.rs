//! Optional per-stage timing of the rasterizer, for benchmarks.
//!
//! [`record`] runs a closure with the calling thread's stage clock on;
//! [`rasterize`](super::rasterize()) and [`rasterize_vjp`](super::rasterize_vjp())
//! call `mark` at the end of each stage, which (only while the clock is
//! on) appends the stage's wall time and the process CPU time spent during
//! it. CPU time over wall time is the parallelism a stage reached (idle
//! workers that spin while waiting for work count as busy). With the clock
//! off a mark is one thread-local read. Results never depend on it.

use std::cell::RefCell;
use std::time::Instant;

/// The time one stage took.
#[derive(Clone, Debug, PartialEq)]
pub struct StageTime {
    /// The stage's name (see the marks in `render`).
    pub name: &'static str,
    /// Wall-clock seconds.
    pub wall: f64,
    /// Process CPU seconds (all threads), `None` where the platform does
    /// not report it.
    pub cpu: Option<f64>,
}

struct Clock {
    wall: Instant,
    cpu: Option<f64>,
    stages: Vec<StageTime>,
}

thread_local! {
    static CLOCK: RefCell<Option<Clock>> = const { RefCell::new(None) };
}

/// `f()` with the stage clock of this thread on, and the stages it marked in
/// order (the rasterizer's own, when `f` calls it on this thread).
pub fn record<R>(f: impl FnOnce() -> R) -> (R, Vec<StageTime>) {
    CLOCK.with(|c| {
        *c.borrow_mut() = Some(Clock {
            wall: Instant::now(),
            cpu: crate::bench::harness::process_cpu_seconds(),
            stages: Vec::new(),
        })
    });
    let r = f();
    let stages = CLOCK.with(|c| c.borrow_mut().take().map(|c| c.stages).unwrap_or_default());
    (r, stages)
}

/// End the stage `name`: when the clock is on, record the time since the
/// previous mark (or since [`record`] started).
pub(crate) fn mark(name: &'static str) {
    CLOCK.with(|c| {
        if let Some(c) = c.borrow_mut().as_mut() {
            let wall = Instant::now();
            let cpu = crate::bench::harness::process_cpu_seconds();
            c.stages.push(StageTime {
                name,
                wall: (wall - c.wall).as_secs_f64(),
                cpu: cpu.zip(c.cpu).map(|(a, b)| a - b),
            });
            c.wall = wall;
            c.cpu = cpu;
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn marks_are_recorded_only_inside_record() {
        mark("outside");
        let ((), st) = record(|| {
            mark("a");
            mark("b");
        });
        assert_eq!(st.iter().map(|s| s.name).collect::<Vec<_>>(), ["a", "b"]);
        assert!(st.iter().all(|s| s.wall >= 0.0));
        let ((), st) = record(|| {});
        assert!(st.is_empty());
    }
}
