//! The fields' element-wise loops over the f32 fast-math functions of
//! [`crate::math::fast`] (re-exported here), compiled for AVX-512, AVX2 and
//! the baseline and picked at run time ([`isa`], [`force_isa`]); every path
//! gives the same bits. In generic code the functions are reached through
//! [`Real`]'s `fast_*` methods: this module's f32 functions in f32, the
//! pinned libm in f64.

pub use crate::math::fast::{
    erf_f32, exp_f32, sigmoid_f32, sin_cos_f32, tanh_f32, ERF_MAX_ULP, EXP_MAX_ULP,
    SIGMOID_MAX_ULP, TANH_MAX_ULP,
};
use crate::math::Real;
use std::sync::atomic::{AtomicU8, Ordering};

/// `sin[i] = sin x[i]`, `cos[i] = cos x[i]` with the pinned libm's bits in
/// both precisions: f32 runs [`sin_cos_f32`] in a vector loop (libm for the
/// rare `|x| ≥ 2²⁸·π/2`, infinities and NaN), f64 calls libm.
pub fn sin_cos_slices<T: Real>(x: &[T], sin: &mut [T], cos: &mut [T]) {
    assert!(
        sin.len() == x.len() && cos.len() == x.len(),
        "sin_cos_slices: sizes differ"
    );
    sin_cos_loop(x, sin, cos);
    if let (Some(sin), Some(cos)) = (T::as_f32_slice_mut(sin), T::as_f32_slice_mut(cos)) {
        for ((&v, s), c) in x.iter().zip(sin).zip(cos) {
            let v = v.to_f64() as f32; // exact: T is f32 here
            if v.to_bits() & 0x7fff_ffff >= 0x4dc9_0fdb {
                *s = libm::sinf(v);
                *c = libm::cosf(v);
            }
        }
    }
}

/// `e^x` as the fields compute it: this module's f32 function, libm in f64.
#[inline(always)]
pub fn exp<T: Real>(x: T) -> T {
    x.fast_exp()
}

/// `erf x` as the fields compute it: this module's f32 function, libm in f64.
#[inline(always)]
pub fn erf<T: Real>(x: T) -> T {
    x.fast_erf()
}

/// `tanh x` as the fields compute it: this module's f32 function, libm in f64.
#[inline(always)]
pub fn tanh<T: Real>(x: T) -> T {
    x.fast_tanh()
}

/// `sigmoid x` as the fields compute it: this module's f32 function,
/// `1/(1 + exp(−x))` with libm's exp in f64.
#[inline(always)]
pub fn sigmoid<T: Real>(x: T) -> T {
    x.fast_sigmoid()
}

/// Serialises the tests that pin the instruction set with [`force_isa`]
/// (a process-wide setting): such a test holds the guard while it runs, so
/// that another one does not change the path underneath it.
#[doc(hidden)]
pub fn isa_test_lock() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// Which instruction set the element-wise loops and the matrix kernels of
/// the fields run on (all give the same bits; see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// AVX-512F (its vector FMA included).
    Avx512,
    /// AVX2 with FMA.
    Avx2,
    /// The build target's baseline (SSE2 on x86-64).
    Baseline,
}

/// 0: the widest the CPU supports; otherwise a pinned [`Isa`] (1 baseline,
/// 2 AVX2, 3 AVX-512).
static FORCED: AtomicU8 = AtomicU8::new(0);

/// Pin the fields' kernels to `isa` (`None`: the widest available), for
/// tests and benchmarks that compare paths; a path the CPU lacks is refused
/// (returns false). Never changes results, only speed.
pub fn force_isa(isa: Option<Isa>) -> bool {
    let code = match isa {
        None => 0,
        Some(Isa::Baseline) => 1,
        Some(Isa::Avx2) if supported(Isa::Avx2) => 2,
        Some(Isa::Avx512) if supported(Isa::Avx512) => 3,
        Some(_) => return false,
    };
    FORCED.store(code, Ordering::Relaxed);
    true
}

fn supported(isa: Isa) -> bool {
    match isa {
        Isa::Baseline => true,
        #[cfg(target_arch = "x86_64")]
        // The AVX2 matrix tile uses FMA (AVX2 CPUs without it are rare).
        Isa::Avx2 => std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma"),
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => std::is_x86_feature_detected!("avx512f"),
        #[cfg(not(target_arch = "x86_64"))]
        _ => false,
    }
}

/// The [`Isa`] the kernels run on now: the pinned one, or the widest this
/// CPU supports.
#[inline]
pub fn isa() -> Isa {
    match FORCED.load(Ordering::Relaxed) {
        1 => return Isa::Baseline,
        2 => return Isa::Avx2,
        3 => return Isa::Avx512,
        _ => {}
    }
    if supported(Isa::Avx512) {
        Isa::Avx512
    } else if supported(Isa::Avx2) {
        Isa::Avx2
    } else {
        Isa::Baseline
    }
}

/// Define `$name(args)` that runs the `#[inline(always)]` generic function
/// `$body(args)` compiled for AVX-512, AVX2 or the baseline, picked at run
/// time: the loop inside `$body` is vectorised as wide as the CPU allows.
macro_rules! multiversion {
    ($vis:vis fn $name:ident<T: Real>($($arg:ident: $ty:ty),*) => $body:ident) => {
        $vis fn $name<T: Real>($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f")]
                unsafe fn avx512<T: Real>($($arg: $ty),*) {
                    $body($($arg),*)
                }
                #[target_feature(enable = "avx2")]
                unsafe fn avx2<T: Real>($($arg: $ty),*) {
                    $body($($arg),*)
                }
                match $crate::kernels::fastmath::isa() {
                    // SAFETY: the CPU supports the feature (checked by isa()).
                    $crate::kernels::fastmath::Isa::Avx512 => return unsafe { avx512::<T>($($arg),*) },
                    // SAFETY: as above (isa() returns Avx2 only where AVX2
                    // and FMA are present).
                    $crate::kernels::fastmath::Isa::Avx2 => return unsafe { avx2::<T>($($arg),*) },
                    $crate::kernels::fastmath::Isa::Baseline => {}
                }
            }
            $body($($arg),*)
        }
    };
}
pub(crate) use multiversion;

multiversion!(fn sin_cos_loop<T: Real>(x: &[T], sin: &mut [T], cos: &mut [T]) => sin_cos_body);

#[inline(always)]
fn sin_cos_body<T: Real>(x: &[T], sin: &mut [T], cos: &mut [T]) {
    for ((&v, s), c) in x.iter().zip(sin.iter_mut()).zip(cos.iter_mut()) {
        (*s, *c) = v.fast_sin_cos();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in ulp between an f32 and the exact value `want` (f64).
    fn ulp(got: f32, want: f64) -> u32 {
        let w = want as f32; // correctly rounded (within ½ ulp of f64's error)
        if got == w {
            return 0;
        }
        let key = |v: f32| {
            let b = v.to_bits() as i64;
            if b < 0x8000_0000 {
                b
            } else {
                0x8000_0000 - b
            }
        };
        (key(got) - key(w)).unsigned_abs() as u32
    }

    fn sweep(lo: f32, hi: f32, steps: usize) -> impl Iterator<Item = f32> {
        (0..=steps).map(move |i| lo + (hi - lo) * (i as f32 / steps as f32))
    }

    /// Every f32 in [lo, hi] with a bit-pattern stride (dense near zero).
    fn bits_sweep(lo: f32, hi: f32, stride: u32) -> Vec<f32> {
        let mut v = Vec::new();
        for sign in [1.0f32, -1.0] {
            let mut b = 0u32;
            loop {
                let x = f32::from_bits(b) * sign;
                if x.abs() > hi.abs().max(lo.abs()) {
                    break;
                }
                if x >= lo && x <= hi {
                    v.push(x);
                }
                b += stride;
            }
        }
        v
    }

    #[test]
    fn exp_error_bound() {
        let mut worst = 0;
        for x in bits_sweep(-87.0, 88.7, 97)
            .into_iter()
            .chain(sweep(-87.0, 88.7, 2_000_000))
        {
            let e = ulp(exp_f32(x), libm::exp(x as f64));
            assert!(
                e <= EXP_MAX_ULP,
                "exp({x:e}): {} vs {}",
                exp_f32(x),
                libm::exp(x as f64)
            );
            worst = worst.max(e);
        }
        assert_eq!(worst, EXP_MAX_ULP, "the documented bound is tight");
        // Limits and special values.
        assert_eq!(exp_f32(0.0), 1.0);
        assert_eq!(exp_f32(89.0), f32::INFINITY);
        assert_eq!(exp_f32(1e30), f32::INFINITY);
        assert_eq!(exp_f32(f32::INFINITY), f32::INFINITY);
        assert_eq!(exp_f32(-200.0), 0.0);
        assert_eq!(exp_f32(f32::NEG_INFINITY), 0.0);
        assert!(exp_f32(f32::NAN).is_nan());
        // Subnormal results: within 1 ulp of the subnormal spacing.
        for x in sweep(-103.0, -87.5, 10_000) {
            let want = libm::exp(x as f64);
            let got = exp_f32(x) as f64;
            assert!((got - want).abs() <= 1.5 * f32::from_bits(1) as f64, "{x}");
        }
    }

    /// Inputs where tanh_f32 and erf_f32 reach their bounds (found by
    /// `tanh_erf_every_f32`; both functions are odd, so ±).
    const TANH_WORST: [f32; 2] = [3.982_021_6, -3.982_021_6];
    const ERF_WORST: [f32; 2] = [2.461_116_8, -2.461_116_8];

    /// tanh and erf against libm in f64 on every f32 in [0, 10] (beyond,
    /// both are ±1 exactly; both are odd to the bit, checked in the tests
    /// above): the documented bounds hold and are reached, at the inputs
    /// the quick tests use. Half a minute in release:
    /// `cargo test --release --lib -- --ignored tanh_erf_every_f32`.
    #[test]
    #[ignore]
    fn tanh_erf_every_f32() {
        use rayon::prelude::*;
        type F = (fn(f32) -> f32, fn(f64) -> f64, u32, [f32; 2]);
        let fs: [F; 2] = [
            (tanh_f32, libm::tanh, TANH_MAX_ULP, TANH_WORST),
            (erf_f32, libm::erf, ERF_MAX_ULP, ERF_WORST),
        ];
        for (f, g, bound, worst_at) in fs {
            let (worst, at) = (0..=10.0f32.to_bits() >> 16)
                .into_par_iter()
                .map(|hi| {
                    (0..=u16::MAX)
                        .map(|lo| f32::from_bits(hi << 16 | lo as u32))
                        .map(|x| (ulp(f(x), g(x as f64)), x))
                        .fold((0, 0.0), |a, b| if b.0 > a.0 { b } else { a })
                })
                .reduce(
                    || (0, 0.0),
                    |a, b| {
                        if b.0 > a.0 || (b.0 == a.0 && b.1 < a.1) {
                            b
                        } else {
                            a
                        }
                    },
                );
            assert_eq!(worst, bound, "the documented bound is the maximum");
            assert_eq!(
                ulp(f(worst_at[0]), g(worst_at[0] as f64)),
                bound,
                "worst input {at:e}"
            );
        }
        assert_eq!(tanh_f32(9.1), 1.0);
        assert_eq!(erf_f32(4.0), 1.0);
    }

    #[test]
    fn erf_error_bound() {
        let mut worst = 0;
        for x in bits_sweep(-6.0, 6.0, 61)
            .into_iter()
            .chain(sweep(-6.0, 6.0, 2_000_000))
            .chain(ERF_WORST)
        {
            let e = ulp(erf_f32(x), libm::erf(x as f64));
            assert!(
                e <= ERF_MAX_ULP,
                "erf({x:e}) = {} vs {}",
                erf_f32(x),
                libm::erf(x as f64)
            );
            worst = worst.max(e);
        }
        assert_eq!(worst, ERF_MAX_ULP, "the documented erf bound is tight");
        assert_eq!(erf_f32(0.0), 0.0);
        assert_eq!(erf_f32(30.0), 1.0);
        assert_eq!(erf_f32(f32::NEG_INFINITY), -1.0);
        assert!(erf_f32(f32::NAN).is_nan());
    }

    #[test]
    fn tanh_and_sigmoid_error_bounds() {
        let (mut wt, mut ws) = (0, 0);
        for x in bits_sweep(-12.0, 12.0, 61)
            .into_iter()
            .chain(sweep(-12.0, 12.0, 2_000_000))
            .chain(TANH_WORST)
        {
            let e = ulp(tanh_f32(x), libm::tanh(x as f64));
            assert!(
                e <= TANH_MAX_ULP,
                "tanh({x:e}) = {} vs {}",
                tanh_f32(x),
                libm::tanh(x as f64)
            );
            wt = wt.max(e);
            let want = 1.0 / (1.0 + libm::exp(-(x as f64)));
            let e = ulp(sigmoid_f32(x), want);
            assert!(
                e <= SIGMOID_MAX_ULP,
                "sigmoid({x:e}) = {} vs {want}",
                sigmoid_f32(x)
            );
            ws = ws.max(e);
        }
        assert_eq!(wt, TANH_MAX_ULP, "the documented tanh bound is tight");
        assert_eq!(ws, SIGMOID_MAX_ULP, "the documented sigmoid bound is tight");
        assert_eq!(tanh_f32(0.0), 0.0);
        assert_eq!(tanh_f32(-0.0).to_bits(), (-0.0f32).to_bits());
        assert_eq!(tanh_f32(50.0), 1.0);
        assert_eq!(tanh_f32(-1e30), -1.0);
        assert_eq!(tanh_f32(f32::INFINITY), 1.0);
        assert!(tanh_f32(f32::NAN).is_nan());
        assert_eq!(sigmoid_f32(200.0), 1.0);
        assert_eq!(sigmoid_f32(-200.0), 0.0);
        assert_eq!(sigmoid_f32(0.0), 0.5);
        // Odd symmetry is exact.
        for x in sweep(0.0, 10.0, 10_000) {
            assert_eq!(tanh_f32(-x).to_bits(), (-tanh_f32(x)).to_bits());
        }
    }

    /// f32 inputs for the sin/cos checks: a stride through all 2³² bit
    /// patterns, every value within 3000 ulp of each range boundary of
    /// libm's sinf/cosf (both signs), and special values.
    fn sin_cos_inputs() -> Vec<f32> {
        let mut v: Vec<f32> = (0..=u32::MAX).step_by(4093).map(f32::from_bits).collect();
        for b in [
            0x3980_0000u32,
            0x3f49_0fda,
            0x4016_cbe3,
            0x407b_53d1,
            0x40af_eddf,
            0x40e2_31d5,
            0x4dc9_0fdb,
        ] {
            for bits in b - 3000..=b + 3000 {
                v.push(f32::from_bits(bits));
                v.push(-f32::from_bits(bits));
            }
        }
        v.extend([0.0, -0.0, f32::MIN_POSITIVE, 1e-45, f32::MAX, f32::INFINITY]);
        v.extend([f32::NEG_INFINITY, f32::NAN, 1.0, -1.0, 665.6, -1300.0]);
        v
    }

    fn assert_libm_sin_cos(xs: &[f32], sin: &[f32], cos: &[f32]) {
        for ((&x, s), c) in xs.iter().zip(sin).zip(cos) {
            assert_eq!(
                s.to_bits(),
                libm::sinf(x).to_bits(),
                "sin {x:e} ({:#x})",
                x.to_bits()
            );
            assert_eq!(
                c.to_bits(),
                libm::cosf(x).to_bits(),
                "cos {x:e} ({:#x})",
                x.to_bits()
            );
        }
    }

    #[test]
    fn sin_cos_gives_the_libm_bits() {
        let _isa = crate::kernels::fastmath::isa_test_lock();
        let xs = sin_cos_inputs();
        // The scalar function, on its whole range.
        for &x in &xs {
            if x.to_bits() & 0x7fff_ffff < 0x4dc9_0fdb {
                let (s, c) = sin_cos_f32(std::hint::black_box(x));
                assert_libm_sin_cos(&[x], &[s], &[c]);
            }
        }
        // The vector loops on every path, huge and non-finite values included.
        for isa in [
            Some(Isa::Baseline),
            Some(Isa::Avx2),
            Some(Isa::Avx512),
            None,
        ] {
            if !force_isa(isa) {
                continue;
            }
            let (mut s, mut c) = (vec![0.0; xs.len()], vec![0.0; xs.len()]);
            sin_cos_slices(&xs, &mut s, &mut c);
            assert_libm_sin_cos(&xs, &s, &c);
        }
        force_isa(None);
        // f64 is libm's.
        let xd: Vec<f64> = xs.iter().map(|&x| x as f64 * 1.000_000_1).collect();
        let (mut s, mut c) = (vec![0.0; xd.len()], vec![0.0; xd.len()]);
        sin_cos_slices(&xd, &mut s, &mut c);
        for ((&x, s), c) in xd.iter().zip(&s).zip(&c) {
            assert_eq!(s.to_bits(), libm::sin(x).to_bits());
            assert_eq!(c.to_bits(), libm::cos(x).to_bits());
        }
    }

    /// Every one of the 2³² f32 values (a few minutes in release:
    /// `cargo test --release --lib -- --ignored sin_cos_every_f32`).
    #[test]
    #[ignore]
    fn sin_cos_every_f32() {
        use rayon::prelude::*;
        (0..=u16::MAX).into_par_iter().for_each(|hi| {
            let xs: Vec<f32> = (0..=u16::MAX)
                .map(|lo| f32::from_bits((hi as u32) << 16 | lo as u32))
                .collect();
            let (mut s, mut c) = (vec![0.0; xs.len()], vec![0.0; xs.len()]);
            sin_cos_slices(&xs, &mut s, &mut c);
            assert_libm_sin_cos(&xs, &s, &c);
        });
    }

    multiversion!(fn tanh_all<T: Real>(x: &mut [T]) => tanh_all_body);

    #[inline(always)]
    fn tanh_all_body<T: Real>(x: &mut [T]) {
        for v in x.iter_mut() {
            *v = tanh(*v);
        }
    }

    #[test]
    fn vector_loops_give_the_scalar_bits() {
        let xs: Vec<f32> = sweep(-20.0, 20.0, 100_003).collect();
        let mut v = xs.clone();
        tanh_all(&mut v);
        for (x, y) in xs.iter().zip(&v) {
            assert_eq!(y.to_bits(), tanh_f32(std::hint::black_box(*x)).to_bits());
        }
        // f64 keeps libm.
        let mut d: Vec<f64> = xs.iter().map(|&x| x as f64).collect();
        tanh_all(&mut d);
        for (x, y) in xs.iter().zip(&d) {
            assert_eq!(y.to_bits(), libm::tanh(*x as f64).to_bits());
        }
    }
}
