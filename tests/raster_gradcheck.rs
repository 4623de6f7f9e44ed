//! f64 central-difference checks of every rasterizer gradient on small random
//! scenes kept away from discontinuities (see `render::check`).

use liquid_splat::render::check::{builtin_cases, run_case, REL_TOL};

#[test]
fn every_gradient_matches_central_differences() {
    let mut failures = Vec::new();
    for case in builtin_cases(7) {
        let report = run_case(&case)
            .unwrap()
            .unwrap_or_else(|| panic!("{}: no scene away from discontinuities", case.name));
        for g in &report.groups {
            println!("[{} seed {}] {g}", report.name, report.seed);
            if !g.passes(REL_TOL) {
                failures.push(format!("{}: {g}", report.name));
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}
