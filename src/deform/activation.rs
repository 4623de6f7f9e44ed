//! Element-wise activations of the deformation fields, each with its
//! derivative (the vjp multiplies the incoming gradient by it).
//!
//! Names follow ncps (docs/UPSTREAM.md §7.1): `relu`, `gelu` (exact erf form, not the
//! tanh approximation), `silu`, `tanh`, `lecun_tanh` (1.7159·tanh(0.666·x),
//! with 0.666 as upstream writes it, not 2/3). `sigmoid` is used by the CfC
//! gate and is not selectable as a backbone activation.
//!
//! `exp`, `erf`, `tanh` and `sigmoid` come from [`fastmath`] (its own
//! vectorisable functions in f32, libm in f64), in the forward and the
//! derivative alike. The slice loops are compiled for AVX-512, AVX2 and the
//! baseline and picked at run time (same bits on every path).

use crate::error::{Error, Result};
use crate::kernels::fastmath::{self, multiversion};
use crate::kernels::{par_blocks_written, vec_written_by};
use crate::math::Real;
use rayon::prelude::*;
use std::fmt;
use std::mem::MaybeUninit;

/// An element-wise activation function.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    /// `max(x, 0)`.
    Relu,
    /// `0.5·x·(1 + erf(x/√2))`.
    Gelu,
    /// `x·σ(x)`.
    Silu,
    /// `tanh x`.
    Tanh,
    /// `1.7159·tanh(0.666·x)`.
    LecunTanh,
    /// `1/(1 + e^{−x})`.
    Sigmoid,
}

const LECUN_A: f64 = 1.7159;
const LECUN_B: f64 = 0.666;

impl Activation {
    /// Parse a backbone activation name: `relu|gelu|silu|tanh|lecun_tanh`.
    pub fn parse(name: &str) -> Result<Self> {
        Ok(match name {
            "relu" => Activation::Relu,
            "gelu" => Activation::Gelu,
            "silu" => Activation::Silu,
            "tanh" => Activation::Tanh,
            "lecun_tanh" => Activation::LecunTanh,
            other => {
                return Err(Error::invalid(
                    "activation",
                    format!("{other:?} (expected relu, gelu, silu, tanh or lecun_tanh)"),
                ))
            }
        })
    }

    /// The name [`parse`](Self::parse) accepts (`sigmoid` for the gate).
    pub fn name(self) -> &'static str {
        match self {
            Activation::Relu => "relu",
            Activation::Gelu => "gelu",
            Activation::Silu => "silu",
            Activation::Tanh => "tanh",
            Activation::LecunTanh => "lecun_tanh",
            Activation::Sigmoid => "sigmoid",
        }
    }

    /// f(x).
    #[inline(always)]
    pub fn apply<T: Real>(self, x: T) -> T {
        let half = T::from_f64(0.5);
        match self {
            Activation::Relu => {
                if x > T::ZERO {
                    x
                } else {
                    T::ZERO
                }
            }
            Activation::Gelu => {
                half * x
                    * (T::ONE + fastmath::erf(x * T::from_f64(std::f64::consts::FRAC_1_SQRT_2)))
            }
            Activation::Silu => x * fastmath::sigmoid(x),
            Activation::Tanh => fastmath::tanh(x),
            Activation::LecunTanh => {
                T::from_f64(LECUN_A) * fastmath::tanh(T::from_f64(LECUN_B) * x)
            }
            Activation::Sigmoid => fastmath::sigmoid(x),
        }
    }

    /// f'(x). ReLU uses 0 at x = 0 (as PyTorch).
    #[inline(always)]
    pub fn derivative<T: Real>(self, x: T) -> T {
        let half = T::from_f64(0.5);
        match self {
            Activation::Relu => {
                if x > T::ZERO {
                    T::ONE
                } else {
                    T::ZERO
                }
            }
            Activation::Gelu => {
                // Φ(x) + x·φ(x), φ(x) = e^{−x²/2}/√(2π).
                let cdf = half
                    * (T::ONE + fastmath::erf(x * T::from_f64(std::f64::consts::FRAC_1_SQRT_2)));
                let pdf = fastmath::exp(-(half * x * x)) * T::from_f64(0.398_942_280_401_432_7);
                cdf + x * pdf
            }
            Activation::Silu => {
                let s = fastmath::sigmoid(x);
                s * (T::ONE + x * (T::ONE - s))
            }
            Activation::Tanh => {
                let y = fastmath::tanh(x);
                T::ONE - y * y
            }
            Activation::LecunTanh => {
                let y = fastmath::tanh(T::from_f64(LECUN_B) * x);
                T::from_f64(LECUN_A * LECUN_B) * (T::ONE - y * y)
            }
            Activation::Sigmoid => {
                let s = fastmath::sigmoid(x);
                s * (T::ONE - s)
            }
        }
    }

    /// `f` applied to every element of `pre` (parallel, element-wise).
    pub fn forward<T: Real>(self, pre: &[T]) -> Vec<T> {
        // Every value is written once (the output is never zeroed first).
        vec_written_by(pre.len(), |out| {
            par_blocks_written(out, 4096, &mut [(); 0], 0, |i, o, _| {
                apply_uninit(self, &pre[i * 4096..i * 4096 + o.len()], o);
                // SAFETY: apply_uninit wrote every value of `o`.
                unsafe { &mut *(o as *mut [MaybeUninit<T>] as *mut [T]) }
            })
        })
    }

    /// `row = f(row + bias)` element-wise on each row of a row-major block
    /// (sequential: meant for a matrix product's epilogue, which already
    /// runs in parallel blocks): a linear
    /// layer's bias and activation in one pass. Each value is written
    /// whatever its sign (an in-place ReLU alone compiles to masked stores,
    /// which are slow on some CPUs).
    pub fn add_bias_apply_block<T: Real>(self, blk: &mut [T], bias: &[T]) {
        if bias.is_empty() {
            return;
        }
        for row in blk.chunks_exact_mut(bias.len()) {
            add_bias_apply(self, row, bias);
        }
    }

    /// `out = f(pre)` on a block of values, writing every value of `out`
    /// (which may start uninitialised; sequential, as
    /// [`add_bias_apply_block`](Self::add_bias_apply_block)).
    pub fn apply_block_uninit<T: Real>(self, pre: &[T], out: &mut [MaybeUninit<T>]) {
        assert_eq!(pre.len(), out.len(), "activation: sizes differ");
        apply_uninit(self, pre, out);
    }

    /// [`backward_in_place`](Self::backward_in_place) on one block of
    /// values, sequential (for a chunk of an output gradient produced inside
    /// a linear layer's backward).
    pub fn backward_block<T: Real>(self, pre: &[T], g: &mut [T]) {
        assert_eq!(pre.len(), g.len(), "activation backward: sizes differ");
        scale_by_derivative(self, pre, g);
    }

    /// vjp: `g ⊙ f'(pre)`, in place on `g`.
    pub fn backward_in_place<T: Real>(self, pre: &[T], g: &mut [T]) {
        if g.len() <= 4096 {
            scale_by_derivative(self, pre, g);
            return;
        }
        g.par_chunks_mut(4096)
            .zip(pre.par_chunks(4096))
            .for_each(|(g, p)| scale_by_derivative(self, p, g));
    }
}

/// vjp of ReLU from its output instead of its input: `g ⊙ f'(pre)` with
/// `f'(pre) = [out > 0]` (the same values, since `out > 0` exactly when
/// `pre > 0`), in place on `g` (the same shape as `out`). Lets a ReLU layer
/// keep only its output.
pub fn relu_backward_from_output<T: Real>(out: &[T], g: &mut [T]) {
    assert_eq!(out.len(), g.len(), "relu backward: sizes differ");
    g.par_chunks_mut(4096)
        .zip(out.par_chunks(4096))
        .for_each(|(g, o)| relu_mask_row(o, g));
}

/// [`relu_backward_from_output`] on one block of rows, sequential (for a
/// chunk of an output gradient produced inside a linear layer's backward).
pub fn relu_backward_from_output_block<T: Real>(out: &[T], g: &mut [T]) {
    assert_eq!(out.len(), g.len(), "relu backward: sizes differ");
    relu_mask_row(out, g)
}

multiversion!(fn relu_mask_row<T: Real>(out: &[T], g: &mut [T]) => relu_mask_row_body);

#[inline(always)]
fn relu_mask_row_body<T: Real>(out: &[T], g: &mut [T]) {
    for (g, &o) in g.iter_mut().zip(out) {
        *g *= if o > T::ZERO { T::ONE } else { T::ZERO };
    }
}

/// One loop per activation (the `match` outside, so each loop vectorises).
macro_rules! per_activation {
    ($act:expr, |$a:ident| $body:expr) => {
        match $act {
            Activation::Relu => {
                let $a = Activation::Relu;
                $body
            }
            Activation::Gelu => {
                let $a = Activation::Gelu;
                $body
            }
            Activation::Silu => {
                let $a = Activation::Silu;
                $body
            }
            Activation::Tanh => {
                let $a = Activation::Tanh;
                $body
            }
            Activation::LecunTanh => {
                let $a = Activation::LecunTanh;
                $body
            }
            Activation::Sigmoid => {
                let $a = Activation::Sigmoid;
                $body
            }
        }
    };
}

multiversion!(fn add_bias_apply<T: Real>(act: Activation, row: &mut [T], bias: &[T]) => add_bias_apply_body);
multiversion!(fn apply_uninit<T: Real>(act: Activation, pre: &[T], out: &mut [MaybeUninit<T>]) => apply_uninit_body);
multiversion!(fn scale_by_derivative<T: Real>(act: Activation, pre: &[T], g: &mut [T]) => scale_by_derivative_body);

#[inline(always)]
fn add_bias_apply_body<T: Real>(act: Activation, row: &mut [T], bias: &[T]) {
    per_activation!(act, |a| {
        for (v, &b) in row.iter_mut().zip(bias) {
            *v = a.apply(*v + b);
        }
    })
}

#[inline(always)]
fn apply_uninit_body<T: Real>(act: Activation, pre: &[T], out: &mut [MaybeUninit<T>]) {
    per_activation!(act, |a| {
        for (o, &p) in out.iter_mut().zip(pre) {
            o.write(a.apply(p));
        }
    })
}

#[inline(always)]
fn scale_by_derivative_body<T: Real>(act: Activation, pre: &[T], g: &mut [T]) {
    per_activation!(act, |a| {
        for (g, &p) in g.iter_mut().zip(pre) {
            *g *= a.derivative(p);
        }
    })
}

impl fmt::Display for Activation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ALL: [Activation; 6] = [
        Activation::Relu,
        Activation::Gelu,
        Activation::Silu,
        Activation::Tanh,
        Activation::LecunTanh,
        Activation::Sigmoid,
    ];

    #[test]
    fn derivatives_match_central_differences() {
        for act in ALL {
            for i in 0..41 {
                // Avoid x = 0 (the ReLU kink).
                let x = -3.05 + 0.15 * i as f64;
                let h = 1e-6;
                let num = (act.apply(x + h) - act.apply(x - h)) / (2.0 * h);
                let a = act.derivative(x);
                let rel = (a - num).abs() / a.abs().max(num.abs()).max(1e-6);
                assert!(rel < 1e-6, "{act} at {x}: {a} vs {num}");
            }
        }
    }

    #[test]
    fn known_values() {
        // gelu(1) = 0.5·(1 + erf(1/√2)) = Φ(1) = 0.8413447460685429
        assert!((Activation::Gelu.apply(1.0f64) - 0.841_344_746_068_542_9).abs() < 1e-15);
        assert_eq!(
            Activation::LecunTanh.apply(1.0f64),
            1.7159 * libm::tanh(0.666)
        );
        // f32 uses the fastmath functions, the same bits in slices and scalars.
        assert_eq!(
            Activation::LecunTanh.apply(1.0f32),
            1.7159f32 * fastmath::tanh_f32(0.666f32)
        );
        assert_eq!(Activation::Relu.apply(-2.0f64), 0.0);
        assert_eq!(
            Activation::parse("lecun_tanh").unwrap(),
            Activation::LecunTanh
        );
        assert!(Activation::parse("sigmoid").is_err());
        assert!(Activation::parse("swish")
            .unwrap_err()
            .to_string()
            .contains("swish"));
    }
}
