use super::*;
use crate::kernels::fastmath::{force_isa, Isa};
use crate::math::Rng;

fn random_weights(seed: u64) -> LpipsWeights {
    let mut r = Rng::new(seed);
    let mut u = |n: usize, s: f64| -> Vec<f32> {
        (0..n)
            .map(|_| r.uniform_range(-s, s) as f32)
            .collect::<Vec<_>>()
    };
    let convs = VGG16_CONVS
        .iter()
        .map(|&(cin, cout)| {
            let s = (6.0 / (9 * cin) as f64).sqrt();
            (u(cout * cin * 9, s), u(cout, 0.05))
        })
        .collect();
    let lins = LAYER_CHANNELS.iter().map(|&c| u(c, 0.1)).collect();
    let id = |n: &str| WeightFile {
        path: n.into(),
        sha256: String::new(),
        official: false,
    };
    LpipsWeights::from_parts(convs, lins, id("vgg"), id("lin")).unwrap()
}

fn random_image(seed: u64, h: usize, w: usize) -> Vec<f64> {
    let mut r = Rng::new(seed);
    (0..3 * h * w).map(|_| r.uniform()).collect()
}

/// The im2col convolution equals a direct 3×3 convolution with zero
/// padding (plain loops, `(c, dy, dx)` order, in f64), and the pool a
/// direct 2×2 max.
#[test]
fn convolution_and_pool_match_direct_loops() {
    let w = random_weights(1);
    let net = Lpips::<f64>::new(&w);
    let (h, wd) = (17, 19);
    let img = random_image(2, h, wd);
    let f = net.features(&img, h, wd, Convention::D3dgs).unwrap();
    // Direct: ScalingLayer, conv1_1 + ReLU, conv1_2 + ReLU.
    let mut x: Vec<f64> = vec![0.0; 3 * h * wd];
    for c in 0..3 {
        for p in 0..h * wd {
            x[c * h * wd + p] = (img[c * h * wd + p] - SHIFT[c] as f64) / SCALE[c] as f64;
        }
    }
    let conv = |x: &[f64], cin: usize, l: usize| -> Vec<f64> {
        let (wt, b) = &w.convs[l];
        let cout = b.len();
        let mut y = vec![0.0; cout * h * wd];
        for o in 0..cout {
            for yy in 0..h {
                for xx in 0..wd {
                    let mut s = b[o] as f64;
                    for c in 0..cin {
                        for dy in 0..3 {
                            for dx in 0..3 {
                                let (sy, sx) = (yy as isize + dy - 1, xx as isize + dx - 1);
                                if sy < 0 || sx < 0 || sy >= h as isize || sx >= wd as isize {
                                    continue;
                                }
                                s += wt[((o * cin + c) * 3 + dy as usize) * 3 + dx as usize] as f64
                                    * x[(c * h + sy as usize) * wd + sx as usize];
                            }
                        }
                    }
                    y[(o * h + yy) * wd + xx] = s.max(0.0);
                }
            }
        }
        y
    };
    let y1 = conv(&x, 3, 0);
    let y2 = conv(&y1, 64, 1);
    let m = &f[0];
    assert_eq!((m.h, m.w, m.c), (h, wd, 64));
    let mut worst = 0.0f64;
    for c in 0..64 {
        for p in 0..h * wd {
            worst = worst.max((m.data[p * 64 + c] - y2[c * h * wd + p]).abs());
        }
    }
    assert!(worst < 1e-12, "conv differs by {worst}");
    // Max-pool of relu1_2 → the input of conv2_1: check the pool alone.
    let pooled = max_pool(m);
    assert_eq!((pooled.h, pooled.w), (8, 9));
    for y in 0..8 {
        for x in 0..9 {
            for c in 0..64 {
                let at = |dy: usize, dx: usize| m.data[((2 * y + dy) * wd + 2 * x + dx) * 64 + c];
                let want = at(0, 0).max(at(0, 1)).max(at(1, 0)).max(at(1, 1));
                assert_eq!(pooled.data[(y * 9 + x) * 64 + c], want);
            }
        }
    }
    // Feature sizes of the five layers (floors of odd sizes).
    let sizes: Vec<_> = f.iter().map(|m| (m.h, m.w, m.c)).collect();
    assert_eq!(
        sizes,
        [
            (17, 19, 64),
            (8, 9, 128),
            (4, 4, 256),
            (2, 2, 512),
            (1, 1, 512)
        ]
    );
}

fn bits<T: Real>(v: &LpipsValue<T>) -> Vec<u64> {
    std::iter::once(v.value.bits())
        .chain(v.per_layer.iter().map(|x| x.bits()))
        .collect()
}

/// Bit-identical results for 1, 2 and 3 threads and on every kernel path
/// this CPU has (the weights are packed for the path in force).
fn check_determinism<T: Real>() {
    let _isa = crate::kernels::fastmath::isa_test_lock();
    let w = random_weights(3);
    let (h, wd) = (33, 21);
    let a: Vec<T> = random_image(4, h, wd)
        .into_iter()
        .map(T::from_f64)
        .collect();
    let b: Vec<T> = random_image(5, h, wd)
        .into_iter()
        .map(T::from_f64)
        .collect();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let net = Lpips::<T>::new(&w);
            bits(&net.distance(&a, &b, h, wd, Convention::D3dgs).unwrap())
        })
    };
    let reference = run(1);
    for t in [2, 3] {
        assert_eq!(run(t), reference, "{t} threads");
    }
    for isa in [Isa::Baseline, Isa::Avx2, Isa::Avx512] {
        if force_isa(Some(isa)) {
            assert_eq!(run(2), reference, "{isa:?}");
        }
    }
    force_isa(None);
}

#[test]
fn lpips_is_identical_across_threads_and_kernel_paths_f32() {
    check_determinism::<f32>();
}

#[test]
fn lpips_is_identical_across_threads_and_kernel_paths_f64() {
    check_determinism::<f64>();
}

#[test]
fn bad_images_are_errors() {
    let net = Lpips::<f32>::new(&random_weights(6));
    let a = vec![0.5f32; 3 * 16 * 16];
    assert!(net.distance(&a, &a, 16, 16, Convention::D3dgs).is_ok());
    assert!(net
        .distance(&a, &a[..10], 16, 16, Convention::D3dgs)
        .is_err());
    let small = vec![0.5f32; 3 * 15 * 20];
    let e = net
        .distance(&small, &small, 15, 20, Convention::D3dgs)
        .unwrap_err();
    assert!(e.to_string().contains("16x16"), "{e}");
}
