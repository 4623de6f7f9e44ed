//! LPIPS v0.1 with the VGG16 backbone, as the `lpips` package computes it
//! (`lpips.LPIPS(net='vgg')`, the metric D-3DGS's `metrics.py` reports).
//!
//! For two `[3, H, W]` images `a`, `b`:
//!
//! 1. Input convention ([`Convention`]): D-3DGS passes `[0, 1]` images
//!    **without** `normalize=True`, so the package's `2x − 1` step is skipped
//!    and `[0, 1]` values reach a network that expects `[−1, 1]`
//!    ([`Convention::D3dgs`], the default here). [`Convention::Normalize`]
//!    applies `2x − 1` first, the convention of other tools.
//! 2. ScalingLayer: `(x − shift) / scale` per channel, shift
//!    `(−0.030, −0.088, −0.188)`, scale `(0.458, 0.448, 0.450)` (the package
//!    stores them as f32; f64 uses those f32 values widened, as `.double()`
//!    does).
//! 3. VGG16 `features[0:30]` (torchvision's layer order): 3×3 convolutions
//!    with padding 1 and bias, each followed by ReLU; 2×2 max-pool with
//!    stride 2 (odd sizes floor) before the 2nd, 3rd, 4th and 5th blocks. The
//!    outputs of relu1_2, relu2_2, relu3_3, relu4_3 and relu5_3 (64, 128,
//!    256, 512, 512 channels) are the five feature maps.
//! 4. Each feature vector (per pixel, over channels) is unit-normalised:
//!    `f / (sqrt(Σ f²) + 1e-10)`.
//! 5. Per layer: `(f_a − f_b)²` through the learned 1×1 linear layer (no
//!    bias), averaged over pixels; the result is the sum over the five layers
//!    (in layer order).
//!
//! Dropout in the linear layers is inactive (the package's eval mode).
//!
//! **Determinism.** Every convolution is an im2col product through the
//! project's matrix kernels ([`crate::kernels::matmul`]): each output is one
//! fused multiply-add sum over `(tap, input channel)` in a fixed order, the
//! same on every instruction-set path and for every thread count. The
//! pixel blocks that run in parallel are disjoint. Channel sums run in
//! channel order; the spatial mean is a fixed pairwise sum over pixels in
//! row-major order, then divided by the pixel count. The result does not
//! depend on the thread count or the CPU.
//!
//! The summation order differs from PyTorch's, so values agree with the
//! package to rounding (measured against it in the tests), not to the bit.

pub mod weights;

pub use weights::{LpipsWeights, Verify, WeightFile};

use crate::error::{Error, Result};
use crate::kernels::matmul::{matmul_block_into, pack, MatRef, Packed};
use crate::kernels::{par_blocks_written, vec_written_by};
use crate::loss::check_image_pair;
use crate::math::sum::pairwise_sum;
use crate::math::Real;
use rayon::prelude::*;

/// How `[0, 1]` images enter the network.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Convention {
    /// As D-3DGS (and Inria 3DGS) call the package: `[0, 1]` images passed
    /// without `normalize=True` (no `2x − 1`).
    D3dgs,
    /// `normalize=True`: `2x − 1` first, so `[0, 1]` becomes `[−1, 1]`.
    Normalize,
}

impl Convention {
    /// Short name used in files and options (`d3dgs`, `normalize`).
    pub fn name(self) -> &'static str {
        match self {
            Convention::D3dgs => "d3dgs",
            Convention::Normalize => "normalize",
        }
    }
    /// A one-line description for reports.
    pub fn describe(self) -> &'static str {
        match self {
            Convention::D3dgs => {
                "LPIPS v0.1 VGG, D-3DGS convention: [0,1] images passed without normalize=True (no 2x-1)"
            }
            Convention::Normalize => {
                "LPIPS v0.1 VGG, normalize=True: [0,1] images mapped to [-1,1] (2x-1) first"
            }
        }
    }
}

/// Channels of VGG16's 13 convolutions, `(in, out)`, in `features` order.
pub const VGG16_CONVS: [(usize, usize); 13] = [
    (3, 64),
    (64, 64),
    (64, 128),
    (128, 128),
    (128, 256),
    (256, 256),
    (256, 256),
    (256, 512),
    (512, 512),
    (512, 512),
    (512, 512),
    (512, 512),
    (512, 512),
];

/// Index in torchvision's `features` of each convolution (its state_dict
/// keys are `features.{i}.weight` / `.bias`).
pub const VGG16_CONV_INDEX: [usize; 13] = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28];

/// Convolutions per slice (relu1_2, relu2_2, relu3_3, relu4_3, relu5_3).
const SLICES: [usize; 5] = [2, 2, 3, 3, 3];

/// Channels of the five feature maps (and of the five linear layers).
pub const LAYER_CHANNELS: [usize; 5] = [64, 128, 256, 512, 512];

/// The ScalingLayer constants as the package stores them (f32).
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];

/// Pixels per parallel task of a convolution (does not affect results).
const PIXEL_BLOCK: usize = 96;

/// One 3×3 convolution: weights as the `[9·in, out]` matrix of the im2col
/// product (row `(dy·3 + dx)·in + c`), packed once.
struct Conv<T> {
    cin: usize,
    cout: usize,
    w: Packed<T>,
    bias: Vec<T>,
}

/// A feature map, pixel-major: `data[(y·w + x)·c + channel]`.
#[derive(Clone, Debug)]
pub struct FeatureMap<T> {
    /// Height, pixels.
    pub h: usize,
    /// Width, pixels.
    pub w: usize,
    /// Channels.
    pub c: usize,
    /// `h · w · c` values.
    pub data: Vec<T>,
}

/// The LPIPS network in precision `T`, ready to evaluate.
pub struct Lpips<T> {
    convs: Vec<Conv<T>>,
    lins: Vec<Vec<T>>,
    /// The file the VGG convolution weights came from.
    pub vgg: WeightFile,
    /// The file the linear-layer weights came from.
    pub lin: WeightFile,
}

/// LPIPS of one image pair: the total and each layer's term.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LpipsValue<T> {
    /// The distance: the sum of the five layer terms.
    pub value: T,
    /// Each VGG layer's term, shallowest first.
    pub per_layer: [T; 5],
}

impl<T: Real> Lpips<T> {
    /// Build the network from loaded weights (shapes were checked on load).
    pub fn new(weights: &LpipsWeights) -> Lpips<T> {
        let convs = VGG16_CONVS
            .iter()
            .zip(&weights.convs)
            .map(|(&(cin, cout), (w, b))| {
                // torch layout [out, in, 3, 3] → im2col matrix [9·in, out].
                let k = 9 * cin;
                let mut m = vec![T::ZERO; k * cout];
                for o in 0..cout {
                    for c in 0..cin {
                        for t in 0..9 {
                            m[(t * cin + c) * cout + o] = T::from_f32(w[(o * cin + c) * 9 + t]);
                        }
                    }
                }
                Conv {
                    cin,
                    cout,
                    w: pack(MatRef::row_major(&m, k, cout)),
                    bias: b.iter().map(|&v| T::from_f32(v)).collect(),
                }
            })
            .collect();
        let lins = weights
            .lins
            .iter()
            .map(|l| l.iter().map(|&v| T::from_f32(v)).collect())
            .collect();
        Lpips {
            convs,
            lins,
            vgg: weights.vgg.clone(),
            lin: weights.lin.clone(),
        }
    }

    /// The five unnormalised feature maps (relu1_2 … relu5_3) of a `[3, h, w]`
    /// image under `convention`. Errors if the image is not `3·h·w` values or
    /// is smaller than 16×16 (four 2×2 pools must leave a pixel).
    pub fn features(
        &self,
        image: &[T],
        h: usize,
        w: usize,
        convention: Convention,
    ) -> Result<Vec<FeatureMap<T>>> {
        check_image_pair(image.len(), image.len(), h, w)?;
        if h < 16 || w < 16 {
            return Err(Error::invalid(
                "LPIPS image size",
                format!("{w}x{h}: VGG16 needs at least 16x16 pixels"),
            ));
        }
        let two = T::from_f64(2.0);
        // [3, h, w] → pixel-major [h·w, 3], input convention, ScalingLayer.
        let mut x = vec![T::ZERO; h * w * 3];
        for c in 0..3 {
            let (shift, scale) = (T::from_f32(SHIFT[c]), T::from_f32(SCALE[c]));
            for p in 0..h * w {
                let mut v = image[c * h * w + p];
                if convention == Convention::Normalize {
                    v = two * v - T::ONE;
                }
                x[p * 3 + c] = (v - shift) / scale;
            }
        }
        let mut cur = FeatureMap {
            h,
            w,
            c: 3,
            data: x,
        };
        let mut out = Vec::with_capacity(5);
        let mut conv = self.convs.iter();
        for (s, &n) in SLICES.iter().enumerate() {
            if s > 0 {
                cur = max_pool(&cur);
            }
            for _ in 0..n {
                let layer = conv.next().expect("13 convolutions");
                cur = conv3x3_relu(&cur, layer);
            }
            out.push(cur.clone());
        }
        Ok(out)
    }

    /// LPIPS between two `[3, h, w]` images as given (no quantisation).
    pub fn distance(
        &self,
        a: &[T],
        b: &[T],
        h: usize,
        w: usize,
        convention: Convention,
    ) -> Result<LpipsValue<T>> {
        check_image_pair(a.len(), b.len(), h, w)?;
        let fa = self.features(a, h, w, convention)?;
        let fb = self.features(b, h, w, convention)?;
        let mut per_layer = [T::ZERO; 5];
        for (l, ((ma, mb), lin)) in fa.iter().zip(&fb).zip(&self.lins).enumerate() {
            per_layer[l] = layer_distance(ma, mb, lin);
        }
        // `val = 0; val += res[l]` in layer order.
        let mut value = T::ZERO;
        for v in per_layer {
            value += v;
        }
        Ok(LpipsValue { value, per_layer })
    }
}

/// LPIPS as the evaluation reports it: an f32 network (as the package runs
/// on the GPU or CPU) applied to 8-bit-quantised renders and ground truth
/// (`u8 / 255` in f32, as `torchvision.transforms.functional.to_tensor`
/// reads a saved PNG), under one input convention.
pub struct Metric {
    net: Lpips<f32>,
    /// How images are mapped before the network.
    pub convention: Convention,
}

/// What produced an LPIPS number: convention and weight files.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MetricInfo {
    /// How images were mapped before the network.
    pub convention: Convention,
    /// [`Convention::describe`].
    pub description: String,
    /// The VGG convolution weight file.
    pub vgg: WeightFile,
    /// The linear-layer weight file.
    pub lin: WeightFile,
}

impl std::fmt::Debug for Metric {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Metric")
            .field("convention", &self.convention)
            .field("vgg", &self.net.vgg)
            .field("lin", &self.net.lin)
            .finish()
    }
}

impl Metric {
    /// The metric with these weights and input convention.
    pub fn new(weights: &LpipsWeights, convention: Convention) -> Metric {
        Metric {
            net: Lpips::new(weights),
            convention,
        }
    }

    /// Read the weight files ([`LpipsWeights::load`]) and build the metric.
    pub fn load(
        vgg: &std::path::Path,
        lin: &std::path::Path,
        verify: Verify,
        convention: Convention,
    ) -> Result<Metric> {
        Ok(Metric::new(
            &LpipsWeights::load(vgg, lin, verify)?,
            convention,
        ))
    }

    /// LPIPS of one `[3, h, w]` render against its ground truth, both
    /// quantised to 8 bits first.
    pub fn view<T: Real>(&self, render: &[T], gt: &[T], h: usize, w: usize) -> Result<f64> {
        check_image_pair(render.len(), gt.len(), h, w)?;
        let u8_f32 = |v: &[T]| -> Vec<f32> {
            v.iter()
                .map(|&x| crate::loss::metrics::to_u8(x) as f32 / 255.0)
                .collect()
        };
        Ok(self
            .net
            .distance(&u8_f32(render), &u8_f32(gt), h, w, self.convention)?
            .value as f64)
    }

    /// What produces this metric's numbers (for records and reports).
    pub fn info(&self) -> MetricInfo {
        MetricInfo {
            convention: self.convention,
            description: self.convention.describe().to_string(),
            vgg: self.net.vgg.clone(),
            lin: self.net.lin.clone(),
        }
    }
}

/// `relu(conv3x3(x) + bias)` with zero padding 1, as an im2col product over
/// disjoint blocks of output pixels.
fn conv3x3_relu<T: Real>(x: &FeatureMap<T>, conv: &Conv<T>) -> FeatureMap<T> {
    assert_eq!(x.c, conv.cin, "convolution input channels");
    let (h, w, cin, cout) = (x.h, x.w, conv.cin, conv.cout);
    let k = 9 * cin;
    let n = h * w;
    let data = vec_written_by(n * cout, |data| {
        par_blocks_written(data, PIXEL_BLOCK * cout, &mut [(); 0], 0, |blk, ob, _| {
            let p0 = blk * PIXEL_BLOCK;
            let rows = ob.len() / cout;
            // im2col rows of this block: [rows, 9·cin], taps in (dy, dx) order.
            let mut col = vec![T::ZERO; rows * k];
            for (r, dst) in col.chunks_exact_mut(k).enumerate() {
                let (y, xx) = ((p0 + r) / w, (p0 + r) % w);
                for dy in 0..3 {
                    let yy = y + dy;
                    if yy == 0 || yy > h {
                        continue;
                    }
                    for dx in 0..3 {
                        let xs = xx + dx;
                        if xs == 0 || xs > w {
                            continue;
                        }
                        let src = ((yy - 1) * w + xs - 1) * cin;
                        let t = dy * 3 + dx;
                        dst[t * cin..(t + 1) * cin].copy_from_slice(&x.data[src..src + cin]);
                    }
                }
            }
            let c = matmul_block_into(MatRef::row_major(&col, rows, k), &conv.w, ob);
            for row in c.chunks_exact_mut(cout) {
                for (v, &b) in row.iter_mut().zip(&conv.bias) {
                    let s = *v + b;
                    // ReLU; NaN stays NaN (as torch's).
                    *v = if s < T::ZERO { T::ZERO } else { s };
                }
            }
            c
        })
    });
    FeatureMap {
        h,
        w,
        c: cout,
        data,
    }
}

/// 2×2 max-pool with stride 2 (odd trailing rows/columns dropped); NaN
/// propagates, as in torch.
fn max_pool<T: Real>(x: &FeatureMap<T>) -> FeatureMap<T> {
    let (h, w, c) = (x.h / 2, x.w / 2, x.c);
    let mut data = vec![T::ZERO; h * w * c];
    data.par_chunks_mut(w * c).enumerate().for_each(|(y, row)| {
        for xx in 0..w {
            let at = |dy: usize, dx: usize| ((2 * y + dy) * x.w + 2 * xx + dx) * c;
            let (a, b, d, e) = (at(0, 0), at(0, 1), at(1, 0), at(1, 1));
            for ch in 0..c {
                let mut m = x.data[a + ch];
                for v in [x.data[b + ch], x.data[d + ch], x.data[e + ch]] {
                    if v > m || v.is_nan() {
                        m = v;
                    }
                }
                row[xx * c + ch] = m;
            }
        }
    });
    FeatureMap { h, w, c, data }
}

/// One layer's term: spatial mean of `lin · (f̂_a − f̂_b)²`, with
/// `f̂ = f / (sqrt(Σ f²) + 1e-10)` per pixel.
fn layer_distance<T: Real>(a: &FeatureMap<T>, b: &FeatureMap<T>, lin: &[T]) -> T {
    let c = a.c;
    let eps = T::from_f64(1e-10);
    let n = a.h * a.w;
    let mut per_pixel = vec![T::ZERO; n];
    per_pixel
        .par_chunks_mut(256)
        .enumerate()
        .for_each(|(blk, out)| {
            for (i, o) in out.iter_mut().enumerate() {
                let p = blk * 256 + i;
                let fa = &a.data[p * c..(p + 1) * c];
                let fb = &b.data[p * c..(p + 1) * c];
                let (mut sa, mut sb) = (T::ZERO, T::ZERO);
                for (&u, &v) in fa.iter().zip(fb) {
                    sa += u * u;
                    sb += v * v;
                }
                let (na, nb) = (sa.sqrt() + eps, sb.sqrt() + eps);
                let mut s = T::ZERO;
                for ((&u, &v), &l) in fa.iter().zip(fb).zip(lin) {
                    let d = u / na - v / nb;
                    s += l * (d * d);
                }
                *o = s;
            }
        });
    pairwise_sum(&per_pixel) / T::from_usize(n)
}

#[cfg(test)]
mod tests;
