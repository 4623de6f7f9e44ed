//! Positional encoding γ_L of D-3DGS (docs/UPSTREAM.md §6.1), with its vjp.
//!
//! `γ_L(p) = [p, sin(2⁰p), cos(2⁰p), sin(2¹p), cos(2¹p), …, sin(2^{L−1}p), cos(2^{L−1}p)]`,
//! where each sin/cos block covers all `d` input dimensions at once, so for
//! xyz the layout is `[x, y, z, sin x, sin y, sin z, cos x, cos y, cos z, sin 2x, …]`.
//! The raw input comes first, there is no π, and the frequencies are exact
//! powers of two (so the argument `2^k · p` is exact). Output width
//! `d + 2·d·L`.

use crate::kernels::{fastmath, par_blocks_written, vec_written_by};
use crate::math::Real;
use rayon::prelude::*;
use std::mem::MaybeUninit;

/// Output width of γ_L for `d` input dimensions.
pub fn encoded_dim(d: usize, levels: usize) -> usize {
    d + 2 * d * levels
}

/// The frequency `2^k`, exact.
fn freq<T: Real>(k: usize) -> T {
    T::from_f64((1u64 << k) as f64)
}

/// `sin(2^k·p)` and `cos(2^k·p)` for each row `p` of `x` `[rows, d]`, laid
/// out `[rows, L, d]`, in one vector loop (libm's bits, see
/// [`fastmath::sin_cos_slices`]).
fn sin_cos_of_arguments<T: Real>(x: &[T], d: usize, levels: usize) -> (Vec<T>, Vec<T>) {
    let mut args = Vec::with_capacity(x.len() * levels);
    for p in x.chunks_exact(d) {
        for k in 0..levels {
            let f = freq::<T>(k);
            args.extend(p.iter().map(|&v| v * f));
        }
    }
    let (mut sin, mut cos) = (vec![T::ZERO; args.len()], vec![T::ZERO; args.len()]);
    fastmath::sin_cos_slices(&args, &mut sin, &mut cos);
    (sin, cos)
}

/// Encode `x` `[n, d]` row-major into `[n, d + 2dL]`.
pub fn encode<T: Real>(x: &[T], d: usize, levels: usize) -> Vec<T> {
    encode_then(x, d, levels, &[], 0)
}

/// `[encode(x) | tail]` row by row, `[n, d + 2dL + tail_w]` (`tail`
/// `[n, tail_w]`): the encoding written straight into the wider rows, with
/// no separate copy.
pub fn encode_then<T: Real>(x: &[T], d: usize, levels: usize, tail: &[T], tail_w: usize) -> Vec<T> {
    let e = encoded_dim(d, levels);
    let w = e + tail_w;
    let n = x.len().checked_div(d).unwrap_or(0);
    if n == 0 || w == 0 {
        return Vec::new();
    }
    assert_eq!(
        tail.len(),
        n * tail_w,
        "encode_then: tail has the wrong size"
    );
    // Every value of every row is written once (never zeroed first). Per
    // block of rows, the arguments 2^k·p first, then all their sines and
    // cosines in one vector loop (libm's bits, see `sin_cos_slices`).
    vec_written_by(n * w, |out| {
        par_blocks_written(out, w * 256, &mut [(); 0], 0, |blk, o, _| {
            let xi = &x[blk * d * 256..(blk * d * 256 + d * 256).min(x.len())];
            let m = d * levels;
            let (sin, cos) = sin_cos_of_arguments(xi, d, levels);
            for (i, (row, p)) in o.chunks_exact_mut(w).zip(xi.chunks_exact(d)).enumerate() {
                let (row, row_tail) = row.split_at_mut(e);
                let r = blk * 256 + i;
                for (dst, &v) in row_tail.iter_mut().zip(&tail[r * tail_w..(r + 1) * tail_w]) {
                    dst.write(v);
                }
                let (row_p, row_sc) = row.split_at_mut(d);
                for (r, &v) in row_p.iter_mut().zip(p) {
                    r.write(v);
                }
                // Level k: d sines, then d cosines.
                let (sn, cs) = (&sin[i * m..(i + 1) * m], &cos[i * m..(i + 1) * m]);
                for ((dst, sk), ck) in row_sc
                    .chunks_exact_mut(2 * d)
                    .zip(sn.chunks_exact(d))
                    .zip(cs.chunks_exact(d))
                {
                    let (ds, dc) = dst.split_at_mut(d);
                    for (r, &v) in ds.iter_mut().zip(sk).chain(dc.iter_mut().zip(ck)) {
                        r.write(v);
                    }
                }
            }
            // SAFETY: the loop above wrote the d inputs, the 2·d·levels
            // sines and cosines and the tail of each row of the block, i.e.
            // all its values.
            unsafe { &mut *(o as *mut [MaybeUninit<T>] as *mut [T]) }
        })
    })
}

/// The derivative of [`encode`] for scalar inputs (`d = 1`): per row of `x`
/// `[n]`, the derivative of each output with respect to `x`, `[n, 1 + 2L]`:
/// `1`, then for k = 0, 1, …: `2^k cos(2^k x)`, `−2^k sin(2^k x)` (the
/// factors of [`encode_vjp`]).
pub fn encode_derivative<T: Real>(x: &[T], levels: usize) -> Vec<T> {
    let (sin, cos) = sin_cos_of_arguments(x, 1, levels);
    let mut out = Vec::with_capacity(x.len() * encoded_dim(1, levels));
    for i in 0..x.len() {
        out.push(T::ONE);
        for k in 0..levels {
            let f = freq::<T>(k);
            out.push(f * cos[i * levels + k]);
            out.push(-(f * sin[i * levels + k]));
        }
    }
    out
}

/// Vector-Jacobian product of [`encode`]: the gradient with respect to `x`
/// `[n, d]` given the gradient `g` `[n, d + 2dL]` of the encoding.
///
/// Per input entry the terms are added in output order: the raw term, then
/// for k = 0, 1, …: `g_sin · 2^k cos(2^k p)`, then `−g_cos · 2^k sin(2^k p)`.
pub fn encode_vjp<T: Real>(x: &[T], g: &[T], d: usize, levels: usize) -> Vec<T> {
    let w = encoded_dim(d, levels);
    let mut out = vec![T::ZERO; x.len()];
    out.par_chunks_mut(d.max(1) * 256)
        .zip(x.par_chunks(d.max(1) * 256))
        .zip(g.par_chunks(w.max(1) * 256))
        .for_each(|((o, xi), gi)| {
            let m = d * levels;
            let (sin, cos) = sin_cos_of_arguments(xi, d, levels);
            for (i, (orow, grow)) in o.chunks_exact_mut(d).zip(gi.chunks_exact(w)).enumerate() {
                for c in 0..d {
                    let mut s = grow[c];
                    for k in 0..levels {
                        let f = freq::<T>(k);
                        let base = d + 2 * d * k;
                        s += grow[base + c] * (f * cos[i * m + k * d + c]);
                        s -= grow[base + d + c] * (f * sin[i * m + k * d + c]);
                    }
                    orow[c] = s;
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::{compare, cotangent, numeric_gradient};

    #[test]
    fn layout_matches_upstream() {
        let x = [0.5f64, -1.25, 2.0];
        let e = encode(&x, 3, 2);
        assert_eq!(e.len(), 3 + 12);
        assert_eq!(&e[..3], &x);
        assert_eq!(e[3], libm::sin(0.5));
        assert_eq!(e[5], libm::sin(2.0));
        assert_eq!(e[6], libm::cos(0.5));
        assert_eq!(e[9], libm::sin(1.0));
        assert_eq!(e[14], libm::cos(4.0));
        assert_eq!(encoded_dim(3, 10), 63);
        assert_eq!(encoded_dim(1, 6), 13);
        assert_eq!(encoded_dim(1, 10), 21);
    }

    #[test]
    fn vjp_matches_central_differences() {
        let mut x = vec![0.3, -0.7, 1.1, 0.05, 0.9, -0.2];
        let (d, l) = (3, 4);
        let v = cotangent(9, 2 * encoded_dim(d, l));
        let a = encode_vjp(&x, &v, d, l);
        let num = numeric_gradient(&mut x, 1e-6, |x| {
            encode(x, d, l).iter().zip(&v).map(|(a, b)| a * b).sum()
        });
        let r = compare("encoding", &a, &num, 1e-6);
        assert!(r.passes(1e-6), "{r}");
    }
}
