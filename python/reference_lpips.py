#!/usr/bin/env python3
"""Golden values for the Rust LPIPS (src/lpips/), computed by the `lpips` package itself.

Writes, under fixtures/lpips/ (or OUT):

- golden.json: LPIPS of image pairs from `lpips.LPIPS(net='vgg')` (v0.1; the package's forward,
  ScalingLayer, normalize_tensor, linear layers, spatial average) with
    * a VGG16 backbone whose weights come from `formula_weights` (below: a counter-based hash,
      exactly reproducible in any language; the Rust test builds the same numbers), and
    * the package's shipped linear weights (weights/v0.1/vgg.pth) or formula linear weights,
  in both input conventions: `d3dgs` (the call D-3DGS's metrics.py makes: [0,1] images, no
  normalize=True) and `normalize` (normalize=True, 2x-1 first), in float32 and float64
  (the model and inputs converted with .double()). Per-layer values come from retPerLayer=True.
- vgg.pth: a copy of the package's weights/v0.1/vgg.pth (BSD-2-Clause, see LICENSE-lpips.txt),
  checked against its SHA-256.
- pth/*.pth and pth/expected.json: small files written by torch.save, both containers (zip and
  legacy), several dtypes, a transposed (strided) tensor, a tensor at a storage offset and an
  nn.Module state_dict (with its _metadata), with the values the reader must return; and
  weight files with a wrong shape or a missing tensor.

Images: a random pair (37x45, odd sizes so that the max-pools floor) and a rendered-like pair:
two test frames of the committed `swing` scene (64x64, RGBA composited on black, rounded to
8 bits), i.e. two renders of the same scene at different times.

Usage:
    python python/reference_lpips.py [OUT]        # default fixtures/lpips
"""

import hashlib
import importlib.metadata
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import torch

import lpips

LPIPS_VGG_SHA256 = "a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868"

# VGG16 convolutions: index in torchvision's `features`, (in, out) channels.
CONV_INDEX = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]
CONV_CHANNELS = [(3, 64), (64, 64), (64, 128), (128, 128), (128, 256), (256, 256), (256, 256),
                 (256, 512), (512, 512), (512, 512), (512, 512), (512, 512), (512, 512)]
LIN_CHANNELS = [64, 128, 256, 512, 512]
# features index -> lpips slice (slice1 = [0:4], slice2 = [4:9], ...).
SLICE_BOUNDS = [0, 4, 9, 16, 23, 30]

M64 = (1 << 64) - 1


def hash_u64(seed, n):
    """splitmix64 finaliser of (seed * G + i * H + C) mod 2^64 for i = 0..n-1 (uint64)."""
    with np.errstate(over="ignore"):
        i = np.arange(n, dtype=np.uint64)
        z = (np.uint64((seed * 0x9E3779B97F4A7C15) & M64) + i * np.uint64(0xD1B54A32D192ED03)
             + np.uint64(0x632BE59BD9B4E019))
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return z


def formula_uniform(seed, n):
    """k / 2^24 with k the top 24 bits of the hash: exact in float32."""
    return (hash_u64(seed, n) >> np.uint64(40)).astype(np.float64) / float(1 << 24)


def formula_weights(base):
    """The backbone and linear weights of formula set `base` (all exact float32 values):
    conv l weight = (u - 1/2) * 2^e with e = round(log2(sqrt(24 / (9 in)))) (about He scale),
    seed base*1000 + 2l; bias = (u - 1/2) / 16, seed base*1000 + 2l + 1;
    linear k = u / 16 (non-negative, as trained LPIPS layers), seed base*1000 + 100 + k."""
    convs = []
    for l, (cin, cout) in enumerate(CONV_CHANNELS):
        e = int(round(np.log2(np.sqrt(24.0 / (9 * cin)))))
        w = (formula_uniform(base * 1000 + 2 * l, cout * cin * 9) - 0.5) * 2.0 ** e
        b = (formula_uniform(base * 1000 + 2 * l + 1, cout) - 0.5) / 16.0
        convs.append((w.astype(np.float32).reshape(cout, cin, 3, 3), b.astype(np.float32)))
    lins = [(formula_uniform(base * 1000 + 100 + k, c) / 16.0).astype(np.float32)
            for k, c in enumerate(LIN_CHANNELS)]
    return convs, lins


def model(vgg_base, lin_base):
    """lpips.LPIPS(net='vgg') with formula backbone weights; shipped linear weights when
    lin_base is None, formula ones otherwise."""
    m = lpips.LPIPS(net="vgg", pretrained=True, pnet_rand=True, verbose=False)
    convs, lins = formula_weights(vgg_base)
    sd = m.state_dict()
    for (w, b), idx in zip(convs, CONV_INDEX):
        s = next(k for k in range(5) if SLICE_BOUNDS[k] <= idx < SLICE_BOUNDS[k + 1]) + 1
        sd[f"net.slice{s}.{idx}.weight"] = torch.from_numpy(w)
        sd[f"net.slice{s}.{idx}.bias"] = torch.from_numpy(b)
    if lin_base is not None:
        _, flins = formula_weights(lin_base)
        for k, l in enumerate(flins):
            sd[f"lin{k}.model.1.weight"] = torch.from_numpy(l).reshape(1, -1, 1, 1)
    m.load_state_dict(sd)
    return m.eval()


def swing_frames(root):
    """Two test frames of fixtures/scenes/swing composited on black, as 8-bit [3,H,W]."""
    from PIL import Image
    out = []
    for name in ["r_000.png", "r_004.png"]:
        rgba = np.asarray(Image.open(root / "fixtures/scenes/swing/test" / name).convert("RGBA"),
                          dtype=np.float64) / 255.0
        rgb = rgba[..., :3] * rgba[..., 3:4]
        u8 = np.floor(rgb * 255.0 + 0.5).clip(0, 255).astype(np.uint8)
        out.append(u8.transpose(2, 0, 1))
    return out


def images(root):
    h, w = 37, 45
    a = (hash_u64(7001, 3 * h * w) >> np.uint64(56)).astype(np.uint8).reshape(3, h, w)
    b = (hash_u64(7002, 3 * h * w) >> np.uint64(56)).astype(np.uint8).reshape(3, h, w)
    # b: a with about a quarter of the values replaced, so that the pair is related.
    keep = formula_uniform(7003, 3 * h * w).reshape(3, h, w) < 0.75
    b = np.where(keep, a, b)
    s0, s1 = swing_frames(root)
    return {"random_37x45": (a, b), "swing_64x64": (s0, s1)}


def lpips_value(m, a, b, convention, dtype):
    ta = torch.from_numpy(a.astype(np.float64) / 255.0)[None].to(dtype)
    tb = torch.from_numpy(b.astype(np.float64) / 255.0)[None].to(dtype)
    mm = m.double() if dtype == torch.float64 else m.float()
    with torch.no_grad():
        v, layers = mm(ta, tb, retPerLayer=True, normalize=(convention == "normalize"))
    return float(v.flatten()[0]), [float(l.flatten()[0]) for l in layers]


def write_reader_fixtures(out):
    """Small torch.save files for the .pth reader, and bad weight files."""
    d = out / "pth"
    d.mkdir(parents=True, exist_ok=True)
    g = torch.Generator().manual_seed(5)
    base = torch.randn(3, 4, generator=g)
    shared = torch.randn(10, generator=g, dtype=torch.float64)
    conv = torch.nn.Sequential(torch.nn.Conv2d(3, 2, 3))
    with torch.no_grad():
        conv[0].weight.copy_(torch.randn(2, 3, 3, 3, generator=g))
        conv[0].bias.copy_(torch.randn(2, generator=g))
    tensors = {
        "f32": torch.randn(2, 3, generator=g),
        "f64": torch.randn(3, generator=g, dtype=torch.float64),
        "f16": torch.randn(4, generator=g).half(),
        "bf16": torch.randn(5, generator=g).bfloat16(),
        "transposed": base.t(),            # strides (1, 4): not row-major
        "base": base,                      # shares the storage of `transposed`
        "offset": shared[3:7],             # a view at storage offset 3
        "scalar": torch.tensor(2.5),
    }
    expected = {}
    for k, v in tensors.items():
        expected[k] = {"shape": list(v.shape), "values": v.double().flatten().tolist()}
    for tag, zipped in [("zip", True), ("legacy", False)]:
        torch.save(tensors, d / f"tensors_{tag}.pth", _use_new_zipfile_serialization=zipped)
        torch.save(conv.state_dict(), d / f"module_{tag}.pth",
                   _use_new_zipfile_serialization=zipped)
    expected["module:0.weight"] = {"shape": [2, 3, 3, 3],
                                   "values": conv[0].weight.double().flatten().tolist()}
    expected["module:0.bias"] = {"shape": [2], "values": conv[0].bias.double().flatten().tolist()}
    (d / "expected.json").write_text(json.dumps(expected, indent=1) + "\n")

    # Bad weight files (small): a linear layer of the wrong width, a backbone with a
    # convolution of the wrong kernel size, and a backbone with only its first convolution.
    lins = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g)
            for k, c in enumerate(LIN_CHANNELS)}
    lins["lin2.model.1.weight"] = torch.rand(1, 255, 1, 1, generator=g)
    torch.save(lins, d / "lin_wrong_shape.pth")
    torch.save({"features.0.weight": torch.zeros(64, 3, 5, 5), "features.0.bias": torch.zeros(64)},
               d / "vgg_wrong_shape.pth")
    torch.save({"features.0.weight": torch.zeros(64, 3, 3, 3), "features.0.bias": torch.zeros(64)},
               d / "vgg_missing.pth")


def main():
    root = Path(__file__).resolve().parent.parent
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else root / "fixtures" / "lpips"
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)

    shipped = Path(lpips.__file__).parent / "weights" / "v0.1" / "vgg.pth"
    digest = hashlib.sha256(shipped.read_bytes()).hexdigest()
    if digest != LPIPS_VGG_SHA256:
        sys.exit(f"{shipped}: SHA-256 {digest}, expected {LPIPS_VGG_SHA256}")
    shutil.copyfile(shipped, out / "vgg.pth")
    shutil.copyfile(Path(lpips.__file__).parent.parent / "lpips-0.1.4.dist-info" / "LICENSE",
                    out / "LICENSE-lpips.txt")

    write_reader_fixtures(out)

    imgs = images(root)
    cases = []
    for vgg_base, lin_base in [(1, None), (2, 3)]:
        m = model(vgg_base, lin_base)
        for name, (a, b) in imgs.items():
            for convention in ["d3dgs", "normalize"]:
                for dtype in [torch.float64, torch.float32]:
                    v, layers = lpips_value(m, a, b, convention, dtype)
                    cases.append({
                        "image": name,
                        "vgg_formula": vgg_base,
                        "lin": "shipped" if lin_base is None else f"formula:{lin_base}",
                        "convention": convention,
                        "dtype": "f64" if dtype == torch.float64 else "f32",
                        "value": v,
                        "per_layer": layers,
                    })
                    print(f"{name:14} vgg {vgg_base} lin {cases[-1]['lin']:9} "
                          f"{convention:9} {cases[-1]['dtype']}: {v:.10f}")
    golden = {
        "generator": "python/reference_lpips.py",
        "lpips_version": importlib.metadata.version("lpips"),
        "torch_version": torch.__version__,
        "lpips_vgg_sha256": LPIPS_VGG_SHA256,
        "images": {k: {"h": int(a.shape[1]), "w": int(a.shape[2]),
                       "a": a.flatten().tolist(), "b": b.flatten().tolist()}
                   for k, (a, b) in imgs.items()},
        "cases": cases,
    }
    (out / "golden.json").write_text(json.dumps(golden) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
