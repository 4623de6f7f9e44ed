"""Fit the rational approximations of tanh and erf used by the f32 fields.

`src/math/fast.rs` evaluates, in plain f32 arithmetic (no FMA),

    tanh x ≈ c·P(c²)/Q(c²),  c = clamp(x, −9.1, 9.1),  P, Q of degree 4,
    erf x  ≈ c·P(c²)/Q(c²),  c = clamp(x, −4, 4),      P of degree 7, Q of degree 4,

with Q(0) = 1. Beyond the clamp both functions round to ±1 in f32 (1 − tanh 9.1 and
erfc 4 are below 2⁻²⁵), and the fits are made to reach ±1 there.

This script computes the coefficients: the rational function of those degrees with the
smallest maximum relative error on [0, clamp], by Lawson's iteratively reweighted least
squares on the linearised problem (x·P(s) − f·Q(s) weighted by 1/(f·Q_prev(s)), in the
scaled variable s = x²/clamp²), on 3,000 Chebyshev points, against mpmath at 30 digits.
It prints each set as the Rust constants (monomials in z = x², highest degree first, as
Horner's rule takes them), rounded to f32 by the compiler.

The error bound that matters is that of the f32 evaluation, which is several times the
fit's (the rounding of the products and sums dominates); the Rust tests measure it against
the pinned libm in f64 (`kernels::fastmath` tests, and the ignored exhaustive ones).

Run: python3 python/fit_fastmath.py   (needs numpy and mpmath)
"""

import mpmath as mp
import numpy as np

mp.mp.dps = 30

FUNCTIONS = {
    # name: (mpmath function, clamp, degree of P, degree of Q)
    "tanh": (mp.tanh, 9.1, 4, 4),
    "erf": (mp.erf, 4.0, 7, 4),
}


def fit(f, clamp, p, q, points=3000, iterations=60):
    """Coefficients (P, Q), monomials in z = x² lowest degree first, and the fit's maximum
    relative error on the points."""
    k = np.arange(points)
    x = clamp * (0.5 - 0.5 * np.cos(np.pi * (k + 0.5) / points))
    x = x[x > 1e-4]
    fx = np.array([float(f(mp.mpf(float(v)))) for v in x])
    s = (x / clamp) ** 2
    # Unknowns: P's p + 1 coefficients, then Q's q coefficients above Q(0) = 1.
    a = np.concatenate(
        [
            np.stack([x * s**i for i in range(p + 1)], 1),
            np.stack([-fx * s**i for i in range(1, q + 1)], 1),
        ],
        1,
    )
    weights = np.full(len(x), 1.0 / len(x))
    q_prev = np.ones_like(x)
    best = None
    for _ in range(iterations):
        scale = np.sqrt(weights) / (np.abs(fx) * np.abs(q_prev))
        sol, *_ = np.linalg.lstsq(a * scale[:, None], fx * scale, rcond=None)
        pc = sol[: p + 1]
        qc = np.concatenate([[1.0], sol[p + 1 :]])
        pv = x * np.polyval(pc[::-1], s)
        qv = np.polyval(qc[::-1], s)
        err = (pv / qv - fx) / fx
        worst = np.max(np.abs(err))
        if best is None or worst < best[0]:
            best = (worst, pc.copy(), qc.copy())
        weights = weights * np.abs(err)
        weights /= weights.sum()
        q_prev = qv
    worst, pc, qc = best
    # From s = z/clamp² back to z.
    pc = pc / clamp ** (2 * np.arange(p + 1))
    qc = qc / clamp ** (2 * np.arange(q + 1))
    return pc, qc, worst


def main():
    for name, (f, clamp, p, q) in FUNCTIONS.items():
        pc, qc, worst = fit(f, clamp, p, q)
        print(f"// {name}: clamp {clamp}, P degree {p}, Q degree {q}; "
              f"fit's maximum relative error {worst:.2e}")
        for label, c in (("P", pc), ("Q", qc)):
            values = ", ".join(f"{np.float32(v)!r}".replace("np.float32(", "").rstrip(")")
                               for v in c[::-1])
            print(f"const {name.upper()}_{label}: [f32; {len(c)}] = [{values}];")


if __name__ == "__main__":
    main()
