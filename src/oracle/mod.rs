//! The oracle: what backend authors run in their CI against this reference.
//!
//! - [`compare`](mod@compare): tensor-by-tensor comparison of an expected case output with
//!   an actual one, with a report richer than a max-abs number (relative L2,
//!   cosine similarity, signed bias, ULP distance, NaN/Inf counts, the worst
//!   element) and PyTorch's `allclose` rule for pass/fail.

pub mod compare;

pub use compare::{
    compare, CompareReport, ElementStats, Status, TensorReport, Tolerance, ToleranceSpec,
    Tolerances, Worst,
};
