"""Shared helpers of the PyTorch references: case-file I/O and metadata parsing.

Case files are safetensors with string metadata; every reference reads one case and
writes one output file with the same tensor names as the Rust oracle.
"""

import torch
from safetensors import safe_open
from safetensors.torch import save_file


def load_case(path):
    """Return (metadata dict, {name: tensor}) of a safetensors file."""
    tensors = {}
    with safe_open(path, framework="pt") as f:
        meta = dict(f.metadata() or {})
        for k in f.keys():
            tensors[k] = f.get_tensor(k)
    return meta, tensors


def save_case(path, tensors, meta):
    """Write tensors (made contiguous) and string metadata."""
    out = {k: v.detach().contiguous() for k, v in tensors.items()}
    save_file(out, path, metadata={k: str(v) for k, v in meta.items()})


def case_dtype(tensors, name):
    """The floating dtype of the case, taken from a required tensor."""
    d = tensors[name].dtype
    if d not in (torch.float32, torch.float64):
        raise SystemExit(f"tensor `{name}` has dtype {d}; expected float32 or float64")
    return d


def require(meta, key):
    if key not in meta:
        raise SystemExit(f"missing metadata `{key}`")
    return meta[key]
