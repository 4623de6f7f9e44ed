//! Arithmetic that runs either on one number or on several lanes at once,
//! with the same bits in every lane.
//!
//! [`Arith`] is what the per-Gaussian backward chain rules
//! ([`super::sh::sh_to_color_vjp`], [`super::covariance::cov3d_vjp`],
//! [`super::quat::quat_to_rotmat_vjp`] and the projection's backward) are
//! written in: every [`Real`] is an `Arith` (one lane), and so is a
//! [`Pack`] of `L` of them. A `Pack` operation applies the scalar operation
//! lane by lane (IEEE add, subtract, multiply, divide and square root, each
//! correctly rounded; Rust never fuses a multiply and an add), so lane `l`
//! of a computation on packs has exactly the bits of the same computation on
//! the scalars of lane `l`, whatever instructions the compiler vectorises
//! it into.

use super::Real;
use std::ops::{Add, AddAssign, Div, Mul, Neg, Sub};

/// A number or a pack of numbers: IEEE arithmetic, constants, a square root,
/// a clamp and a lane-wise choice.
pub trait Arith:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
{
    /// The scalar type of a lane.
    type Elem: Real;
    /// One condition per lane: `bool` for a scalar, `[bool; L]` for a pack,
    /// the register types' own masks for the rasterizer's vector lanes.
    type Mask: Copy;
    /// `0` in every lane.
    const ZERO: Self;
    /// `1` in every lane.
    const ONE: Self;
    /// `v` in every lane.
    fn splat(v: Self::Elem) -> Self;
    /// `Elem::from_f64(x)` in every lane.
    #[inline(always)]
    fn from_f64(x: f64) -> Self {
        Self::splat(<Self::Elem as Real>::from_f64(x))
    }
    /// The square root of every lane.
    fn sqrt(self) -> Self;
    /// [`Real::clamp`] of every lane.
    fn clamp(self, lo: Self, hi: Self) -> Self;
    /// `self == o` per lane.
    fn eq_mask(self, o: Self) -> Self::Mask;
    /// `m ? a : b` per lane.
    fn select(m: Self::Mask, a: Self, b: Self) -> Self;
}

impl<T: Real> Arith for T {
    type Elem = T;
    type Mask = bool;
    const ZERO: Self = <T as Real>::ZERO;
    const ONE: Self = <T as Real>::ONE;
    #[inline(always)]
    fn splat(v: T) -> T {
        v
    }
    #[inline(always)]
    fn sqrt(self) -> T {
        Real::sqrt(self)
    }
    #[inline(always)]
    fn clamp(self, lo: T, hi: T) -> T {
        Real::clamp(self, lo, hi)
    }
    #[inline(always)]
    fn eq_mask(self, o: T) -> bool {
        self == o
    }
    #[inline(always)]
    fn select(m: bool, a: T, b: T) -> T {
        if m {
            a
        } else {
            b
        }
    }
}

/// `L` numbers computed lane by lane (laid out as `[T; L]`).
///
/// The operations are written as loops over the lanes, not with
/// `std::array::from_fn`: in the large lane-parallel functions the compiler
/// may leave `from_fn`'s closures out of line, and an out-of-line function
/// is compiled without the caller's instruction set (so for SSE2 inside an
/// AVX-512 kernel).
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(transparent)]
pub struct Pack<T, const L: usize>(pub [T; L]);

impl<T: Real, const L: usize> Pack<T, L> {
    /// `v` in every lane.
    #[inline(always)]
    pub fn splat(v: T) -> Self {
        Pack([v; L])
    }

    /// Lane `l` is `f(l)`.
    #[inline(always)]
    pub fn from_fn(f: impl FnMut(usize) -> T) -> Self {
        Pack(std::array::from_fn(f))
    }
}

macro_rules! pack_op {
    ($tr:ident, $f:ident, $op:tt) => {
        impl<T: Real, const L: usize> $tr for Pack<T, L> {
            type Output = Self;
            #[inline(always)]
            fn $f(self, o: Self) -> Self {
                let mut r = self;
                for l in 0..L {
                    r.0[l] = self.0[l] $op o.0[l];
                }
                r
            }
        }
    };
}
pack_op!(Add, add, +);
pack_op!(Sub, sub, -);
pack_op!(Mul, mul, *);
pack_op!(Div, div, /);

impl<T: Real, const L: usize> Neg for Pack<T, L> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        let mut r = self;
        for l in 0..L {
            r.0[l] = -self.0[l];
        }
        r
    }
}

impl<T: Real, const L: usize> AddAssign for Pack<T, L> {
    #[inline(always)]
    fn add_assign(&mut self, o: Self) {
        for l in 0..L {
            self.0[l] += o.0[l];
        }
    }
}

impl<T: Real, const L: usize> Arith for Pack<T, L> {
    type Elem = T;
    type Mask = [bool; L];
    const ZERO: Self = Pack([<T as Real>::ZERO; L]);
    const ONE: Self = Pack([<T as Real>::ONE; L]);
    #[inline(always)]
    fn splat(v: T) -> Self {
        Pack([v; L])
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        let mut r = self;
        for l in 0..L {
            r.0[l] = Real::sqrt(self.0[l]);
        }
        r
    }
    #[inline(always)]
    fn clamp(self, lo: Self, hi: Self) -> Self {
        let mut r = self;
        for l in 0..L {
            r.0[l] = Real::clamp(self.0[l], lo.0[l], hi.0[l]);
        }
        r
    }
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // a loop over lanes (see the type's docs)
    fn eq_mask(self, o: Self) -> [bool; L] {
        let mut m = [false; L];
        for l in 0..L {
            m[l] = self.0[l] == o.0[l];
        }
        m
    }
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // a loop over lanes (see the type's docs)
    fn select(m: [bool; L], a: Self, b: Self) -> Self {
        let mut r = b;
        for l in 0..L {
            if m[l] {
                r.0[l] = a.0[l];
            }
        }
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::covariance::{cov3d_vjp, cov3d_vjp_scaled};
    use crate::math::sh::{color_vjp, sh_to_color, sh_to_color_vjp};
    use crate::math::Rng;

    const L: usize = 5;

    /// Lane `l` of the SH colour and covariance vjps on packs has the bits
    /// of the scalar functions on lane `l`'s inputs: random Gaussians, every
    /// degree, channels clamped or not (about one in three), non-unit
    /// quaternions, scales of both signs.
    #[allow(clippy::needless_range_loop)] // lanes and slots as indices
    fn lanes_match_scalar<T: Real>() {
        let mut rng = Rng::new(19);
        let mut r = |lo: f64, hi: f64| T::from_f64(rng.uniform_range(lo, hi));
        for round in 0..40 {
            let degree = round % 4;
            let coeffs: Vec<[T; 48]> = (0..L)
                .map(|_| std::array::from_fn(|_| r(-1.0, 0.7)))
                .collect();
            let means: [[T; 3]; L] = std::array::from_fn(|_| std::array::from_fn(|_| r(-2.0, 2.0)));
            let campos: [T; 3] = std::array::from_fn(|_| r(-3.0, 3.0));
            let gcol: [[T; 3]; L] = std::array::from_fn(|_| std::array::from_fn(|_| r(-1.0, 1.0)));
            let scale: [[T; 3]; L] = std::array::from_fn(|_| std::array::from_fn(|_| r(-0.5, 0.5)));
            let quat: [[T; 4]; L] = std::array::from_fn(|_| std::array::from_fn(|_| r(-1.5, 1.5)));
            let gcov: [[T; 6]; L] = std::array::from_fn(|_| std::array::from_fn(|_| r(-1.0, 1.0)));
            let modifier = r(0.5, 1.5);
            let fwd: Vec<_> = (0..L)
                .map(|l| sh_to_color(degree, &coeffs[l], means[l], campos))
                .collect();
            let pk = |f: &dyn Fn(usize) -> T| Pack::<T, L>::from_fn(f);
            let mut put = [[T::ZERO; L]; 48];
            let gmean = color_vjp(
                degree,
                |q| pk(&|l| coeffs[l][q]),
                std::array::from_fn(|a| pk(&|l| means[l][a])),
                campos.map(Pack::splat),
                std::array::from_fn(|ch| std::array::from_fn(|l| fwd[l].clamped[ch])),
                std::array::from_fn(|ch| pk(&|l| gcol[l][ch])),
                |q, v| put[q] = v.0,
            );
            let cov_in = (
                std::array::from_fn(|a| pk(&|l| scale[l][a])),
                Pack::splat(modifier),
                std::array::from_fn(|q| pk(&|l| quat[l][q])),
                std::array::from_fn(|q| pk(&|l| gcov[l][q])),
            );
            let exact = cov3d_vjp(cov_in.0, cov_in.1, cov_in.2, cov_in.3);
            let scaled = cov3d_vjp_scaled(cov_in.0, cov_in.1, cov_in.2, cov_in.3);
            let bits = |v: T| v.bits();
            for l in 0..L {
                let mut want = [T::ZERO; 48];
                let gm = sh_to_color_vjp(
                    degree, &coeffs[l], means[l], campos, &fwd[l], gcol[l], &mut want,
                );
                let n = 3 * (degree + 1) * (degree + 1);
                for q in 0..n {
                    assert_eq!(bits(put[q][l]), bits(want[q]), "degree {degree} slot {q}");
                }
                for a in 0..3 {
                    assert_eq!(bits(gmean[a].0[l]), bits(gm[a]), "degree {degree} mean {a}");
                }
                for (vjp, got) in [
                    (cov3d_vjp::<T> as fn(_, _, _, _) -> _, exact),
                    (cov3d_vjp_scaled::<T>, scaled),
                ] {
                    let (ws, wq) = vjp(scale[l], modifier, quat[l], gcov[l]);
                    for a in 0..3 {
                        assert_eq!(bits(got.0[a].0[l]), bits(ws[a]));
                    }
                    for q in 0..4 {
                        assert_eq!(bits(got.1[q].0[l]), bits(wq[q]));
                    }
                }
            }
        }
    }

    #[test]
    fn lanes_match_scalar_f32() {
        lanes_match_scalar::<f32>();
    }

    #[test]
    fn lanes_match_scalar_f64() {
        lanes_match_scalar::<f64>();
    }
}
