#!/usr/bin/env python3
"""Cross-check the Rust oracle against the PyTorch references on seeded cases.

For each seed and dtype: cases from both generators (`liquid-splat case new` and
`gen_cases.py`), the Rust output (`case run`) as expected, the PyTorch reference's output as
actual, compared by `case compare` with fixtures/cases/tolerances_<dtype>.json. Prints one
line per case and exits 1 if any comparison fails (2 if a tool fails to run).

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
        "loss": "reference_loss.py"}


def sh(*args):
    r = subprocess.run([str(a) for a in args], capture_output=True, text=True)
    if r.returncode != 0:
        print(f"command failed ({r.returncode}): {' '.join(map(str, args))}\n{r.stderr}")
        sys.exit(2)


def rust_cases(binary, out, seed, dtype):
    """(name, path) of `case new` cases: rasterize (exact), deform mlp and cfc, loss."""
    specs = [("rasterize", []), ("deform", ["--field", "mlp"]), ("deform", ["--field", "cfc"]),
             ("loss", [])]
    cases = []
    for stage, extra in specs:
        name = f"new_{stage}{'_' + extra[1] if extra else ''}_{dtype}_s{seed}"
        p = out / f"{name}.safetensors"
        sh(binary, "case", "new", stage, p, "--dtype", dtype, "--seed", seed, *extra)
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
    args = ap.parse_args(argv)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="ls-cross-"))
    out.mkdir(parents=True, exist_ok=True)
    failed = 0
    print(f"{'case':40s} {'result':6s} worst tensor (rel_l2, max_abs)")
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
                worst = max((t for t in report["tensors"] if t["stats"]),
                            key=lambda t: t["stats"]["rel_l2"])
                s = worst["stats"]
                ok = report["passed"]
                failed += not ok
                print(f"{name:40s} {'pass' if ok else 'FAIL':6s} {worst['name']} "
                      f"({s['rel_l2']:.2e}, {s['max_abs_error']:.2e})"
                      + ("" if ok else "\n" + r.stdout))
    print(f"{'all passed' if failed == 0 else f'{failed} failed'}; files in {out}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
