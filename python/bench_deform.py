#!/usr/bin/env python3
"""PyTorch CPU timing of the deformation fields, the workloads of `liquid-splat bench deform`.

MLP D8 W256 (the D-3DGS DeformNetwork) and CfC D6 W128 (stacked ncps CfCCell, backbone 2x64
GELU), synthetic variant, f32, N Gaussians, forward and forward+backward, median of --reps
runs after one warm-up (and the fastest run), plus the median process CPU time divided by the
thread count (as `bench deform` prints it; less sensitive to a loaded machine). Run it beside
`liquid-splat --threads T bench deform` on the same machine with the same thread count.

Usage:
    python bench_deform.py [--threads 2] [--n 20000] [--reps 5]
"""

import argparse
import statistics
import time

import torch

from reference_deform import CfCField, DeformNetwork


def timed(fn, reps, threads):
    """Median and fastest wall time, and median process CPU time / threads (ms)."""
    fn()  # warm-up (allocator, thread pool)
    out, cpu = [], []
    for _ in range(reps):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        out.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3 / threads)
    return statistics.median(out), min(out), statistics.median(cpu)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--reps", type=int, default=5)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    xyz = (torch.rand(a.n, 3, generator=g) * 2 - 1) * 1.3
    # One time for every Gaussian, as in training (and in `liquid-splat bench deform`).
    t = torch.rand(1, 1, generator=g).expand(a.n, 1).contiguous()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, N = {a.n}, f32, "
          f"median of {a.reps} (fastest)")
    for name, net in [("mlp D8 W256", DeformNetwork(8, 256)), ("cfc D6 W128", CfCField(6, 128))]:
        def fwd():
            with torch.no_grad():
                net(xyz, t)

        def fwd_bwd():
            net.zero_grad(set_to_none=True)
            tt = t.clone().requires_grad_(True)
            dx, dr, ds = net(xyz, tt)
            (dx.sum() + dr.sum() + ds.sum()).backward()

        f, fmin, fcpu = timed(fwd, a.reps, a.threads)
        fb, fbmin, fbcpu = timed(fwd_bwd, a.reps, a.threads)
        print(f"{name:<14} forward {f:8.1f} ms ({fmin:.1f})   forward+backward {fb:8.1f} ms "
              f"({fbmin:.1f})   CPU/threads {fcpu:.1f} / {fbcpu:.1f}")


if __name__ == "__main__":
    main()
