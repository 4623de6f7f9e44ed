//! Optional per-operation timing of the deformation fields, for
//! `liquid-splat bench deform`: every matrix product and every separate
//! element-wise pass of a field's forward and backward, with its shape and
//! FLOPs, so where the time goes stays visible.
//!
//! Off by default: then each instrumented operation costs one relaxed atomic
//! load, and no label is built. Timing changes no result. Records are kept
//! per process; operations run on the calling thread (their products use the
//! rayon pool inside), so the layer names are a per-thread stack.

use std::cell::RefCell;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Instant;

static ON: AtomicBool = AtomicBool::new(false);
static LOG: Mutex<Vec<Record>> = Mutex::new(Vec::new());

thread_local! {
    static LAYERS: RefCell<Vec<String>> = const { RefCell::new(Vec::new()) };
}

/// What kind of work an operation is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// A matrix product (with whatever epilogue is fused into it).
    Product,
    /// A separate element-wise pass (or a reduction over rows).
    Elementwise,
}

/// One timed operation.
#[derive(Clone, Debug)]
pub struct Record {
    /// The enclosing layers, outermost first, then the operation
    /// (`"cfc forward / cell 0 / heads / x·Wᵀ (+ gate, update)"`).
    pub label: String,
    /// Product or element-wise pass.
    pub kind: Kind,
    /// Operand shapes, for example `[20000,64]·[64,512]`.
    pub shape: String,
    /// Floating-point operations (2 per multiply-add of a product; for an
    /// element-wise pass, its element count).
    pub work: f64,
    /// Wall time of the operation, seconds.
    pub seconds: f64,
}

/// Turn recording on or off (off by default).
pub fn enable(on: bool) {
    ON.store(on, Ordering::Relaxed);
}

/// Whether recording is on.
#[inline]
pub fn enabled() -> bool {
    ON.load(Ordering::Relaxed)
}

/// The records so far, in the order the operations finished; clears them.
pub fn take() -> Vec<Record> {
    std::mem::take(&mut *LOG.lock().unwrap_or_else(|e| e.into_inner()))
}

/// Run `f` with `name` pushed on this thread's layer stack (labels of the
/// operations inside start with it). Free when recording is off.
pub fn layer<R>(name: impl FnOnce() -> String, f: impl FnOnce() -> R) -> R {
    if !enabled() {
        return f();
    }
    LAYERS.with(|l| l.borrow_mut().push(name()));
    let r = f();
    LAYERS.with(|l| l.borrow_mut().pop());
    r
}

/// Run and time `f`, one operation of `kind` (see [`Record`]); `what` and
/// `shape` are only built when recording is on.
pub fn op<R>(
    kind: Kind,
    what: impl FnOnce() -> String,
    shape: impl FnOnce() -> String,
    work: f64,
    f: impl FnOnce() -> R,
) -> R {
    if !enabled() {
        return f();
    }
    let t0 = Instant::now();
    let r = f();
    let seconds = t0.elapsed().as_secs_f64();
    let mut label = LAYERS.with(|l| l.borrow().join(" / "));
    if !label.is_empty() {
        label.push_str(" / ");
    }
    label.push_str(&what());
    let rec = Record {
        label,
        kind,
        shape: shape(),
        work,
        seconds,
    };
    LOG.lock().unwrap_or_else(|e| e.into_inner()).push(rec);
    r
}

/// [`op`] for a product `[m, k]·[k, n]` (`2·m·k·n` FLOPs).
pub fn product<R>(
    what: impl FnOnce() -> String,
    m: usize,
    k: usize,
    n: usize,
    f: impl FnOnce() -> R,
) -> R {
    op(
        Kind::Product,
        what,
        || format!("[{m},{k}]·[{k},{n}]"),
        2.0 * (m * k * n) as f64,
        f,
    )
}

/// [`op`] for an element-wise pass over `shape` (`rows × cols` elements).
pub fn elementwise<R>(
    what: impl FnOnce() -> String,
    rows: usize,
    cols: usize,
    f: impl FnOnce() -> R,
) -> R {
    op(
        Kind::Elementwise,
        what,
        || format!("[{rows},{cols}]"),
        (rows * cols) as f64,
        f,
    )
}

/// One operation of a fused pass (see [`Tally`]): what it is, its shape,
/// its work per call and how many calls a pass makes.
pub struct TallyOp {
    what: String,
    kind: Kind,
    shape: String,
    work: f64,
    calls: usize,
}

impl TallyOp {
    /// A product `[m, k]·[k, n]` (each call's shape, over all the blocks
    /// of rows it is split into) run `calls` times in a pass.
    pub fn product(what: &str, m: usize, k: usize, n: usize, calls: usize) -> Self {
        TallyOp {
            what: what.to_string(),
            kind: Kind::Product,
            shape: format!("[{m},{k}]·[{k},{n}]"),
            work: 2.0 * (m * k * n) as f64,
            calls,
        }
    }

    /// An element-wise pass over `rows × cols` (each call's) run `calls`
    /// times in a pass.
    pub fn elementwise(what: &str, rows: usize, cols: usize, calls: usize) -> Self {
        TallyOp {
            what: what.to_string(),
            kind: Kind::Elementwise,
            shape: format!("[{rows},{cols}]"),
            work: (rows * cols) as f64,
            calls,
        }
    }
}

/// The operations of a fused parallel pass (one that runs every operation
/// on a block of rows after the other, on every thread): each operation's
/// time is summed over the blocks and threads, and recorded as that CPU time
/// divided by the thread count (the operation's share of the pass's wall
/// time when the threads are busy), with the label marked `(fused)`.
pub struct Tally {
    prefix: String,
    ops: Vec<TallyOp>,
    nanos: Vec<AtomicU64>,
}

impl Tally {
    /// A tally of `ops` (built only when recording is on; `None` when off).
    pub fn new(ops: impl FnOnce() -> Vec<TallyOp>) -> Option<Self> {
        if !enabled() {
            return None;
        }
        let ops = ops();
        let mut prefix = LAYERS.with(|l| l.borrow().join(" / "));
        if !prefix.is_empty() {
            prefix.push_str(" / ");
        }
        Some(Tally {
            prefix,
            nanos: ops.iter().map(|_| AtomicU64::new(0)).collect(),
            ops,
        })
    }

    /// Run `f`, adding its time to operation `op` of `tally` (just run it
    /// when there is no tally).
    #[inline]
    pub fn time<R>(tally: Option<&Tally>, op: usize, f: impl FnOnce() -> R) -> R {
        match tally {
            None => f(),
            Some(t) => {
                let t0 = Instant::now();
                let r = f();
                let ns = t0.elapsed().as_nanos() as u64;
                t.nanos[op].fetch_add(ns, Ordering::Relaxed);
                r
            }
        }
    }

    /// Record every operation (its calls as separate records of equal
    /// share, so that a table summing calls shows the count).
    pub fn finish(self) {
        let threads = rayon::current_num_threads().max(1) as f64;
        let mut log = LOG.lock().unwrap_or_else(|e| e.into_inner());
        for (op, ns) in self.ops.into_iter().zip(self.nanos) {
            let calls = op.calls.max(1);
            let seconds = ns.into_inner() as f64 * 1e-9 / threads / calls as f64;
            for _ in 0..op.calls {
                log.push(Record {
                    label: format!("{}{} (fused)", self.prefix, op.what),
                    kind: op.kind,
                    shape: op.shape.clone(),
                    work: op.work,
                    seconds,
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Labels nest; nothing is recorded while off.
    #[test]
    fn records_nest_and_only_when_on() {
        let run = || {
            layer(
                || "outer".into(),
                || {
                    product(|| "p".into(), 2, 3, 4, || ());
                    layer(|| "inner".into(), || elementwise(|| "e".into(), 5, 6, || 7))
                },
            )
        };
        assert_eq!(run(), 7);
        assert!(!take().iter().any(|r| r.label.starts_with("outer")));
        enable(true);
        assert_eq!(run(), 7);
        enable(false);
        // Other tests may record while it is on: keep this test's records.
        let r: Vec<Record> = take()
            .into_iter()
            .filter(|r| r.label.starts_with("outer / "))
            .collect();
        assert_eq!(r.len(), 2);
        assert_eq!(r[0].label, "outer / p");
        assert_eq!(
            (r[0].kind, r[0].shape.as_str(), r[0].work),
            (Kind::Product, "[2,3]·[3,4]", 48.0)
        );
        assert_eq!(r[1].label, "outer / inner / e");
        assert_eq!((r[1].kind, r[1].work), (Kind::Elementwise, 30.0));
    }
}
