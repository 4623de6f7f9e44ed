//! `liquid-splat gradcheck ...`: central-difference gradient checks in f64.

use crate::error::Outcome;
use crate::render::check;
use clap::Subcommand;

/// Subcommands of `gradcheck`.
#[derive(Subcommand)]
pub enum GradcheckWhat {
    /// The rasterizer's gradients on built-in random scenes (exit 1 if any
    /// relative error exceeds 1e-6).
    Raster {
        /// Seed of the built-in random scenes.
        #[arg(long, default_value_t = 7)]
        seed: u64,
    },
}

/// Run a `gradcheck` subcommand.
pub fn run(what: GradcheckWhat) -> crate::Result<Outcome> {
    match what {
        GradcheckWhat::Raster { seed } => gradcheck_raster(seed),
    }
}

fn gradcheck_raster(seed: u64) -> crate::Result<Outcome> {
    let mut ok = true;
    outln!(
        "{:<22} {:<16} {:>6} {:>11} {:>11}",
        "case (scene seed)",
        "input",
        "n",
        "max abs",
        "max rel"
    );
    for case in check::builtin_cases(seed) {
        match check::run_case(&case)? {
            None => {
                outln!(
                    "{:<22} no scene away from discontinuities in 20 draws",
                    case.name
                );
                ok = false;
            }
            Some(r) => {
                for g in &r.groups {
                    let pass = g.passes(check::REL_TOL);
                    ok &= pass;
                    outln!(
                        "{:<22} {:<16} {:>6} {:>11.3e} {:>11.3e}{}",
                        format!("{} ({})", r.name, r.seed),
                        g.name,
                        g.count,
                        g.max_abs,
                        g.max_rel,
                        if pass { "" } else { "  FAIL" }
                    );
                }
            }
        }
    }
    outln!(
        "tolerance: relative {:e}; {}",
        check::REL_TOL,
        if ok { "all passed" } else { "FAILED" }
    );
    Ok(Outcome::of_check(ok))
}
