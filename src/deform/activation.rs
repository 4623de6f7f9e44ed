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

    /// `(f(x), f'(x))`, each with the bits of [`apply`](Self::apply) and
    /// [`derivative`](Self::derivative), their common transcendental
    /// function evaluated once.
    #[inline(always)]
    pub fn apply_and_derivative<T: Real>(self, x: T) -> (T, T) {
        let half = T::from_f64(0.5);
        match self {
            Activation::Gelu => {
                let e = fastmath::erf(x * T::from_f64(std::f64::consts::FRAC_1_SQRT_2));
                let cdf = half * (T::ONE + e);
                let pdf = fastmath::exp(-(half * x * x)) * T::from_f64(0.398_942_280_401_432_7);
                (half * x * (T::ONE + e), cdf + x * pdf)
            }
            Activation::Silu => {
                let s = fastmath::sigmoid(x);
                (x * s, s * (T::ONE + x * (T::ONE - s)))
            }
            Activation::Tanh => {
                let y = fastmath::tanh(x);
                (y, T::ONE - y * y)
            }
            Activation::LecunTanh => {
                let y = fastmath::tanh(T::from_f64(LECUN_B) * x);
                (
                    T::from_f64(LECUN_A) * y,
                    T::from_f64(LECUN_A * LECUN_B) * (T::ONE - y * y),
                )
            }
            Activation::Sigmoid => {
                let s = fastmath::sigmoid(x);
                (s, s * (T::ONE - s))
            }
            Activation::Relu => (self.apply(x), self.derivative(x)),
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

    /// `pre += bias` row by row (`bias.len()` wide) and `out = f(pre)`, in
    /// one sequential pass writing every value of `out` (which may start
    /// uninitialised): the bits of adding the bias, then
    /// [`apply_block_uninit`](Self::apply_block_uninit).
    pub fn add_bias_apply_block_uninit<T: Real>(
        self,
        pre: &mut [T],
        bias: &[T],
        out: &mut [MaybeUninit<T>],
    ) {
        assert_eq!(pre.len(), out.len(), "activation: sizes differ");
        assert!(
            !bias.is_empty() && pre.len().is_multiple_of(bias.len()),
            "activation: bias width"
        );
        add_bias_apply_uninit(self, pre, bias, out);
    }

    /// `out = f(pre)` on a block of values, writing every value of `out`
    /// (which may start uninitialised; sequential, as
    /// [`add_bias_apply_block`](Self::add_bias_apply_block)).
    pub fn apply_block_uninit<T: Real>(self, pre: &[T], out: &mut [MaybeUninit<T>]) {
        assert_eq!(pre.len(), out.len(), "activation: sizes differ");
        apply_uninit(self, pre, out);
    }

    /// `out = f(pre)` and `deriv = f'(pre)` on a block of values, writing
    /// every value of both (sequential): the bits of
    /// [`apply_block_uninit`](Self::apply_block_uninit) and of the
    /// derivative [`backward_block`](Self::backward_block) multiplies by, in
    /// one pass.
    pub fn apply_and_derivative_block<T: Real>(
        self,
        pre: &[T],
        out: &mut [MaybeUninit<T>],
        deriv: &mut [MaybeUninit<T>],
    ) {
        assert_eq!(pre.len(), out.len(), "activation: sizes differ");
        assert_eq!(pre.len(), deriv.len(), "activation: sizes differ");
        apply_and_derivative_uninit(self, pre, out, deriv);
    }

    /// `g ⊙ deriv` in place, with `deriv` from
    /// [`apply_and_derivative_block`](Self::apply_and_derivative_block):
    /// the bits of [`backward_block`](Self::backward_block).
    pub fn backward_block_from_derivative<T: Real>(deriv: &[T], g: &mut [T]) {
        assert_eq!(deriv.len(), g.len(), "activation backward: sizes differ");
        scale_by(deriv, g);
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
multiversion!(fn add_bias_apply_uninit<T: Real>(act: Activation, pre: &mut [T], bias: &[T], out: &mut [MaybeUninit<T>]) => add_bias_apply_uninit_body);
multiversion!(fn scale_by_derivative<T: Real>(act: Activation, pre: &[T], g: &mut [T]) => scale_by_derivative_body);

multiversion!(fn apply_and_derivative_uninit<T: Real>(act: Activation, pre: &[T], out: &mut [MaybeUninit<T>], deriv: &mut [MaybeUninit<T>]) => apply_and_derivative_uninit_body);
multiversion!(fn scale_by<T: Real>(d: &[T], g: &mut [T]) => scale_by_body);

#[inline(always)]
fn apply_and_derivative_uninit_body<T: Real>(
    act: Activation,
    pre: &[T],
    out: &mut [MaybeUninit<T>],
    deriv: &mut [MaybeUninit<T>],
) {
    per_activation!(act, |a| {
        for ((o, d), &p) in out.iter_mut().zip(deriv.iter_mut()).zip(pre) {
            let (f, df) = a.apply_and_derivative(p);
            o.write(f);
            d.write(df);
        }
    })
}

#[inline(always)]
fn scale_by_body<T: Real>(d: &[T], g: &mut [T]) {
    for (g, &d) in g.iter_mut().zip(d) {
        *g *= d;
    }
}

#[inline(always)]
fn add_bias_apply_body<T: Real>(act: Activation, row: &mut [T], bias: &[T]) {
    per_activation!(act, |a| {
        for (v, &b) in row.iter_mut().zip(bias) {
            *v = a.apply(*v + b);
        }
    })
}

#[inline(always)]
fn add_bias_apply_uninit_body<T: Real>(
    act: Activation,
    pre: &mut [T],
    bias: &[T],
    out: &mut [MaybeUninit<T>],
) {
    let w = bias.len();
    per_activation!(act, |a| {
        for (pr, or) in pre.chunks_exact_mut(w).zip(out.chunks_exact_mut(w)) {
            for ((p, o), &b) in pr.iter_mut().zip(or.iter_mut()).zip(bias) {
                *p += b;
                o.write(a.apply(*p));
            }
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

    /// The fused value and derivative have the bits of the separate ones,
    /// in f32 (the fast-math functions) and f64, across the functions'
    /// ranges.
    #[test]
    fn fused_value_and_derivative_have_the_separate_bits() {
        for act in ALL {
            for i in 0..4001 {
                let x = -20.0 + 0.01 * i as f64;
                let (f, d) = act.apply_and_derivative(x);
                assert_eq!(f.to_bits(), act.apply(x).to_bits(), "{act} f at {x}");
                assert_eq!(d.to_bits(), act.derivative(x).to_bits(), "{act} f' at {x}");
                let x = x as f32;
                let (f, d) = act.apply_and_derivative(x);
                assert_eq!(f.to_bits(), act.apply(x).to_bits(), "{act} f at {x}");
                assert_eq!(d.to_bits(), act.derivative(x).to_bits(), "{act} f' at {x}");
            }
            // And the block passes.
            let pre: Vec<f32> = (0..1000).map(|i| -8.0 + 0.016 * i as f32).collect();
            let mut out = vec![MaybeUninit::uninit(); pre.len()];
            let mut der = vec![MaybeUninit::uninit(); pre.len()];
            act.apply_and_derivative_block(&pre, &mut out, &mut der);
            // SAFETY: the block pass wrote every value of both.
            let (out, der): (Vec<f32>, Vec<f32>) = unsafe {
                (
                    out.iter().map(|v| v.assume_init()).collect(),
                    der.iter().map(|v| v.assume_init()).collect(),
                )
            };
            let mut want = vec![MaybeUninit::uninit(); pre.len()];
            act.apply_block_uninit(&pre, &mut want);
            for (o, w) in out.iter().zip(&want) {
                // SAFETY: apply_block_uninit wrote every value.
                assert_eq!(o.to_bits(), unsafe { w.assume_init() }.to_bits(), "{act}");
            }
            let g: Vec<f32> = (0..1000).map(|i| 1.0 - 0.0021 * i as f32).collect();
            let (mut a, mut b) = (g.clone(), g.clone());
            act.backward_block(&pre, &mut a);
            Activation::backward_block_from_derivative(&der, &mut b);
            assert_eq!(
                a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                b.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "{act}"
            );
        }
    }

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
