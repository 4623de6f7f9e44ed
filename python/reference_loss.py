#!/usr/bin/env python3
"""Independent PyTorch reference of the training loss: (1 - l) * L1 + l * (1 - SSIM), l = 0.2.

Written from the project's notes (docs/UPSTREAM.md §6.4 and §6.7, docs/DECISIONS.md §2b):
11x11 Gaussian window with sigma 1.5 (in f32 cases the upstream f32 window: exp in f64,
stored as f32, normalised by its f32 sum; in f64 cases the same formula in f64), depthwise
convolution with zero padding 5, C1 = 0.01^2, C2 = 0.03^2, mean over channels and pixels.
The image is not clamped before the loss.

Usage:
    python reference_loss.py CASE.safetensors OUT.safetensors

Case (stage `loss`): image [3,H,W], gt [3,H,W]; optional metadata lambda_dssim (0.2).
Output: l1, ssim, loss (rank-0, shape []), grad_image [3,H,W] (autograd of `loss`).
"""

import argparse
import math
import sys

import torch
import torch.nn.functional as F

from common import case_dtype, load_case, save_case


def gaussian_1d(dtype, size=11, sigma=1.5):
    """Upstream: exp(-(k - 5)^2 / (2 sigma^2)) with math.exp (f64), stored in `dtype`,
    normalised by its sum in `dtype`."""
    g = torch.tensor([math.exp(-((k - size // 2) ** 2) / float(2 * sigma ** 2))
                      for k in range(size)], dtype=dtype)
    return g / g.sum()


def window_2d(dtype, channels=3):
    g = gaussian_1d(dtype)[:, None]
    w = (g @ g.T)[None, None]
    return w.expand(channels, 1, 11, 11).contiguous()


def ssim(img, gt):
    """Mean SSIM of two [C,H,W] images."""
    C = img.shape[0]
    w = window_2d(img.dtype, C)
    conv = lambda x: F.conv2d(x[None], w, padding=5, groups=C)[0]
    mu1, mu2 = conv(img), conv(gt)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s1 = conv(img * img) - mu1_sq
    s2 = conv(gt * gt) - mu2_sq
    s12 = conv(img * gt) - mu12
    C1, C2 = 0.01 ** 2, 0.03 ** 2
    m = ((2 * mu12 + C1) * (2 * s12 + C2)) / ((mu1_sq + mu2_sq + C1) * (s1 + s2 + C2))
    return m.mean()


def run(meta, t):
    dtype = case_dtype(t, "image")
    lam = float(meta.get("lambda_dssim", "0.2"))
    img = t["image"].to(dtype).clone().requires_grad_(True)
    gt = t["gt"].to(dtype)
    if img.shape != gt.shape or img.dim() != 3:
        raise SystemExit(f"image {tuple(img.shape)} and gt {tuple(gt.shape)} must be equal [C,H,W]")
    l1 = (img - gt).abs().mean()
    s = ssim(img, gt)
    loss = (1.0 - lam) * l1 + lam * (1.0 - s)
    loss.backward()
    one = lambda v: v.detach().reshape(())  # rank-0, as the Rust oracle writes them
    return {"l1": one(l1), "ssim": one(s), "loss": one(loss), "grad_image": img.grad}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("case")
    ap.add_argument("out")
    args = ap.parse_args(argv)
    meta, t = load_case(args.case)
    if meta.get("stage") != "loss":
        raise SystemExit(f"{args.case}: stage is {meta.get('stage')!r}, expected 'loss'")
    save_case(args.out, run(meta, t), {"stage": "loss", "producer": "python/reference_loss.py",
                                       "torch": torch.__version__})
    return 0


if __name__ == "__main__":
    sys.exit(main())
