//! `liquid-splat count`: the paper's parameter counts (docs/UPSTREAM.md §6.3, §8.2)
//! and the ptflops MAC conventions (§8.3), as the CLI prints them.

mod support;

fn run(args: &[&str]) -> (i32, String, String) {
    let out = support::cli(&[&["count"], args].concat());
    (
        support::code(&out),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn json(args: &[&str]) -> serde_json::Value {
    let mut a = args.to_vec();
    a.push("--json");
    let (code, out, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    serde_json::from_str(&out).unwrap()
}

#[test]
fn paper_parameter_counts() {
    // docs/UPSTREAM.md §8.2: 0.5223 M, 0.7829 M, 0.3345 M in the paper's Table 3.
    for (args, params) in [
        (&["--field", "mlp"][..], 522_280u64),
        (
            &["--field", "mlp", "--depth", "8", "--width", "256"][..],
            522_280,
        ),
        (
            &["--field", "cfc", "--depth", "8", "--width", "256"][..],
            782_888,
        ),
        (
            &["--field", "cfc", "--depth", "6", "--width", "128"][..],
            334_504,
        ),
        (&["--field", "cfc"][..], 334_504),
        (&["--field", "mlp", "--variant", "real"][..], 506_378),
        (&["--field", "mlp", "--6dof"][..], 523_051),
        (&["--field", "cfc", "--variant", "real"][..], 318_602),
    ] {
        let v = json(args);
        assert_eq!(v["parameters"], params, "{args:?}");
        // Text output too, with thousands separators.
        let (code, out, _) = run(args);
        assert_eq!(code, 0);
        let grouped = format!("{},{:03}", params / 1000, params % 1000);
        assert!(out.contains(&format!("parameters: {grouped}")), "{out}");
    }
}

#[test]
fn macs_per_gaussian_and_total() {
    // docs/UPSTREAM.md §8.3 reference table, CfC D6 W128 with GELU and with SiLU.
    let v = json(&["--field", "cfc", "--gaussians", "20000"]);
    assert_eq!(v["gaussians"], 20_000);
    assert_eq!(v["macs"]["pytorch"]["per_gaussian"], 336_552);
    assert_eq!(v["macs"]["pytorch_no_functional"]["per_gaussian"], 335_528);
    assert_eq!(v["macs"]["aten"]["per_gaussian"], 334_504);
    assert_eq!(v["macs"]["aten"]["total"], 334_504u64 * 20_000);
    let v = json(&["--field", "cfc", "--activation", "silu"]);
    assert_eq!(v["macs"]["pytorch"]["per_gaussian"], 335_784);
    assert_eq!(v["macs"]["pytorch"]["total"], 335_784);
    // D-3DGS MLP: the trunk's F.relu only counted by the functional patch.
    let v = json(&["--field", "mlp"]);
    assert_eq!(v["macs"]["pytorch"]["per_gaussian"], 524_840);
    assert_eq!(v["macs"]["pytorch_no_functional"]["per_gaussian"], 522_536);
    // The convention is named in the text output.
    let (_, out, _) = run(&["--field", "mlp", "--gaussians", "3"]);
    assert!(out.contains("ptflops aten backend"), "{out}");
    assert!(out.contains("count_functional=True"), "{out}");
    assert!(out.contains("1,574,520"), "{out}"); // 3 × 524,840
}

#[test]
fn bad_arguments_exit_2() {
    for args in [
        &["--field", "transformer"][..],
        &["--field", "mlp", "--depth", "2"][..],
        &["--field", "cfc", "--activation", "swish"][..],
        &["--field", "cfc", "--6dof"][..],
        &["--field", "mlp", "--variant", "blender"][..],
        &["--field", "mlp", "--gaussians", "-1"][..],
        &["--field", "cfc", "--depth", "0"][..],
    ] {
        let (code, _, err) = run(args);
        assert_eq!(code, 2, "{args:?}: {err}");
        assert!(!err.is_empty());
    }
    let (code, _, err) = run(&["--field", "transformer"]);
    assert_eq!(code, 2);
    assert!(err.contains("transformer"), "{err}");
}
