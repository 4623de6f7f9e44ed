//! Oracle stage `step` (one training iteration): gradients against central
//! finite differences of the `loss` output, the Adam update and the
//! statistics against hand computations, thread-count bit-identity, and
//! malformed cases.

mod support;

use liquid_splat::io::{Tensor, TensorFile};
use liquid_splat::math::gradcheck::{compare, numeric_gradient};
use liquid_splat::math::Precision;
use liquid_splat::oracle::new::{new_case, CaseSpec};
use liquid_splat::oracle::run_case;

fn case(precision: Precision, seed: u64) -> TensorFile {
    let mut spec = CaseSpec::new("step");
    spec.precision = precision;
    spec.seed = seed;
    spec.count = 6;
    new_case(&spec).unwrap()
}

fn f64s(f: &TensorFile, name: &str) -> Vec<f64> {
    f.tensors[name].to_f64().iter().copied().collect()
}

fn i32s(f: &TensorFile, name: &str) -> Vec<i32> {
    f.i32_array(name).unwrap().iter().copied().collect()
}

fn set(f: &mut TensorFile, name: &str, i: usize, v: f64) {
    match f.tensors.get_mut(name).unwrap() {
        Tensor::F64(x) => *x.iter_mut().nth(i).unwrap() = v,
        _ => panic!("{name} is not F64"),
    }
}

fn loss(f: &TensorFile) -> f64 {
    run_case(f).unwrap().get_real::<f64>("loss", &[]).unwrap()[0]
}

/// Check `grad.<name>` at `indices` against central differences of `loss`.
fn check(c: &TensorFile, out: &TensorFile, name: &str, indices: &[usize]) {
    let analytic_all = f64s(out, &format!("grad.{name}"));
    let floor = 1e-3 * analytic_all.iter().fold(0.0f64, |a, &g| a.max(g.abs()));
    assert!(floor > 0.0, "grad.{name} is all zero");
    let mut analytic = vec![];
    let mut numeric = vec![];
    for &i in indices {
        let mut x = vec![f64s(c, name)[i]];
        let mut probe = c.clone();
        let g = numeric_gradient(&mut x, 1e-6, |x| {
            set(&mut probe, name, i, x[0]);
            loss(&probe)
        });
        analytic.push(analytic_all[i]);
        numeric.push(g[0]);
    }
    let r = compare(name, &analytic, &numeric, floor);
    eprintln!("{r}");
    assert!(r.passes(1e-5), "{r}");
}

/// Indices of the first `k` rows of width `w` belonging to visible Gaussians,
/// column `col`.
fn visible(out: &TensorFile, w: usize, col: usize, k: usize) -> Vec<usize> {
    let radii = i32s(out, "radii");
    radii
        .iter()
        .enumerate()
        .filter(|(_, &r)| r > 0)
        .take(k)
        .map(|(i, _)| i * w + col)
        .collect()
}

#[test]
fn gradients_match_finite_differences_of_the_loss() {
    let c = case(Precision::F64, 3);
    let out = run_case(&c).unwrap();
    assert!(
        visible(&out, 1, 0, 16).len() >= 4,
        "too few visible Gaussians"
    );
    // sh coefficient 0 (f_dc) and 3 (degree 1) of channel 1, K = 16.
    let sh: Vec<usize> = visible(&out, 48, 1, 3)
        .into_iter()
        .flat_map(|i| [i, i + 9])
        .collect();
    check(&c, &out, "sh", &sh);
    check(&c, &out, "scaling", &visible(&out, 3, 2, 4));
    check(&c, &out, "rotation", &visible(&out, 4, 1, 4));
    check(&c, &out, "opacity", &visible(&out, 1, 0, 4));
    for (name, idx) in [
        ("head.weight", vec![0, 17, 45, 150]),
        ("head.bias", vec![0, 4, 9]),
        ("cells.0.ff1.weight", vec![3, 40]),
        ("cells.1.time_a.bias", vec![2, 11]),
        ("skip.weight", vec![5, 600]),
    ] {
        check(&c, &out, name, &idx);
    }
    // The field's position input is detached (upstream), so grad.xyz is the
    // total derivative only with the field off.
    let mut off = c.clone();
    off.set_meta("field_on", "false");
    let out_off = run_case(&off).unwrap();
    check(&off, &out_off, "xyz", &visible(&out_off, 3, 0, 4));
    check(&off, &out_off, "xyz", &visible(&out_off, 3, 2, 2));
}

/// Adam, written out for one element (torch 1.13 formula, betas 0.9/0.999,
/// eps 1e-15): the returned parameter, m, v.
fn adam(p: f64, g: f64, m: f64, v: f64, step: u64, lr: f64) -> (f64, f64, f64) {
    let t = step as i32 + 1;
    let m = 0.9 * m + 0.1 * g;
    let v = 0.999 * v + 0.001 * g * g;
    let bc1 = 1.0 - 0.9f64.powi(t);
    let bc2 = 1.0 - 0.999f64.powi(t);
    (p - lr / bc1 * m / (v.sqrt() / bc2.sqrt() + 1e-15), m, v)
}

#[test]
fn adam_update_and_statistics_match_hand_computation() {
    let mut c = case(Precision::F64, 4);
    // Gaussian 0 behind the camera (at (0.2, -0.3, -4) looking at +z): culled.
    for (k, v) in [0.2, -0.3, -6.0].into_iter().enumerate() {
        set(&mut c, "xyz", k, v);
    }
    let out = run_case(&c).unwrap();
    let lr = |k: &str| -> f64 { c.meta_parse(&format!("lr.{k}")).unwrap() };
    // (tensor, Adam group, rate, elements): sh 0..3 is f_dc, 3.. f_rest.
    for (name, group, rate, elements) in [
        ("xyz", "xyz", lr("xyz"), vec![4, 7]),
        ("sh", "sh", lr("f_dc"), vec![1, 50]),
        ("sh", "sh", lr("f_rest"), vec![4, 47, 60]),
        ("opacity", "opacity", lr("opacity"), vec![2]),
        ("rotation", "rotation", lr("rotation"), vec![5]),
        ("head.weight", "field", lr("field"), vec![3]),
    ] {
        let step: u64 = c.meta_parse(&format!("adam.{group}.step")).unwrap();
        assert_eq!(
            out.meta_parse::<u64>(&format!("new.adam.{group}.step"))
                .unwrap(),
            step + 1
        );
        // Field state is flat in layout order; find the weight's offset.
        let offset = if group == "field" {
            let spec = liquid_splat::oracle::field::field_from_tensor_file::<f64>(
                liquid_splat::oracle::field::config_from_meta(&c).unwrap(),
                &field_weights(&c),
            )
            .unwrap();
            spec.layout()
                .iter()
                .find(|s| s.name == name)
                .unwrap()
                .offset
        } else {
            0
        };
        let (p, g) = (f64s(&c, name), f64s(&out, &format!("grad.{name}")));
        let (m, v) = (
            f64s(&c, &format!("adam.{group}.m")),
            f64s(&c, &format!("adam.{group}.v")),
        );
        let new = f64s(&out, &format!("new.{name}"));
        let (nm, nv) = (
            f64s(&out, &format!("new.adam.{group}.m")),
            f64s(&out, &format!("new.adam.{group}.v")),
        );
        for i in elements {
            let j = offset + i;
            let (wp, wm, wv) = adam(p[i], g[i], m[j], v[j], step, rate);
            assert!(
                (new[i] - wp).abs() <= 1e-15 * p[i].abs() + 1e-12 * (wp - p[i]).abs(),
                "{name}[{i}]: {} vs {wp}",
                new[i]
            );
            assert!(new[i] != p[i], "{name}[{i}] did not move");
            assert!((nm[j] - wm).abs() <= 1e-15 * wm.abs(), "{group}.m[{j}]");
            assert!((nv[j] - wv).abs() <= 1e-15 * wv.abs(), "{group}.v[{j}]");
        }
    }
    // f_dc and f_rest rates differ, so the SH rate really is per coefficient.
    assert_ne!(lr("f_dc"), lr("f_rest"));

    // Statistics: visible Gaussians add the NDC gradient norm.
    let radii = i32s(&out, "radii");
    let g2 = f64s(&out, "grad_means2d");
    let (acc0, acc1) = (f64s(&c, "stats.accum"), f64s(&out, "stats.accum"));
    let den0 = i32s(&c, "stats.denom");
    let den1 = i32s(&out, "stats.denom");
    let mr0 = i32s(&c, "stats.max_radii");
    let mr1 = i32s(&out, "stats.max_radii");
    assert_eq!(radii[0], 0);
    assert!(radii.iter().any(|&r| r > 0));
    for i in 0..radii.len() {
        let vis = radii[i] > 0;
        let norm = (g2[3 * i] * g2[3 * i] + g2[3 * i + 1] * g2[3 * i + 1]).sqrt();
        let want = if vis { acc0[i] + norm } else { acc0[i] };
        assert_eq!(acc1[i], want, "accum[{i}]");
        assert_eq!(den1[i], den0[i] + vis as i32, "denom[{i}]");
        assert_eq!(mr1[i], if vis { mr0[i].max(radii[i]) } else { mr0[i] });
    }
}

fn field_weights(c: &TensorFile) -> TensorFile {
    let mut w = TensorFile::new("weights");
    for (name, t) in &c.tensors {
        let other = ["xyz", "sh", "scaling", "rotation", "opacity", "bg", "gt"]
            .contains(&name.as_str())
            || ["viewmatrix", "projmatrix", "campos"].contains(&name.as_str())
            || name.starts_with("adam.")
            || name.starts_with("stats.");
        if !other {
            w.tensors.insert(name.clone(), t.clone());
        }
    }
    w
}

#[test]
fn field_off_leaves_the_field_and_its_state_alone() {
    let mut c = case(Precision::F64, 5);
    c.set_meta("field_on", "false");
    let out = run_case(&c).unwrap();
    assert!(!out.contains("grad.head.weight"));
    assert_eq!(f64s(&out, "new.head.weight"), f64s(&c, "head.weight"));
    assert_eq!(
        f64s(&out, "new.adam.field.m"),
        f64s(&c, "adam.field.m"),
        "no gradient, no Adam step (torch skips .grad = None)"
    );
    assert_eq!(out.meta("new.adam.field.step").unwrap(), "7");
    assert_eq!(out.meta("new.adam.xyz.step").unwrap(), "8");
    // Absent optimizer state and statistics are zeros at step 0.
    let mut bare = case(Precision::F64, 5);
    bare.tensors
        .retain(|k, _| !k.starts_with("adam.") && !k.starts_with("stats."));
    bare.metadata.retain(|k, _| !k.starts_with("adam."));
    let out = run_case(&bare).unwrap();
    assert_eq!(out.meta("new.adam.sh.step").unwrap(), "1");
    let denom = i32s(&out, "stats.denom");
    let radii = i32s(&out, "radii");
    let vis: Vec<i32> = radii.iter().map(|&r| (r > 0) as i32).collect();
    assert_eq!(denom, vis);
}

#[test]
fn same_bits_for_one_and_three_threads() {
    for precision in [Precision::F32, Precision::F64] {
        let c = case(precision, 6);
        let run =
            |threads| support::with_threads(threads, || run_case(&c).unwrap().to_bytes().unwrap());
        assert!(run(1) == run(3), "{precision}");
    }
}

#[test]
fn malformed_cases_are_errors_naming_the_problem() {
    let base = case(Precision::F32, 7);
    let n = base.shape("xyz").unwrap()[0];
    type Edit = Box<dyn Fn(&mut TensorFile)>;
    let cases: Vec<(&str, Edit)> = vec![
        (
            "xyz",
            Box::new(|c| {
                c.tensors.remove("xyz");
            }),
        ),
        (
            "sh",
            Box::new(move |c| c.insert_real("sh", vec![n, 5, 3], &vec![0f32; n * 15])),
        ),
        (
            "opacity",
            Box::new(move |c| c.insert_real("opacity", vec![n], &vec![0f32; n])),
        ),
        (
            "rotation",
            Box::new(move |c| c.insert_real("rotation", vec![n, 3], &vec![0f32; 3 * n])),
        ),
        (
            "gt",
            Box::new(|c| c.insert_real("gt", vec![3, 16, 15], &[0f32; 720])),
        ),
        (
            "bg",
            Box::new(|c| {
                c.tensors.remove("bg");
            }),
        ),
        (
            "viewmatrix",
            Box::new(|c| c.insert_real("viewmatrix", vec![3, 4], &[0f32; 12])),
        ),
        (
            "adam.xyz.v",
            Box::new(|c| {
                c.tensors.remove("adam.xyz.v");
            }),
        ),
        (
            "adam.sh.m",
            Box::new(|c| c.insert_real("adam.sh.m", vec![2], &[0f32; 2])),
        ),
        (
            "adam.opacity.v",
            Box::new(move |c| c.insert_real("adam.opacity.v", vec![n, 1], &vec![-1f32; n])),
        ),
        (
            "stats.denom",
            Box::new(move |c| c.insert_real("stats.denom", vec![n], &vec![0f32; n])),
        ),
        (
            "stats.max_radii",
            Box::new(move |c| c.insert_i32("stats.max_radii", vec![n], vec![-1; n])),
        ),
        (
            "head.weight",
            Box::new(|c| {
                c.tensors.remove("head.weight");
            }),
        ),
        (
            "head.wieght",
            Box::new(|c| c.insert_real("head.wieght", vec![1], &[0f32])),
        ),
        (
            "F64",
            Box::new(|c| c.insert_real("bg", vec![3], &[0f64; 3])),
        ),
        (
            "active_sh_degree",
            Box::new(|c| c.set_meta("active_sh_degree", 4)),
        ),
        ("lr.xyz", Box::new(|c| c.set_meta("lr.xyz", "-1e-3"))),
        (
            "lambda_dssim",
            Box::new(|c| c.set_meta("lambda_dssim", "1.5")),
        ),
        (
            "time",
            Box::new(|c| {
                c.metadata.remove("time");
            }),
        ),
        ("field_on", Box::new(|c| c.set_meta("field_on", "maybe"))),
        (
            "adam.xyz.step",
            Box::new(|c| c.set_meta("adam.xyz.step", "-2")),
        ),
        ("stage", Box::new(|c| c.set_meta("stage", "steps"))),
    ];
    for (what, edit) in cases {
        let mut c = base.clone();
        edit(&mut c);
        let err = run_case(&c).expect_err(what).to_string();
        assert!(err.contains(what), "{what}: {err}");
    }
    assert!(run_case(&base).is_ok());
}

/// The published f32 tolerances for the step outputs are tight enough to
/// catch a 1% error in one gradient or moment tensor of the golden case.
#[test]
fn f32_tolerances_catch_a_one_percent_error() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/cases");
    let tol = liquid_splat::oracle::Tolerances::load(&dir.join("tolerances_f32.json")).unwrap();
    let expected = TensorFile::load(&dir.join("step_f32.expected.safetensors")).unwrap();
    assert!(
        liquid_splat::oracle::compare(&expected, &expected, &tol)
            .unwrap()
            .passed
    );
    for name in [
        "grad.xyz",
        "grad.sh",
        "grad.rotation",
        "grad_means2d",
        "stats.accum",
        "new.adam.xyz.m",
        "new.adam.sh.v",
    ] {
        let mut actual = expected.clone();
        match actual.tensors.get_mut(name).unwrap() {
            Tensor::F32(v) => v.iter_mut().for_each(|x| *x *= 1.01),
            _ => panic!("{name}"),
        }
        let report = liquid_splat::oracle::compare(&expected, &actual, &tol).unwrap();
        assert!(!report.passed, "{name}: {report}");
    }
}
