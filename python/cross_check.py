#!/usr/bin/env python3
"""Cross-check the Rust oracle against the PyTorch references on seeded cases.

For each seed and dtype: cases of every stage from both generators (`liquid-splat case new`
and `gen_cases.py`), the Rust output (`case run`) as expected, the PyTorch reference's output
as actual, compared by `case compare` with fixtures/cases/tolerances_<dtype>.json. f64 cases
must also agree to a relative L2 error of at most --f64-rel-l2 (default 1e-10) in every
tensor. Covered: rasterize (exact and inria gradient modes), deform (MLP, 6-DoF MLP, CfC;
synthetic and real variants), loss, step (6-DoF MLP, MLP and CfC; synthetic and real
variants; fresh and warm Adam state; field on and off). Prints one line per case and exits 1
if any comparison fails (2 if a tool fails to run).

Usage:
    python python/cross_check.py [--seeds 0 1 2] [--bin target/release/liquid-splat] [--out DIR]
"""

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
REFS = {"rasterize": "reference_raster.py", "deform": "reference_deform.py",
        "loss": "reference_loss.py", "step": "reference_step.py"}

# `case new` cases: (stage, name, options, fresh). A fresh step case is the generated one
# without its Adam state and statistics (a first iteration).
RUST_SPECS = [
    ("rasterize", "rasterize", [], False),
    ("rasterize", "rasterize_inria", ["--gradient", "inria"], False),
    ("deform", "deform_mlp", ["--field", "mlp"], False),
    ("deform", "deform_mlp_6dof", ["--field", "mlp", "--6dof"], False),
    ("deform", "deform_mlp_6dof_real", ["--field", "mlp", "--6dof", "--variant", "real"], False),
    ("deform", "deform_cfc", ["--field", "cfc"], False),
    ("deform", "deform_cfc_real", ["--field", "cfc", "--variant", "real"], False),
    ("loss", "loss", [], False),
    ("step", "step_6dof_synthetic_warm", ["--field", "mlp", "--6dof", "--variant", "synthetic"],
     False),
    ("step", "step_6dof_synthetic_fresh", ["--field", "mlp", "--6dof", "--variant", "synthetic"],
     True),
    ("step", "step_6dof_real_warm", ["--field", "mlp", "--6dof"], False),
    ("step", "step_6dof_real_fresh", ["--field", "mlp", "--6dof"], True),
    ("step", "step_mlp_real_warm", ["--field", "mlp"], False),
    ("step", "step_cfc_real_warm", [], False),
]


def sh(*args):
    r = subprocess.run([str(a) for a in args], capture_output=True, text=True)
    if r.returncode != 0:
        print(f"command failed ({r.returncode}): {' '.join(map(str, args))}\n{r.stderr}")
        sys.exit(2)


def make_fresh(path):
    """Drop a step case's Adam state and statistics (a first iteration)."""
    sys.path.insert(0, str(HERE))
    from common import load_case, save_case
    meta, t = load_case(path)
    t = {k: v for k, v in t.items() if not k.startswith(("adam.", "stats."))}
    meta = {k: v for k, v in meta.items() if not k.startswith("adam.")}
    save_case(path, t, meta)


def rust_cases(binary, out, seed, dtype):
    cases = []
    for stage, name, extra, fresh in RUST_SPECS:
        name = f"new_{name}_{dtype}_s{seed}"
        p = out / f"{name}.safetensors"
        sh(binary, "case", "new", stage, p, "--dtype", dtype, "--seed", seed, *extra)
        if fresh:
            make_fresh(p)
        cases.append((stage, name, p))
    return cases


def python_cases(out, seed, dtype):
    d = out / f"gen_s{seed}"
    sh(sys.executable, HERE / "gen_cases.py", d, "--seed", seed, "--dtype", dtype)
    cases = []
    for p in sorted(d.glob(f"*_{dtype}.safetensors")):
        stage = p.stem.split("_")[0]
        cases.append((stage, f"gen_{p.stem}_s{seed}", p))
    return cases


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--bin", default=str(ROOT / "target" / "release" / "liquid-splat"))
    ap.add_argument("--out", help="keep the files here (default: a temporary directory)")
    ap.add_argument("--f64-rel-l2", type=float, default=1e-10,
                    help="largest relative L2 error of any tensor of an f64 case")
    args = ap.parse_args(argv)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="ls-cross-"))
    out.mkdir(parents=True, exist_ok=True)
    failed = 0
    print(f"{'case':44s} {'result':6s} worst tensor (rel_l2, max_abs)")
    for seed in args.seeds:
        for dtype in ["f32", "f64"]:
            tol = ROOT / "fixtures" / "cases" / f"tolerances_{dtype}.json"
            for stage, name, case in rust_cases(args.bin, out, seed, dtype) + python_cases(
                    out, seed, dtype):
                exp, act, rep = (out / f"{name}.{s}" for s in ("rust.safetensors",
                                                               "torch.safetensors", "json"))
                sh(args.bin, "case", "run", case, exp)
                sh(sys.executable, HERE / REFS[stage], case, act)
                r = subprocess.run([args.bin, "case", "compare", exp, act, "--tolerances", tol,
                                    "--report", rep], capture_output=True, text=True)
                if r.returncode == 2:
                    print(f"{name}: unusable input\n{r.stderr}")
                    sys.exit(2)
                report = json.loads(rep.read_text())
                with_stats = [t for t in report["tensors"] if t["stats"]]
                worst = max(with_stats, key=lambda t: t["stats"]["rel_l2"])
                s = worst["stats"]
                ok = report["passed"]
                note = "" if ok else "\n" + r.stdout
                if dtype == "f64" and s["rel_l2"] > args.f64_rel_l2:
                    ok = False
                    note += f"\n{worst['name']}: relative L2 error above {args.f64_rel_l2}"
                failed += not ok
                print(f"{name:44s} {'pass' if ok else 'FAIL':6s} {worst['name']} "
                      f"({s['rel_l2']:.2e}, {s['max_abs_error']:.2e})" + note)
    print(f"{'all passed' if failed == 0 else f'{failed} failed'}; files in {out}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
