//! # liquid-splat
//!
//! A deterministic, multithreaded CPU reference implementation of Deformable
//! 3D Gaussian Splatting (D-3DGS) with a liquid deformation field: a stack of
//! closed-form continuous-time (CfC) cells in place of the D-3DGS MLP. The MLP
//! field is implemented as the baseline.
//!
//! ## The pipeline, in module order
//!
//! ```text
//! dataset ──► camera + time ──► deform (field) ──► deformed Gaussians ──► render
//!   (frames)    (camera)         (mlp | cfc)         (gaussians)          (rasterizer)
//!                                                                            │
//!        densify ◄── optim (Adam) ◄── backward (each stage's vjp) ◄── loss ◄─┘
//! ```
//!
//! - [`math`]: the `Real` scalar trait (f32 / f64), the pinned math library,
//!   small vectors, matrices and quaternions, the seeded generator and the
//!   finite-difference gradient checker.
//! - [`kernels`]: the deterministic matrix product and the f32 fast-math
//!   functions, with run-time instruction-set paths that give the same bits.
//! - [`camera`]: pinhole cameras and the matrices the rasterizer consumes.
//! - [`io`]: atomic writes, named-tensor (safetensors) files, PNG and EXR,
//!   PyTorch `.pth` reading.
//! - [`dataset`]: D-NeRF and nerfies loaders, built-in scenes.
//! - [`deform`]: the MLP and CfC deformation fields, forward and backward.
//! - [`gaussians`]: raw per-Gaussian parameters, the table of parameter
//!   groups, activations, initialisation, Inria PLY.
//! - [`render`]: the rasterizer, forward and backward (`exact` or `inria`).
//! - [`gsplat`]: gsplat's projection, tile intersection, rasterize-to-pixels
//!   and composite `rasterization`, at gsplat 1.5.3 and 1.6 (`exact` or
//!   `gsplat` backward); docs/GSPLAT.md.
//! - [`loss`]: L1, SSIM and their backward; PSNR/SSIM metrics.
//! - [`lpips`]: LPIPS v0.1 (VGG16) as the `lpips` package computes it, with
//!   weights read from PyTorch `.pth` files ([`io::pth`]).
//! - [`optim`], [`densify`]: Adam and schedules; clone, split, prune, reset.
//! - [`train`]: [`train::Model`] (forward, backward, render),
//!   [`train::Trainer::step`], the training-state codec, checkpoints, whole
//!   runs.
//! - [`oracle`]: case files for every stage and the comparison report.
//! - [`cli`]: the command-line tool as a library function (the binary and
//!   the Python package run it).
//! - [`experiment`]: a training run's persisted description
//!   ([`experiment::RunSpec`], `run.json`) and the experiment driver (plan,
//!   resume rule, smoothness sweep, run records).
//! - [`report`]: per-run records and the experiment report (Markdown, CSV,
//!   PNG plots, temporal smoothness of a learned deformation).
//! - [`bench`](mod@bench): throughput measurements and their harness (`bench`
//!   subcommand, `cargo bench`).
//! - [`memory`], [`threads`]: process-wide allocator tuning and worker pools
//!   (optionally pinned), for speed only.
//!
//! ## Determinism
//! The same inputs give the same bits whatever the thread count, run or CPU:
//! work is split into fixed pieces, every floating-point reduction has a fixed
//! order, transcendental functions come from one pinned pure-Rust library
//! (`libm`; in f32 the fields' activations use [`kernels::fastmath`], plain
//! arithmetic with the same bits on every instruction set), and all
//! randomness comes from explicit seeds.
//!
//! ## Naming of backward passes and saved state
//! - A primitive (a free function) `f` has its backward `f_vjp`, defined
//!   beside it (same module, or `f_vjp.rs` next to `f.rs`). `f_vjp` takes
//!   what `f` took, or the state `f` saved, plus the cotangent of `f`'s
//!   output, and returns the cotangents of `f`'s inputs.
//! - A type with parameters (a layer, a field, a model) has the methods
//!   `forward` and `backward`; `backward` takes the state `forward` saved and
//!   the output cotangent and returns the parameters' gradients and the
//!   inputs' cotangents.
//! - State a forward saves for its backward is a type named `<Name>Saved`;
//!   gradients of a type's parameters are a type named `<Name>Gradients`.

#![warn(missing_docs)]
#![warn(unsafe_op_in_unsafe_fn)]
#![warn(clippy::undocumented_unsafe_blocks)]

/// `println!` for the tool's results on standard output: when the output
/// cannot be written (a pipe whose reader has gone), the command ends by an
/// unwind carrying [`cli::StdoutError`] instead of a panic (see
/// [`cli::print_out`]).
macro_rules! outln {
    () => { $crate::cli::print_out(format_args!("\n")) };
    ($($arg:tt)*) => { $crate::cli::print_out(format_args!("{}\n", format_args!($($arg)*))) };
}

pub mod bench;
pub mod camera;
pub mod cli;
pub mod dataset;
pub mod deform;
pub mod densify;
pub mod error;
pub mod experiment;
pub mod fuzz;
pub mod gaussians;
pub mod gsplat;
pub mod io;
pub mod kernels;
pub mod loss;
pub mod lpips;
pub mod math;
pub mod memory;
pub mod optim;
pub mod oracle;
pub mod render;
pub mod report;
pub mod threads;
pub mod train;

pub use error::{Error, Result};
