//! Deformation fields: gradients by central differences, an independent
//! scalar re-implementation of both forwards, thread-count determinism,
//! weight files and the oracle stage.

mod support;

use approx::abs_diff_eq;
use liquid_splat::deform::{
    Activation, CfcConfig, Deformation, Field, FieldConfig, FieldKind, MlpConfig, Variant,
};
use liquid_splat::io::TensorFile;
use liquid_splat::math::gradcheck::{compare, cotangent};
use liquid_splat::math::Rng;

fn config(
    kind: FieldKind,
    variant: Variant,
    depth: usize,
    width: usize,
    act: Activation,
) -> FieldConfig {
    match kind {
        FieldKind::Mlp => {
            assert_eq!(act, Activation::Relu, "the MLP field is ReLU");
            FieldConfig::Mlp(MlpConfig {
                variant,
                depth,
                width,
                is_6dof: false,
            })
        }
        FieldKind::Cfc => FieldConfig::Cfc(CfcConfig {
            variant,
            depth,
            width,
            activation: act,
            backbone_units: 6,
            backbone_layers: 2,
        }),
    }
}

fn inputs(seed: u64, n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut r = Rng::new(seed);
    let xyz = (0..3 * n).map(|_| r.uniform_range(-1.0, 1.0)).collect();
    let t = (0..n).map(|_| r.uniform()).collect();
    (xyz, t)
}

fn dot(d: &Deformation<f64>, v: &Deformation<f64>) -> f64 {
    let mut s = 0.0;
    for (a, b) in [
        (&d.d_xyz, &v.d_xyz),
        (&d.d_rotation, &v.d_rotation),
        (&d.d_scaling, &v.d_scaling),
    ] {
        for (x, y) in a.iter().zip(b.iter()) {
            s += x * y;
        }
    }
    s
}

/// Sixth-order central difference
/// `(45(L₁ − L₋₁) − 9(L₂ − L₋₂) + (L₃ − L₋₃)) / 60h`, `Lₖ = L(x + k·s)`, with a
/// step `s = h·max(1, |x|)`: truncation error O(h⁶), so a step of 1e-2 keeps
/// both truncation and rounding noise near 1e-13, well below the 1e-6
/// tolerance even for small gradient entries.
fn central6(x: f64, h: f64, mut f: impl FnMut(f64) -> f64) -> f64 {
    let s = h * x.abs().max(1.0);
    let mut d = [0.0; 3];
    for (k, dk) in d.iter_mut().enumerate() {
        let o = (k + 1) as f64 * s;
        *dk = f(x + o) - f(x - o);
    }
    (45.0 * d[0] - 9.0 * d[1] + d[2]) / (60.0 * s)
}

/// Move every ReLU pre-activation at least `margin` away from the kink by
/// shifting the biases of the units that come too close (test-only change of
/// the weights; layer by layer in forward order, re-evaluating after each).
fn clear_relu_kinks(field: &mut Field<f64>, xyz: &[f64], t: &[f64], margin: f64) {
    let cfg = *field.config();
    let scalar = if cfg.kind() == FieldKind::Mlp {
        scalar_mlp
    } else {
        scalar_cfc
    };
    for _ in 0..64 {
        let file = liquid_splat::oracle::field::field_to_tensor_file(field);
        RELU_PRE.with(|r| r.borrow_mut().clear());
        let mut per_row = Vec::new();
        for i in 0..t.len() {
            scalar(&file, &cfg, &xyz[3 * i..3 * i + 3], t[i]);
            per_row.push(RELU_PRE.with(|r| std::mem::take(&mut *r.borrow_mut())));
        }
        // First layer (in forward order) with a pre-activation inside the margin.
        let layers = per_row[0].len();
        let bad = (0..layers).find(|&k| {
            per_row
                .iter()
                .any(|row| row[k].1.iter().any(|v| v.abs() < margin))
        });
        let Some(k) = bad else { return };
        let name = per_row[0][k].0.clone();
        let spec = field
            .layout()
            .iter()
            .find(|s| s.name == format!("{name}.bias"))
            .unwrap()
            .clone();
        for unit in 0..spec.len() {
            let vals: Vec<f64> = per_row.iter().map(|row| row[k].1[unit]).collect();
            let shift = (0..400)
                .map(|j| if j % 2 == 0 { 1.0 } else { -1.0 } * (j / 2) as f64 * 0.25 * margin)
                .find(|c| vals.iter().all(|v| (v + c).abs() >= margin))
                .expect("a bias shift clears the kink");
            field.params_mut()[spec.offset + unit] += shift;
        }
    }
    panic!("could not clear the ReLU kinks");
}

/// Check every parameter tensor and t; entries of tensors with more than
/// `dense` values are sampled with a fixed stride (all tensors are covered).
fn gradcheck(cfg: FieldConfig, seed: u64, dense: usize) {
    gradcheck_with(cfg, seed, dense, 1e-2, |_| {});
}

/// Step of the central differences in t (see `gradcheck_with`).
const T_STEP: f64 = 1e-5;

/// [`gradcheck`] with relative weight step `h`, after `prepare` edits the
/// initial weights.
fn gradcheck_with(
    cfg: FieldConfig,
    seed: u64,
    dense: usize,
    h: f64,
    prepare: impl Fn(&mut Field<f64>),
) {
    gradcheck_times(cfg, seed, dense, h, prepare, None);
}

/// [`gradcheck_with`] on the five times `times` instead of random ones.
fn gradcheck_times(
    cfg: FieldConfig,
    seed: u64,
    dense: usize,
    h: f64,
    prepare: impl Fn(&mut Field<f64>),
    times: Option<[f64; 5]>,
) {
    let n = 5;
    let mut field = Field::<f64>::new(cfg, seed).unwrap();
    prepare(&mut field);
    let (xyz, mut t) = inputs(seed + 100, n);
    if let Some(times) = times {
        t = times.to_vec();
    }
    // Relative weight steps of 3 × 1e-2 move pre-activations by far less than this.
    clear_relu_kinks(&mut field, &xyz, &t, 0.2);
    let v = Deformation {
        d_xyz: cotangent(seed + 1, 3 * n),
        d_rotation: cotangent(seed + 2, 4 * n),
        d_scaling: cotangent(seed + 3, 3 * n),
    };
    let (d0, cache) = field.forward(&xyz, &t).unwrap();
    let fg = field.backward(&cache, &v).unwrap();
    let (gp, gt) = (&fg.params, &fg.t);
    let tol = 1e-6;
    // Round-off of the numeric reference itself: central6 divides loss
    // differences by 60·s with coefficients 2·(45 + 9 + 1), so an error of
    // δ in the loss becomes up to 1.83·δ/s in the derivative (s ≥ h). The
    // loss is allowed 16 ulps (the measured scatter of the estimate across
    // step sizes on a near-zero entry was about 3 ulps of the loss,
    // 6e-14 absolute at h = 1e-2). Entries whose numeric value is below
    // this noise are compared in absolute terms against it instead of
    // relatively; every other entry is unaffected.
    let noise = 1.83 * 16.0 * f64::EPSILON * dot(&d0, &v).abs() / h;
    let mut f = field.clone();
    for spec in field.layout() {
        let range = spec.range();
        let stride = if range.len() > dense { 7 } else { 1 };
        let idx: Vec<usize> = range.clone().step_by(stride).collect();
        let mut analytic = Vec::new();
        let mut numeric = Vec::new();
        for &i in &idx {
            let num = central6(field.params()[i], h, |x| {
                f.params_mut()[i] = x;
                let (d, _) = f.forward(&xyz, &t).unwrap();
                dot(&d, &v)
            });
            f.params_mut()[i] = field.params()[i];
            analytic.push(gp[i]);
            numeric.push(num);
        }
        let scale = analytic.iter().fold(0.0f64, |m, a| m.max(a.abs()));
        let floor = (1e-3 * scale).max(noise / tol).max(1e-10);
        let r = compare(&spec.name, &analytic, &numeric, floor);
        assert!(r.passes(tol), "{cfg:?}\n{r}");
    }
    let num: Vec<f64> = (0..n)
        .map(|k| {
            let mut tt = t.clone();
            // γ₁₀(t) has frequencies up to 512: a smaller step for t. 1e-5
            // is where truncation (above 3e-5) and round-off (below 1e-6)
            // are both smallest: measured on the real-variant CfC, typical
            // entries agree with the analytic gradient to 1e-12 relative
            // (1e-10 at a step of 1e-7, 1e-7 at 3e-4).
            central6(t[k], T_STEP, |x| {
                tt[k] = x;
                dot(&field.forward(&xyz, &tt).unwrap().0, &v)
            })
        })
        .collect();
    let t_noise = noise * h / T_STEP;
    let r = compare("t", gt, &num, (t_noise / tol).max(1e-10));
    assert!(r.passes(tol), "{cfg:?}\n{r}");
    // The canonical means: zero for additive fields, (R − I)ᵀ·g through the
    // 6-DoF warp (the network's own input stays stop-gradient).
    let gx = &fg.xyz;
    // Only the explicit dependence on x: the warp with the head outputs frozen.
    let wv = warp_heads(&field, &xyz, &t);
    let num: Vec<f64> = (0..3 * n)
        .map(|k| {
            let mut xx = xyz.clone();
            central6(xyz[k], 1e-2, |x| {
                xx[k] = x;
                warp_dot(&wv, &xx, &v.d_xyz)
            })
        })
        .collect();
    if cfg.is_6dof() {
        let r = compare("xyz (warp)", gx, &num, 1e-10);
        assert!(r.passes(tol), "{cfg:?}\n{r}");
    } else {
        assert!(gx.iter().all(|&g| g == 0.0));
    }
}

/// The raw `branch_w | branch_v` outputs `[n, 6]` of a 6-DoF field, by the
/// scalar re-implementation; empty for other fields.
fn warp_heads(field: &Field<f64>, xyz: &[f64], t: &[f64]) -> Vec<f64> {
    let cfg = *field.config();
    if !cfg.is_6dof() {
        return Vec::new();
    }
    let file = liquid_splat::oracle::field::field_to_tensor_file(field);
    (0..t.len())
        .flat_map(|i| {
            let h = mlp_trunk(&file, &cfg, &xyz[3 * i..3 * i + 3], t[i]);
            let mut wv = lin(&file, "branch_w", &h);
            wv.extend(lin(&file, "branch_v", &h));
            wv
        })
        .collect()
}

/// `Σ g · warp(w, v, x)` over Gaussians with the head outputs `wv` held fixed.
fn warp_dot(wv: &[f64], xyz: &[f64], g: &[f64]) -> f64 {
    if wv.is_empty() {
        return 0.0;
    }
    let mut s = 0.0;
    for i in 0..xyz.len() / 3 {
        let d = se3_rodrigues(
            &wv[6 * i..6 * i + 3],
            &wv[6 * i + 3..6 * i + 6],
            &xyz[3 * i..3 * i + 3],
        );
        for k in 0..3 {
            s += g[3 * i + k] * d[k];
        }
    }
    s
}

fn cross(a: &[f64], b: &[f64]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Independent form of the 6-DoF warp (docs/UPSTREAM.md §6.2) with cross products
/// instead of matrices: `R·x = x + sin θ·w'×x + (1 − cos θ)·w'×(w'×x)`,
/// `p = θ·v' + (1 − cos θ)·w'×v' + (θ − sin θ)·w'×(w'×v')`, with
/// `w' = w/θ + 1e-5`, `v' = v/θ + 1e-5`; returns `R·x + p − x` (and the
/// crate's θ = 0 limit, `v`, when w = 0).
fn se3_rodrigues(w: &[f64], v: &[f64], x: &[f64]) -> [f64; 3] {
    let th = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
    if th == 0.0 {
        return [v[0], v[1], v[2]];
    }
    let w1: Vec<f64> = w.iter().map(|c| c / th + 1e-5).collect();
    let v1: Vec<f64> = v.iter().map(|c| c / th + 1e-5).collect();
    let (s, c) = (libm::sin(th), libm::cos(th));
    let wx = cross(&w1, x);
    let wwx = cross(&w1, &wx);
    let wv = cross(&w1, &v1);
    let wwv = cross(&w1, &wv);
    [0, 1, 2].map(|k| {
        s * wx[k] + (1.0 - c) * wwx[k] + th * v1[k] + (1.0 - c) * wv[k] + (th - s) * wwv[k]
    })
}

#[test]
fn cfc_gradients_every_activation_and_depth() {
    for act in [
        Activation::Gelu,
        Activation::Relu,
        Activation::Silu,
        Activation::Tanh,
        Activation::LecunTanh,
    ] {
        for depth in [1, 3, 4] {
            gradcheck(
                config(FieldKind::Cfc, Variant::Real, depth, 8, act),
                11 + depth as u64,
                256,
            );
        }
    }
    // Synthetic variant (timenet), odd and even depth; the 13×256 and 256×30
    // timenet weights are sampled with stride 7.
    gradcheck(
        config(FieldKind::Cfc, Variant::Synthetic, 3, 8, Activation::Gelu),
        5,
        256,
    );
    gradcheck(
        config(
            FieldKind::Cfc,
            Variant::Synthetic,
            2,
            8,
            Activation::LecunTanh,
        ),
        6,
        256,
    );
}

/// Shared times: the CfC field merges time_a and time_b for each τ (see
/// `deform::cfc`), and both fields run the timenet once per run of equal
/// times. One τ for every row (the training case: time_a's weight gradient
/// is then τ times time_b's), and runs of repeated times, some equal to the
/// first row's and some not.
#[test]
fn gradients_with_shared_times() {
    for times in [
        [0.37; 5],
        [0.2, 0.2, 0.7, 0.2, 0.7],
        [0.6, 0.1, 0.1, 0.6, 0.6],
    ] {
        for cfg in [
            config(FieldKind::Cfc, Variant::Real, 3, 8, Activation::Gelu),
            config(
                FieldKind::Cfc,
                Variant::Synthetic,
                2,
                8,
                Activation::LecunTanh,
            ),
            // Both fields' timenet runs once per run of equal times, its
            // backward once per run (each row's t gradient from the run's
            // Jacobian).
            config(FieldKind::Mlp, Variant::Synthetic, 3, 8, Activation::Relu),
        ] {
            gradcheck_times(cfg, 21, 256, 1e-2, |_| {}, Some(times));
        }
    }
}

/// Backbones of one and of three layers (the paper's cells have two): the
/// backward's loop over the layers after the first, and a backbone whose
/// first layer feeds the heads directly.
#[test]
fn cfc_gradients_other_backbone_depths() {
    for (layers, depth, act) in [
        (1, 3, Activation::Gelu),
        (3, 2, Activation::Silu),
        (3, 1, Activation::LecunTanh),
    ] {
        let cfg = FieldConfig::Cfc(CfcConfig {
            variant: Variant::Real,
            depth,
            width: 8,
            activation: act,
            backbone_units: 6,
            backbone_layers: layers,
        });
        gradcheck(cfg, 40 + layers as u64, 256);
    }
}

#[test]
fn mlp_gradients_several_depths() {
    for depth in [3, 4, 5] {
        gradcheck(
            config(FieldKind::Mlp, Variant::Real, depth, 8, Activation::Relu),
            21 + depth as u64,
            256,
        );
    }
    gradcheck(
        config(FieldKind::Mlp, Variant::Synthetic, 3, 8, Activation::Relu),
        7,
        256,
    );
}

fn six_dof(variant: Variant, depth: usize) -> FieldConfig {
    FieldConfig::Mlp(MlpConfig {
        variant,
        depth,
        width: 8,
        is_6dof: true,
    })
}

#[test]
fn mlp_6dof_gradients() {
    gradcheck(six_dof(Variant::Real, 3), 31, 256);
    gradcheck(six_dof(Variant::Synthetic, 4), 32, 256);
}

/// Zero `branch_w` weights and bias: w = 0 exactly, θ = 0 for every Gaussian.
fn zero_branch_w(field: &mut Field<f64>) {
    for s in field.layout().to_vec() {
        if s.name.starts_with("branch_w.") {
            field.params_mut()[s.range()].fill(0.0);
        }
    }
}

#[test]
fn mlp_6dof_theta_zero_is_finite_and_defined() {
    let cfg = six_dof(Variant::Real, 3);
    let mut field = Field::<f64>::new(cfg, 40).unwrap();
    zero_branch_w(&mut field);
    let n = 6;
    let (xyz, t) = inputs(41, n);
    let (d, cache) = field.forward(&xyz, &t).unwrap();
    // d_xyz is the branch_v output itself (R = I, p = v).
    let file = liquid_splat::oracle::field::field_to_tensor_file(&field);
    for i in 0..n {
        let h = mlp_trunk(&file, &cfg, &xyz[3 * i..3 * i + 3], t[i]);
        let v = lin(&file, "branch_v", &h);
        for (k, vk) in v.iter().enumerate() {
            let got = d.d_xyz[3 * i + k];
            assert!(
                abs_diff_eq!(got, *vk, epsilon = 1e-12 * vk.abs().max(1.0)),
                "{got} vs {vk}"
            );
        }
    }
    let g = Deformation {
        d_xyz: cotangent(1, 3 * n),
        d_rotation: cotangent(2, 4 * n),
        d_scaling: cotangent(3, 3 * n),
    };
    let fg = field.backward(&cache, &g).unwrap();
    assert!(fg.params.iter().chain(&fg.t).all(|v| v.is_finite()));
    assert!(fg.xyz.iter().all(|&v| v == 0.0));
    // The defined gradient at θ = 0 is what central differences see there.
    // The warp is not smooth at w = 0 (its 1e-5 offsets add terms in ‖w‖²
    // that depend on the direction of w at order 1e-5), so the difference
    // quotient carries an error of about 0.6·step·1e-5·C; and upstream's
    // `(1 − cos θ)·[w']×(v/θ)` loses ~1e-16/θ absolutely to cancellation,
    // which the quotient divides by the step again. A step of 1e-3 keeps
    // both near 1e-9 (1e-2 leaves ~1e-7 of the first, 1e-5 ~1e-6 of the second).
    gradcheck_with(cfg, 40, 256, 1e-3, zero_branch_w);
}

// ---- independent scalar re-implementation of the forward passes ----

fn lin(f: &TensorFile, name: &str, x: &[f64]) -> Vec<f64> {
    let w = f.real_array::<f64>(&format!("{name}.weight")).unwrap();
    let ws = w.shape().to_vec();
    let w: Vec<f64> = w.iter().copied().collect();
    let b: Vec<f64> = f
        .real_array::<f64>(&format!("{name}.bias"))
        .unwrap()
        .iter()
        .copied()
        .collect();
    assert_eq!(ws[1], x.len(), "{name}");
    (0..ws[0])
        .map(|o| {
            let mut s = 0.0;
            for (k, xk) in x.iter().enumerate() {
                s += xk * w[o * ws[1] + k];
            }
            s + b[o]
        })
        .collect()
}

fn gamma(p: &[f64], levels: usize) -> Vec<f64> {
    let mut out = p.to_vec();
    for k in 0..levels {
        let fr = (1u64 << k) as f64;
        out.extend(p.iter().map(|v| libm::sin(v * fr)));
        out.extend(p.iter().map(|v| libm::cos(v * fr)));
    }
    out
}

thread_local! {
    /// ReLU pre-activations seen by the scalar forward, per layer name (test-only probe).
    static RELU_PRE: std::cell::RefCell<Vec<(String, Vec<f64>)>> = const { std::cell::RefCell::new(Vec::new()) };
}

fn relu_probe(name: &str, pre: &[f64]) -> Vec<f64> {
    RELU_PRE.with(|r| r.borrow_mut().push((name.to_string(), pre.to_vec())));
    pre.iter().map(|v| v.max(0.0)).collect()
}

fn time_feature(f: &TensorFile, variant: Variant, t: f64) -> Vec<f64> {
    match variant {
        Variant::Synthetic => {
            let h = relu_probe("timenet.0", &lin(f, "timenet.0", &gamma(&[t], 6)));
            lin(f, "timenet.2", &h)
        }
        Variant::Real => gamma(&[t], 10),
    }
}

fn scalar_cfc(f: &TensorFile, c: &FieldConfig, x: &[f64], t: f64) -> Vec<f64> {
    let FieldConfig::Cfc(c) = c else {
        panic!("not a CfC configuration")
    };
    let mut u = gamma(x, 10);
    u.extend(time_feature(f, c.variant, t));
    let mut h = vec![0.0; c.width];
    for l in 0..c.depth {
        if l == c.depth / 2 {
            for (hv, s) in h.iter_mut().zip(lin(f, "skip", &u)) {
                *hv += s;
            }
        }
        let mut z: Vec<f64> = u.iter().chain(h.iter()).copied().collect();
        for j in 0..c.backbone_layers {
            let name = format!("cells.{l}.backbone.{}", 2 * j);
            let pre = lin(f, &name, &z);
            z = if c.activation == Activation::Relu {
                relu_probe(&name, &pre)
            } else {
                pre.iter().map(|&v| c.activation.apply(v)).collect()
            };
        }
        let ff1 = lin(f, &format!("cells.{l}.ff1"), &z);
        let ff2 = lin(f, &format!("cells.{l}.ff2"), &z);
        let ta = lin(f, &format!("cells.{l}.time_a"), &z);
        let tb = lin(f, &format!("cells.{l}.time_b"), &z);
        for j in 0..c.width {
            let s = 1.0 / (1.0 + libm::exp(-(ta[j] * t + tb[j])));
            h[j] = libm::tanh(ff1[j]) * (1.0 - s) + s * libm::tanh(ff2[j]);
        }
    }
    lin(f, "head", &h)
}

/// The MLP trunk's last hidden layer.
fn mlp_trunk(f: &TensorFile, c: &FieldConfig, x: &[f64], t: f64) -> Vec<f64> {
    let FieldConfig::Mlp(c) = c else {
        panic!("not an MLP configuration")
    };
    let mut input = gamma(x, 10);
    input.extend(time_feature(f, c.variant, t));
    let mut h = input.clone();
    for i in 0..c.depth {
        let name = format!("linear.{i}");
        h = relu_probe(&name, &lin(f, &name, &h));
        if i == c.depth / 2 {
            h = input.iter().chain(h.iter()).copied().collect();
        }
    }
    h
}

fn scalar_mlp(f: &TensorFile, c: &FieldConfig, x: &[f64], t: f64) -> Vec<f64> {
    let h = mlp_trunk(f, c, x, t);
    let mut out = if c.is_6dof() {
        let (w, v) = (lin(f, "branch_w", &h), lin(f, "branch_v", &h));
        se3_rodrigues(&w, &v, x).to_vec()
    } else {
        lin(f, "gaussian_warp", &h)
    };
    out.extend(lin(f, "gaussian_rotation", &h));
    out.extend(lin(f, "gaussian_scaling", &h));
    out
}

#[test]
fn forward_matches_scalar_reimplementation() {
    // More rows than two blocks of the products (48 rows), so that the
    // layers chained into a product's epilogue (heads, time network) run on
    // several blocks, including a partial one.
    let n = 100;
    for (cfg, scalar) in [
        (
            config(FieldKind::Cfc, Variant::Synthetic, 3, 8, Activation::Gelu),
            scalar_cfc as fn(&_, &_, &_, _) -> _,
        ),
        (
            config(FieldKind::Cfc, Variant::Real, 4, 8, Activation::LecunTanh),
            scalar_cfc,
        ),
        (
            config(FieldKind::Cfc, Variant::Real, 1, 8, Activation::Gelu),
            scalar_cfc,
        ),
        (
            config(FieldKind::Mlp, Variant::Synthetic, 5, 8, Activation::Relu),
            scalar_mlp,
        ),
        (
            config(FieldKind::Mlp, Variant::Real, 4, 8, Activation::Relu),
            scalar_mlp,
        ),
        (six_dof(Variant::Synthetic, 4), scalar_mlp),
    ] {
        let field = Field::<f64>::new(cfg, 3).unwrap();
        let file = liquid_splat::oracle::field::field_to_tensor_file(&field);
        let (xyz, t) = inputs(4, n);
        let (d, _) = field.forward(&xyz, &t).unwrap();
        for i in 0..n {
            let want = scalar(&file, &cfg, &xyz[3 * i..3 * i + 3], t[i]);
            let got: Vec<f64> = d.d_xyz[3 * i..3 * i + 3]
                .iter()
                .chain(&d.d_rotation[4 * i..4 * i + 4])
                .chain(&d.d_scaling[3 * i..3 * i + 3])
                .copied()
                .collect();
            for (a, b) in got.iter().zip(&want) {
                assert!(
                    abs_diff_eq!(a, b, epsilon = 1e-12 * b.abs().max(1.0)),
                    "{cfg:?}: {got:?} vs {want:?}"
                );
            }
        }
    }
}

// ---- determinism, files, oracle ----

/// The same bits whichever instruction set the matrix and element-wise
/// kernels run on (AVX-512, AVX2, baseline SSE2), for every activation's
/// f32 transcendental functions (exp, erf, tanh, sigmoid).
#[test]
fn fields_are_bit_identical_across_cpu_paths() {
    let _isa = liquid_splat::kernels::fastmath::isa_test_lock();
    use liquid_splat::kernels::fastmath::{force_isa, Isa};
    let n = 700;
    for cfg in [
        config(FieldKind::Cfc, Variant::Synthetic, 3, 16, Activation::Gelu),
        // One cell: the skip is added before it (its state is read).
        config(FieldKind::Cfc, Variant::Synthetic, 1, 16, Activation::Gelu),
        config(FieldKind::Cfc, Variant::Real, 2, 16, Activation::Silu),
        config(FieldKind::Cfc, Variant::Real, 2, 16, Activation::LecunTanh),
        config(FieldKind::Cfc, Variant::Real, 2, 16, Activation::Tanh),
        config(FieldKind::Mlp, Variant::Synthetic, 4, 16, Activation::Relu),
        six_dof(Variant::Real, 3),
    ] {
        let field = Field::<f32>::new(cfg, 9).unwrap();
        let mut r = Rng::new(2);
        let mut draw = |k: usize, lo: f64, hi: f64| -> Vec<f32> {
            (0..k).map(|_| r.uniform_range(lo, hi) as f32).collect()
        };
        let xyz = draw(3 * n, -1.5, 1.5);
        let random = draw(n, 0.0, 1.0);
        let g = Deformation {
            d_xyz: draw(3 * n, -1.0, 1.0),
            d_rotation: draw(4 * n, -1.0, 1.0),
            d_scaling: draw(3 * n, -1.0, 1.0),
        };
        // Random times, and one time for every row (as in training).
        for t in [random, vec![0.45; n]] {
            let run = || forward_backward_bits(&field, &xyz, &t, &g);
            assert!(force_isa(Some(Isa::Baseline)));
            let base = run();
            for isa in [Isa::Avx2, Isa::Avx512] {
                if force_isa(Some(isa)) {
                    assert_eq!(base, run(), "{cfg:?} on {isa:?}");
                } else {
                    eprintln!("{isa:?} not supported here: not compared");
                }
            }
            force_isa(None);
            assert_eq!(base, run(), "{cfg:?}");
        }
    }
}

/// An output gradient for `n` Gaussians, uniform in [-1, 1], drawn from `r`.
fn random_cotangent(r: &mut Rng, n: usize) -> Deformation<f32> {
    let mut draw =
        |k: usize| -> Vec<f32> { (0..k).map(|_| r.uniform_range(-1.0, 1.0) as f32).collect() };
    Deformation {
        d_xyz: draw(3 * n),
        d_rotation: draw(4 * n),
        d_scaling: draw(3 * n),
    }
}

/// A Gaussian's deformation and its gradient with respect to its time are
/// the same bits whatever the other rows of the batch: the CfC field merges
/// its time heads per run of equal τ, with one merged layer per τ, and both
/// fields' timenet runs once per run of equal t, so rows alone, rows in runs
/// (crossing the CfC forward's 96-row blocks and the backward's 512-row
/// chunks), and rows whose τ equals or differs from the first row's all give
/// the same values, for the CfC and the MLP field.
#[test]
fn rows_do_not_depend_on_the_batch() {
    for cfg in [
        config(FieldKind::Cfc, Variant::Synthetic, 3, 16, Activation::Gelu),
        config(FieldKind::Mlp, Variant::Synthetic, 4, 16, Activation::Relu),
    ] {
        rows_do_not_depend_on_the_batch_for(cfg);
    }
}

fn rows_do_not_depend_on_the_batch_for(cfg: FieldConfig) {
    let n = 700;
    let field = Field::<f32>::new(cfg, 4).unwrap();
    let mut r = Rng::new(8);
    let xyz: Vec<f32> = (0..3 * n)
        .map(|_| r.uniform_range(-1.0, 1.0) as f32)
        .collect();
    let g = random_cotangent(&mut r, n);
    let row = |d: &Deformation<f32>, i: usize| -> Vec<u32> {
        d.d_xyz[3 * i..3 * i + 3]
            .iter()
            .chain(&d.d_rotation[4 * i..4 * i + 4])
            .chain(&d.d_scaling[3 * i..3 * i + 3])
            .map(|v| v.to_bits())
            .collect()
    };
    let uniform = vec![0.3f32; n];
    // Runs of 1 to 90 rows, times from a few values (0.3 is the first's).
    let mut runs = Vec::with_capacity(n);
    let values = [0.3f32, 0.55, 0.3, 0.8, 0.05, 0.55];
    let mut k = 0;
    while runs.len() < n {
        let len = 1 + (k * 37) % 90;
        runs.extend(std::iter::repeat_n(
            values[k % values.len()],
            len.min(n - runs.len()),
        ));
        k += 1;
    }
    for t in [uniform, runs] {
        let (d, cache) = field.forward(&xyz, &t).unwrap();
        let gt = field.backward(&cache, &g).unwrap().t;
        for i in (0..n).step_by(23).chain([n - 1]) {
            let one = |v: &[f32], w: usize| v[w * i..w * (i + 1)].to_vec();
            let (d1, c1) = field.forward(&one(&xyz, 3), &[t[i]]).unwrap();
            assert_eq!(row(&d, i), row(&d1, 0), "row {i}, τ {}", t[i]);
            let g1 = Deformation {
                d_xyz: one(&g.d_xyz, 3),
                d_rotation: one(&g.d_rotation, 4),
                d_scaling: one(&g.d_scaling, 3),
            };
            let gt1 = field.backward(&c1, &g1).unwrap().t;
            assert_eq!(gt[i].to_bits(), gt1[0].to_bits(), "row {i}, τ {}", t[i]);
        }
    }
}

#[test]
fn fields_are_bit_identical_across_thread_counts() {
    let n = 1100; // more than two reduction chunks of 512 rows
    for cfg in [
        config(FieldKind::Cfc, Variant::Synthetic, 3, 16, Activation::Gelu),
        config(FieldKind::Mlp, Variant::Synthetic, 4, 16, Activation::Relu),
        six_dof(Variant::Synthetic, 4),
    ] {
        let field = Field::<f32>::new(cfg, 9).unwrap();
        let mut r = Rng::new(1);
        let xyz: Vec<f32> = (0..3 * n)
            .map(|_| r.uniform_range(-1.0, 1.0) as f32)
            .collect();
        let random: Vec<f32> = (0..n).map(|_| r.uniform() as f32).collect();
        let g = random_cotangent(&mut r, n);
        // Random times, and one time for every row (as in training).
        for t in [random, vec![0.45; n]] {
            let run = |threads: usize| {
                support::with_threads(threads, || forward_backward_bits(&field, &xyz, &t, &g))
            };
            let one = run(1);
            assert_eq!(one, run(2), "{cfg:?}");
            assert_eq!(one, run(3), "{cfg:?}");
        }
    }
}

#[test]
fn weight_file_round_trip_and_errors() {
    let cfg = config(FieldKind::Cfc, Variant::Synthetic, 2, 8, Activation::Gelu);
    let field = Field::<f32>::new(cfg, 1).unwrap();
    let bytes = liquid_splat::oracle::field::field_to_tensor_file(&field)
        .to_bytes()
        .unwrap();
    let file = TensorFile::from_bytes(std::path::Path::new("w.safetensors"), &bytes).unwrap();
    assert_eq!(
        liquid_splat::oracle::field::config_from_meta(&file).unwrap(),
        cfg
    );
    let back = liquid_splat::oracle::field::field_from_tensor_file::<f32>(cfg, &file).unwrap();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(back.params()), bits(field.params()));
    assert_eq!(back.layout(), field.layout());

    let mut missing = file.clone();
    missing.tensors.remove("cells.1.time_b.bias");
    let e = liquid_splat::oracle::field::field_from_tensor_file::<f32>(cfg, &missing)
        .unwrap_err()
        .to_string();
    assert!(e.contains("cells.1.time_b.bias"), "{e}");

    let mut extra = file.clone();
    extra.insert_real::<f32>("cells.2.ff1.weight", vec![1], &[0.0]);
    let e = liquid_splat::oracle::field::field_from_tensor_file::<f32>(cfg, &extra)
        .unwrap_err()
        .to_string();
    assert!(e.contains("cells.2.ff1.weight"), "{e}");

    let mut bad = file.clone();
    bad.insert_real::<f32>("skip.weight", vec![93, 8], &[0.0; 93 * 8]);
    let e = liquid_splat::oracle::field::field_from_tensor_file::<f32>(cfg, &bad)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("skip.weight") && e.contains("[8,93]") && e.contains("[93,8]"),
        "{e}"
    );

    let e = liquid_splat::oracle::field::field_from_tensor_file::<f64>(cfg, &file)
        .unwrap_err()
        .to_string();
    assert!(e.contains("F64"), "{e}");
}

#[test]
fn state_dict_names_and_order() {
    let field = Field::<f32>::new(FieldConfig::new(FieldKind::Mlp), 0).unwrap();
    let names: Vec<&str> = field.layout().iter().map(|s| s.name.as_str()).collect();
    assert_eq!(
        &names[..4],
        &[
            "timenet.0.weight",
            "timenet.0.bias",
            "timenet.2.weight",
            "timenet.2.bias"
        ]
    );
    assert_eq!(names[4], "linear.0.weight");
    assert_eq!(field.layout()[4 + 2 * 5].shape, vec![256, 256 + 93]); // linear.5
    assert_eq!(
        &names[names.len() - 6..],
        &[
            "gaussian_warp.weight",
            "gaussian_warp.bias",
            "gaussian_rotation.weight",
            "gaussian_rotation.bias",
            "gaussian_scaling.weight",
            "gaussian_scaling.bias"
        ]
    );
    assert_eq!(field.param_count(), 522_280);
    let cfc = Field::<f32>::new(FieldConfig::new(FieldKind::Cfc), 0).unwrap();
    assert_eq!(cfc.param_count(), 334_504);
    let names: Vec<&str> = cfc.layout().iter().map(|s| s.name.as_str()).collect();
    assert_eq!(
        &names[4..16],
        &[
            "cells.0.backbone.0.weight",
            "cells.0.backbone.0.bias",
            "cells.0.backbone.2.weight",
            "cells.0.backbone.2.bias",
            "cells.0.ff1.weight",
            "cells.0.ff1.bias",
            "cells.0.ff2.weight",
            "cells.0.ff2.bias",
            "cells.0.time_a.weight",
            "cells.0.time_a.bias",
            "cells.0.time_b.weight",
            "cells.0.time_b.bias"
        ]
    );
    assert_eq!(
        &names[names.len() - 4..],
        &["skip.weight", "skip.bias", "head.weight", "head.bias"]
    );
    // Offsets are contiguous.
    let mut off = 0;
    for s in cfc.layout() {
        assert_eq!(s.offset, off);
        off += s.len();
    }
    assert_eq!(off, cfc.params().len());
}

#[test]
fn initialisation_bounds_follow_the_decisions() {
    let cfg = config(FieldKind::Cfc, Variant::Synthetic, 2, 8, Activation::Gelu);
    let f = Field::<f64>::new(cfg, 2).unwrap();
    for s in f.layout() {
        let fan_in = *s.shape.last().unwrap() as f64;
        let (out, inn) = (s.shape[0] as f64, fan_in);
        let bound = if s.name.starts_with("cells.") && s.name.ends_with(".weight") {
            (6.0 / (inn + out)).sqrt()
        } else if s.name.ends_with(".bias") {
            let w = f
                .layout()
                .iter()
                .find(|w| w.name == s.name.replace(".bias", ".weight"))
                .unwrap();
            1.0 / (w.shape[1] as f64).sqrt()
        } else {
            1.0 / fan_in.sqrt()
        };
        let v = &f.params()[s.range()];
        let max = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(max <= bound, "{}: {max} > {bound}", s.name);
        if v.len() >= 50 {
            assert!(max > 0.8 * bound, "{}: {max} vs {bound}", s.name);
        }
    }
    // Same seed, same weights; different seed, different weights.
    assert_eq!(Field::<f64>::new(cfg, 2).unwrap().params(), f.params());
    assert_ne!(Field::<f64>::new(cfg, 3).unwrap().params(), f.params());
}

#[test]
fn bad_inputs_are_errors() {
    let f = Field::<f32>::new(FieldConfig::new(FieldKind::Cfc), 0).unwrap();
    assert!(f.forward(&[0.0; 5], &[0.0; 2]).is_err());
    let (_, c) = f.forward(&[0.0; 6], &[0.0; 2]).unwrap();
    assert!(f.backward(&c, &Deformation::zeros(3)).is_err());
    let mut cfg = MlpConfig::paper();
    cfg.depth = 2;
    assert!(Field::<f32>::new(cfg.into(), 0)
        .unwrap_err()
        .to_string()
        .contains("depth"));
    cfg.depth = 8;
    cfg.is_6dof = true;
    assert!(Field::<f32>::new(cfg.into(), 0).is_ok());
    // A 6-DoF CfC field cannot be written down: `CfcConfig` has no such
    // option; a CfC field with no cell is refused.
    let cfc = CfcConfig {
        depth: 0,
        ..CfcConfig::paper()
    };
    assert!(Field::<f32>::new(cfc.into(), 0)
        .unwrap_err()
        .to_string()
        .contains("depth"));
}

#[test]
fn oracle_stage_matches_direct_calls() {
    for cfg in [
        config(FieldKind::Cfc, Variant::Synthetic, 3, 8, Activation::Silu),
        config(FieldKind::Mlp, Variant::Real, 3, 8, Activation::Relu),
        six_dof(Variant::Synthetic, 3),
    ] {
        let field = Field::<f64>::new(cfg, 4).unwrap();
        let n = 6;
        let (xyz, t) = inputs(8, n);
        let g = Deformation {
            d_xyz: cotangent(1, 3 * n),
            d_rotation: cotangent(2, 4 * n),
            d_scaling: cotangent(3, 3 * n),
        };
        let mut case = liquid_splat::oracle::field::field_to_tensor_file(&field);
        case.set_meta("stage", "deform");
        case.insert_real("xyz", vec![n, 3], &xyz);
        case.insert_real("t", vec![n, 1], &t);
        case.insert_real("grad_d_xyz", vec![n, 3], &g.d_xyz);
        case.insert_real("grad_d_rotation", vec![n, 4], &g.d_rotation);
        case.insert_real("grad_d_scaling", vec![n, 3], &g.d_scaling);
        let out = liquid_splat::oracle::deform::run(&case).unwrap();
        let (d, c) = field.forward(&xyz, &t).unwrap();
        let fg = field.backward(&c, &g).unwrap();
        assert_eq!(out.get_real::<f64>("d_xyz", &[n, 3]).unwrap(), d.d_xyz);
        assert_eq!(
            out.get_real::<f64>("d_rotation", &[n, 4]).unwrap(),
            d.d_rotation
        );
        assert_eq!(
            out.get_real::<f64>("d_scaling", &[n, 3]).unwrap(),
            d.d_scaling
        );
        assert_eq!(out.get_real::<f64>("grad_t", &[n, 1]).unwrap(), fg.t);
        if cfg.is_6dof() {
            assert_eq!(out.get_real::<f64>("grad_xyz", &[n, 3]).unwrap(), fg.xyz);
            // The transform moves x to x + d_xyz (to rounding).
            let m = out.get_real::<f64>("d_xyz_se3", &[n, 4, 4]).unwrap();
            for i in 0..n {
                let mi = &m[16 * i..16 * i + 16];
                assert_eq!(&mi[12..], &[0.0, 0.0, 0.0, 1.0]);
                for r in 0..3 {
                    let moved = mi[4 * r] * xyz[3 * i]
                        + mi[4 * r + 1] * xyz[3 * i + 1]
                        + mi[4 * r + 2] * xyz[3 * i + 2]
                        + mi[4 * r + 3];
                    let want = xyz[3 * i + r] + d.d_xyz[3 * i + r];
                    assert!((moved - want).abs() < 1e-12, "{moved} vs {want}");
                }
            }
        } else {
            assert!(out.get_real::<f64>("grad_xyz", &[n, 3]).is_err());
        }
        for s in field.layout() {
            assert_eq!(
                out.get_real::<f64>(&format!("grad.{}", s.name), &s.shape)
                    .unwrap(),
                fg.params[s.range()].to_vec()
            );
        }
        // A wrong stage and a misshaped input are errors naming the problem.
        let mut wrong = case.clone();
        wrong.set_meta("stage", "rasterize");
        assert!(liquid_splat::oracle::deform::run(&wrong)
            .unwrap_err()
            .to_string()
            .contains("stage"));
        let mut bad = case.clone();
        bad.insert_real("t", vec![n], &t);
        assert!(liquid_splat::oracle::deform::run(&bad)
            .unwrap_err()
            .to_string()
            .contains("`t`"));
    }
}

type Bits = (Vec<u32>, Vec<u32>, Vec<u32>, Vec<u32>, Vec<u32>, Vec<u32>);

/// The bits of a field's outputs and of every gradient of its backward.
fn forward_backward_bits(field: &Field<f32>, xyz: &[f32], t: &[f32], g: &Deformation<f32>) -> Bits {
    let (d, c) = field.forward(xyz, t).unwrap();
    let fg = field.backward(&c, g).unwrap();
    let (gp, gt, gx) = (fg.params, fg.t, fg.xyz);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    (
        bits(&d.d_xyz),
        bits(&d.d_rotation),
        bits(&d.d_scaling),
        bits(&gp),
        bits(&gt),
        bits(&gx),
    )
}
