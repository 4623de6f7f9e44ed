//! Absent cotangents read as zeros in every stage that has them: a case
//! without its cotangent tensors is a forward-only run, with the same forward
//! outputs as the full case and gradients that are all zero.

use liquid_splat::oracle::gsplat::{self, GsplatOptions};
use liquid_splat::oracle::new::{new_case, CaseSpec};
use liquid_splat::oracle::run_case;

/// A cotangent input: the rasterizer's `grad_out_*`, the field's `grad_d_*`
/// and gsplat's `v_<output>`.
fn is_cotangent(name: &str) -> bool {
    name.starts_with("grad_") || name.starts_with("v_")
}

/// A gradient output: `grad_*` / `grad.<weight>` and gsplat's `v_<input>`.
fn is_gradient(name: &str) -> bool {
    name.starts_with("grad") || name.starts_with("v_")
}

fn check(spec: &CaseSpec) {
    let label = format!("{} {:?}", spec.stage, spec.gsplat);
    let full = new_case(spec).unwrap();
    let mut bare = full.clone();
    bare.tensors.retain(|name, _| !is_cotangent(name));
    assert!(
        bare.tensors.len() < full.tensors.len(),
        "{label}: the case has no cotangents"
    );
    let want = run_case(&full).unwrap();
    let got = run_case(&bare).unwrap();
    assert_eq!(
        got.tensors.keys().collect::<Vec<_>>(),
        want.tensors.keys().collect::<Vec<_>>(),
        "{label}"
    );
    let mut gradients = 0;
    for (name, t) in &got.tensors {
        if is_gradient(name) {
            gradients += 1;
            let values = t.to_f64();
            assert!(
                values.iter().all(|&x| x == 0.0),
                "{label}: `{name}` is not zero without cotangents"
            );
            assert!(
                want.tensors[name].to_f64().iter().any(|&x| x != 0.0),
                "{label}: `{name}` is zero with cotangents too (the test would not see a change)"
            );
        } else {
            assert_eq!(t, &want.tensors[name], "{label}: forward output `{name}`");
        }
    }
    assert!(gradients > 0, "{label}: no gradient outputs");
}

#[test]
fn rasterize_and_deform_without_cotangents() {
    check(&CaseSpec::new("rasterize"));
    check(&CaseSpec::new("deform"));
}

#[test]
fn gsplat_stages_without_cotangents() {
    for stage in gsplat::STAGES {
        if stage == gsplat::ISECT {
            continue; // piecewise constant: no cotangents
        }
        for packed in [false, true] {
            for antialiased in [false, true] {
                let mut spec = CaseSpec::new(stage);
                spec.gsplat = GsplatOptions {
                    packed,
                    antialiased,
                    ..GsplatOptions::default()
                };
                check(&spec);
            }
        }
    }
}

#[test]
fn a_present_cotangent_of_the_wrong_shape_is_still_an_error() {
    let mut case = new_case(&CaseSpec::new(gsplat::PROJECTION)).unwrap();
    case.insert_real::<f64>("v_depths", vec![1], &[1.0]);
    let e = run_case(&case).unwrap_err().to_string();
    assert!(e.contains("v_depths"), "{e}");
}
