use super::*;
use std::path::Path;

fn file(name: &str, tensors: &[(&str, Tensor)]) -> TensorFile {
    let mut f = TensorFile::new(name);
    for (n, t) in tensors {
        f.tensors.insert(n.to_string(), t.clone());
    }
    f
}

fn f32t(shape: &[usize], v: &[f32]) -> Tensor {
    Tensor::real::<f32>(shape.to_vec(), v)
}

fn f64t(shape: &[usize], v: &[f64]) -> Tensor {
    Tensor::real::<f64>(shape.to_vec(), v)
}

fn only(report: &CompareReport) -> &TensorReport {
    assert_eq!(report.tensors.len(), 1);
    &report.tensors[0]
}

#[test]
fn identical_files_pass_with_zero_error() {
    let t = f32t(&[2, 3], &[1.0, -2.0, 0.0, 3.5, 1e-30, -7.25]);
    let e = file(
        "e",
        &[
            ("color", t.clone()),
            ("radii", Tensor::i32(vec![2], vec![3, 0])),
        ],
    );
    let a = file(
        "a",
        &[("color", t), ("radii", Tensor::i32(vec![2], vec![3, 0]))],
    );
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    assert!(r.passed, "{r}");
    for t in &r.tensors {
        let s = t.stats.as_ref().unwrap();
        assert_eq!(s.max_abs_error, 0.0);
        assert_eq!(s.rel_l2, 0.0);
        assert_eq!(s.ulp_max, Some(0));
        assert_eq!(s.cosine, 1.0);
    }
}

#[test]
fn crafted_mismatch_fails_and_names_the_worst_element() {
    let ev = [1.0f64, 2.0, 3.0, 4.0, 5.0, 6.0];
    let mut av = ev;
    av[4] += 1e-3; // element [1,1] of a [2,3] tensor
    av[1] += 1e-9; // within tolerance
    let e = file("e", &[("grad_means3D", f64t(&[2, 3], &ev))]);
    let a = file("a", &[("grad_means3D", f64t(&[2, 3], &av))]);
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    assert!(!r.passed);
    let t = only(&r);
    assert_eq!(t.status, Status::Fail);
    let s = t.stats.as_ref().unwrap();
    assert_eq!(s.mismatches, 1);
    let w = s.worst.as_ref().unwrap();
    assert_eq!(w.index, vec![1, 1]);
    assert_eq!((w.expected, w.actual), (5.0, av[4]));
    assert_eq!(s.max_abs_error, av[4] - 5.0);
    // Independent values: relative error 1e-3/5, bias = (1e-3 + 1e-9)/6 up to rounding.
    assert!((s.max_rel_error - 2e-4).abs() < 1e-15);
    assert!((s.bias - (1e-3 + 1e-9) / 6.0).abs() < 1e-15);
    let norm_e = (1.0f64 + 4.0 + 9.0 + 16.0 + 25.0 + 36.0).sqrt();
    assert!(
        (s.rel_l2 - ((av[4] - 5.0).powi(2) + (av[1] - 2.0).powi(2)).sqrt() / norm_e).abs() < 1e-15
    );
    let text = r.to_string();
    assert!(text.contains("FAIL") && text.contains("[1, 1]"), "{text}");
}

#[test]
fn near_miss_within_tolerance_passes_and_just_outside_fails() {
    // f32 default: atol 1e-5, rtol 1.3e-6. For e = 1: allowance 1.13e-5.
    let e = file("e", &[("x", f32t(&[1], &[1.0]))]);
    let inside = file("a", &[("x", f32t(&[1], &[1.0 + 1.1e-5]))]);
    let outside = file("a", &[("x", f32t(&[1], &[1.0 + 1.2e-5]))]);
    let tol = Tolerances::default();
    assert!(compare(&e, &inside, &tol).unwrap().passed);
    assert!(!compare(&e, &outside, &tol).unwrap().passed);
    // The rule is asymmetric: scaled by |expected|, like torch.allclose.
    let t = Tolerance {
        atol: 0.0,
        rtol: 0.1,
        max_mismatch_fraction: 0.0,
        equal_nan: false,
    };
    assert!(t.matches(1.1, 1.0 + 1e-12));
    assert!(!t.matches(1.0, 0.9));
}

#[test]
fn ulp_distance_in_the_tensors_own_dtype() {
    let one = 1.0f32;
    let next = f32::from_bits(one.to_bits() + 3);
    let e = file("e", &[("x", f32t(&[3], &[one, -0.0, f32::from_bits(1)]))]);
    let a = file("a", &[("x", f32t(&[3], &[next, 0.0, -f32::from_bits(1)]))]);
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    let s = only(&r).stats.clone().unwrap();
    // 3 ulp; -0 vs +0 is 0 ulp; smallest subnormal vs its negative is 2 ulp.
    assert_eq!(s.ulp_max, Some(3));
    assert!((s.ulp_mean.unwrap() - 5.0 / 3.0).abs() < 1e-15);

    let e = file("e", &[("x", f64t(&[1], &[1.0]))]);
    let a = file(
        "a",
        &[("x", f64t(&[1], &[f64::from_bits(1.0f64.to_bits() - 2)]))],
    );
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    assert_eq!(only(&r).stats.as_ref().unwrap().ulp_max, Some(2));

    let e = file("e", &[("n", Tensor::i32(vec![3], vec![5, 7, -2]))]);
    let a = file("a", &[("n", Tensor::i32(vec![3], vec![5, 4, -3]))]);
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    let s = only(&r).stats.clone().unwrap();
    assert_eq!(s.ulp_max, Some(3));
    assert!((s.ulp_mean.unwrap() - 4.0 / 3.0).abs() < 1e-15);
    assert_eq!(s.mismatches, 2, "integers are exact by default");
}

#[test]
fn nan_matches_only_nan_and_only_with_equal_nan() {
    let e = file("e", &[("x", f32t(&[3], &[f32::NAN, 1.0, 2.0]))]);
    let a = file("a", &[("x", f32t(&[3], &[f32::NAN, 1.0, 2.0]))]);
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    assert!(!r.passed, "NaN != NaN without equal_nan");
    let s = only(&r).stats.clone().unwrap();
    assert_eq!((s.nan_expected, s.nan_actual, s.mismatches), (1, 1, 1));
    assert_eq!(s.worst.unwrap().index, vec![0]);

    let mut tol = Tolerances::default();
    tol.default.equal_nan = Some(true);
    assert!(compare(&e, &a, &tol).unwrap().passed);

    // NaN on one side only fails even with equal_nan, and ranks as worst.
    let a2 = file("a", &[("x", f32t(&[3], &[1.0, 1.0, 2.5]))]);
    let r = compare(&e, &a2, &tol).unwrap();
    let s = only(&r).stats.clone().unwrap();
    assert_eq!(s.mismatches, 2);
    assert_eq!(s.worst.unwrap().index, vec![0]);
    assert_eq!((s.nan_expected, s.nan_actual), (1, 0));
}

#[test]
fn infinities_match_only_themselves() {
    let e = file(
        "e",
        &[("x", f64t(&[3], &[f64::INFINITY, 1.0, f64::NEG_INFINITY]))],
    );
    let a = file("a", &[("x", f64t(&[3], &[f64::INFINITY, 1.0, 1e308]))]);
    let mut tol = Tolerances::default();
    tol.default.rtol = Some(1.0);
    let r = compare(&e, &a, &tol).unwrap();
    let s = only(&r).stats.clone().unwrap();
    assert_eq!((s.inf_expected, s.inf_actual, s.mismatches), (2, 1, 1));
    assert_eq!(s.max_abs_error, f64::INFINITY);
    assert!(r.to_json().contains("\"inf\""));
}

#[test]
fn shape_and_dtype_mismatches_fail_with_a_sentence() {
    let e = file("e", &[("means2D", f32t(&[2, 2], &[0.0; 4]))]);
    let a = file("a", &[("means2D", f32t(&[4], &[0.0; 4]))]);
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    let t = only(&r);
    assert_eq!(t.status, Status::Fail);
    assert!(t.stats.is_none());
    assert!(
        t.problems[0].contains("shape [4], expected [2,2]"),
        "{:?}",
        t.problems
    );

    let a = file("a", &[("means2D", f64t(&[2, 2], &[0.0; 4]))]);
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    let t = only(&r);
    assert_eq!(t.status, Status::Fail);
    assert!(
        t.problems[0].contains("dtype F64, expected F32"),
        "{:?}",
        t.problems
    );
    assert_eq!(t.stats.as_ref().unwrap().ulp_max, None);
}

#[test]
fn missing_tensor_fails_and_extra_is_only_listed() {
    let x = f32t(&[1], &[1.0]);
    let e = file("e", &[("a", x.clone()), ("b", x.clone())]);
    let a = file("a", &[("a", x.clone()), ("c", x.clone())]);
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    assert!(!r.passed);
    assert_eq!(r.missing, vec!["b".to_string()]);
    assert_eq!(r.extra, vec!["c".to_string()]);
    assert_eq!(r.failures(), 1);

    let e = file("e", &[("a", x.clone())]);
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    assert!(r.passed, "an extra tensor alone does not fail");
    assert_eq!(r.extra, vec!["c".to_string()]);
}

#[test]
fn tolerance_entries_that_apply_to_nothing_are_listed() {
    let x = f32t(&[1], &[1.0]);
    let e = file("e", &[("grad_means", x.clone()), ("radii", x.clone())]);
    let tol = Tolerances::from_json(
        Path::new("t.json"),
        r#"{"tensors": {"grad_*": {"rtol": 1e-3}, "grad_means": {"rtol": 1e-4},
            "*": {"rtol": 1e-2}, "radius": {"atol": 0}, "v_*": {"rtol": 1e-3}}}"#,
    )
    .unwrap();
    let r = compare(&e, &e, &tol).unwrap();
    assert!(r.passed, "unused entries do not fail a comparison");
    // "grad_*" is shadowed by the exact "grad_means"; "*" applies to radii; the
    // misspelt "radius" and "v_*" match nothing.
    assert_eq!(r.unused_tolerances, vec!["grad_*", "radius", "v_*"]);
    let text = r.to_string();
    assert!(
        text.contains("tolerance entries that apply to no tensor here: grad_*, radius, v_*"),
        "{text}"
    );
    assert!(r.to_json().contains("\"unused_tolerances\""));

    let r = compare(&e, &e, &Tolerances::default()).unwrap();
    assert!(r.unused_tolerances.is_empty());
    // An empty name is refused outright.
    let err = Tolerances::from_json(Path::new("t.json"), r#"{"tensors": {"": {"rtol": 1}}}"#)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("t.json") && err.contains("named \"\""),
        "{err}"
    );
    assert!(!r.to_string().contains("tolerance entries"));
}

#[test]
fn mismatch_fraction_allows_a_small_band() {
    let ev: Vec<f32> = (0..100).map(|i| i as f32).collect();
    let mut av = ev.clone();
    av[10] += 1.0;
    av[20] += 1.0;
    let e = file("e", &[("color", f32t(&[100], &ev))]);
    let a = file("a", &[("color", f32t(&[100], &av))]);
    let mut tol = Tolerances::default();
    assert!(!compare(&e, &a, &tol).unwrap().passed);
    tol.tensors.insert(
        "col*".into(),
        ToleranceSpec {
            max_mismatch_fraction: Some(0.02),
            ..Default::default()
        },
    );
    let r = compare(&e, &a, &tol).unwrap();
    assert!(r.passed, "{r}");
    assert_eq!(only(&r).stats.as_ref().unwrap().allowed_mismatches, 2);
    tol.tensors.get_mut("col*").unwrap().max_mismatch_fraction = Some(0.019);
    assert!(!compare(&e, &a, &tol).unwrap().passed);
}

#[test]
fn tolerance_file_resolution_order() {
    let json = r#"{
        "default": {"atol": 1e-3, "rtol": 1e-4},
        "tensors": {
            "grad_*": {"rtol": 1e-2},
            "grad_means*": {"atol": 0.5},
            "grad_means3D": {"max_mismatch_fraction": 0.25},
            "n_*": {"max_mismatch_fraction": 0.1}
        }
    }"#;
    let t = Tolerances::from_json(Path::new("tol.json"), json).unwrap();
    let f = t.resolve("color", "F32");
    assert_eq!((f.atol, f.rtol, f.max_mismatch_fraction), (1e-3, 1e-4, 0.0));
    let f = t.resolve("grad_shs", "F32");
    assert_eq!((f.atol, f.rtol), (1e-3, 1e-2));
    // The more specific pattern wins over `grad_*`, and does not merge with it.
    let f = t.resolve("grad_means2D", "F64");
    assert_eq!((f.atol, f.rtol), (0.5, 1e-4));
    // An exact name wins over every pattern.
    let f = t.resolve("grad_means3D", "F32");
    assert_eq!(
        (f.atol, f.rtol, f.max_mismatch_fraction),
        (1e-3, 1e-4, 0.25)
    );
    // Integers stay exact under `default`, but take per-tensor entries.
    let f = t.resolve("radii", "I32");
    assert_eq!((f.atol, f.rtol), (0.0, 0.0));
    assert_eq!(t.resolve("n_contrib", "I32").max_mismatch_fraction, 0.1);
    // Dtype defaults.
    let d = Tolerances::default();
    assert_eq!(d.resolve("x", "F32").atol, 1e-5);
    assert_eq!(d.resolve("x", "F32").rtol, 1.3e-6);
    assert_eq!(d.resolve("x", "F64").atol, 1e-7);
}

#[test]
fn bad_tolerance_files_are_errors() {
    let p = Path::new("tol.json");
    for bad in [
        r#"{"default": {"atol": -1}}"#,
        r#"{"default": {"atl": 1}}"#,
        r#"{"tensors": {"x": {"max_mismatch_fraction": 1.5}}}"#,
        r#"{"defaults": {}}"#,
        "not json",
    ] {
        assert!(Tolerances::from_json(p, bad).is_err(), "{bad}");
    }
}

#[test]
fn glob_patterns() {
    assert!(glob_match("grad_*", "grad_means3D"));
    assert!(glob_match("*3D", "grad_means3D"));
    assert!(glob_match("g*m*3*", "grad_means3D"));
    assert!(glob_match("*", ""));
    assert!(!glob_match("grad_*", "color"));
    assert!(!glob_match("*2D", "grad_means3D"));
    assert!(glob_match("a*a", "aaa"));
    assert!(!glob_match("a*ab", "aaa"));
}

#[test]
fn cosine_and_degenerate_norms() {
    let e = file("e", &[("x", f64t(&[2], &[1.0, 0.0]))]);
    let a = file("a", &[("x", f64t(&[2], &[0.0, 1.0]))]);
    let s = only(&compare(&e, &a, &Tolerances::default()).unwrap())
        .stats
        .clone()
        .unwrap();
    assert_eq!(s.cosine, 0.0);
    assert_eq!(s.rel_l2, 2f64.sqrt());
    let z = file("z", &[("x", f64t(&[2], &[0.0, 0.0]))]);
    let s = only(&compare(&z, &z, &Tolerances::default()).unwrap())
        .stats
        .clone()
        .unwrap();
    assert_eq!((s.cosine, s.rel_l2), (1.0, 0.0));
    let s = only(&compare(&z, &a, &Tolerances::default()).unwrap())
        .stats
        .clone()
        .unwrap();
    assert_eq!((s.cosine, s.rel_l2), (0.0, f64::INFINITY));
}

#[test]
fn empty_expected_file_is_unusable() {
    let e = TensorFile::new("e");
    let a = file("a", &[("x", f32t(&[1], &[1.0]))]);
    assert!(compare(&e, &a, &Tolerances::default()).is_err());
}

#[test]
fn report_json_round_trips_through_serde_json() {
    let e = file("e", &[("x", f32t(&[2], &[1.0, 2.0]))]);
    let a = file("a", &[("x", f32t(&[2], &[1.0, 2.5]))]);
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    let v: serde_json::Value = serde_json::from_str(&r.to_json()).unwrap();
    assert_eq!(v["passed"], false);
    assert_eq!(v["tensors"][0]["status"], "fail");
    assert_eq!(v["tensors"][0]["stats"]["worst"]["index"][0], 1);
    assert_eq!(v["tensors"][0]["stats"]["max_abs_error"], 0.5);
}

#[test]
fn f32_tensors_are_compared_in_f32_as_torch_isclose_does() {
    // torch.isclose(a, e, rtol=1e-3, atol=0) and numpy.isclose (both in
    // float32) say this pair is close; the same rule in f64 says it is not.
    let (e, a) = (0.18586217f32, 0.18604803f32);
    let tol = Tolerance {
        atol: 0.0,
        rtol: 1e-3,
        max_mismatch_fraction: 0.0,
        equal_nan: false,
    };
    assert!(tol.matches_f32(a, e));
    assert!(!tol.matches(a as f64, e as f64));
    // |a − e| overflowing f32 is no match, as in torch.
    assert!(!tol.matches_f32(f32::MAX, -f32::MAX));
}

fn i64t(v: &[i64]) -> Tensor {
    Tensor::I64(ndarray::ArrayD::from_shape_vec(ndarray::IxDyn(&[v.len()]), v.to_vec()).unwrap())
}

/// I64 tensors (gsplat's ids) are matched on their exact difference: two
/// values beyond 2^53 that round to the same f64 still differ, and the
/// integer distance is reported in full, even past `i64`'s range.
#[test]
fn i64_tensors_are_compared_exactly() {
    let big = (1i64 << 60) + 1;
    assert_eq!(big as f64, (big - 1) as f64);
    let e = file("e", &[("isect_ids", i64t(&[0, big, -5]))]);
    let same = compare(&e, &e, &Tolerances::default()).unwrap();
    assert!(same.passed, "{same}");
    let a = file("a", &[("isect_ids", i64t(&[0, big - 1, -5]))]);
    let r = compare(&e, &a, &Tolerances::default()).unwrap();
    assert!(!r.passed, "{r}");
    let t = only(&r);
    assert_eq!(t.dtype, "I64");
    let s = t.stats.as_ref().unwrap();
    assert_eq!(s.mismatches, 1);
    assert_eq!(s.ulp_max, Some(1));
    assert_eq!(s.worst.as_ref().unwrap().index, vec![1]);
    // Default `atol` does not reach integers, as for I32; a tensor's own entry does.
    let loose = Tolerances::from_json(
        Path::new("t.json"),
        r#"{"default": {"atol": 2}, "tensors": {"ids": {"atol": 2}}}"#,
    )
    .unwrap();
    assert!(!compare(&e, &a, &loose).unwrap().passed);
    let e2 = file("e", &[("ids", i64t(&[big]))]);
    let a2 = file("a", &[("ids", i64t(&[big - 2]))]);
    assert!(compare(&e2, &a2, &loose).unwrap().passed);
    let far = file("a", &[("ids", i64t(&[i64::MIN]))]);
    let r = compare(&file("e", &[("ids", i64t(&[i64::MAX]))]), &far, &loose).unwrap();
    assert_eq!(only(&r).stats.as_ref().unwrap().ulp_max, Some(u64::MAX));
    // An I32 tensor against an I64 one: a dtype problem, values still compared.
    let a3 = file("a", &[("ids", Tensor::i32(vec![1], vec![7]))]);
    let r = compare(&file("e", &[("ids", i64t(&[7]))]), &a3, &loose).unwrap();
    let t = only(&r);
    assert_eq!(t.problems, vec!["dtype I32, expected I64".to_string()]);
    assert_eq!(t.stats.as_ref().unwrap().mismatches, 0);
}
