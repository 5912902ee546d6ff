"""Fused CPU kernel (numba) of the row-sparse Adam step of `h2viz.mapping.optim.GrowingAdam` (whose torch code
is the reference): one pass over the rows updates those with a non-zero gradient in place. Through torch the
same step is ~12 operations (a row mask, gathers and scatters of the touched rows): ~1 ms a step on the corner
priors, against ~0.05 ms here.

Importing this module raises ImportError when numba is not installed.
"""

from __future__ import annotations

import numpy as np

from h2viz.mapping.kernels.jit import njit


@njit
def sparse_adam(
    p: np.ndarray,
    g: np.ndarray,
    m: np.ndarray,
    v: np.ndarray,
    steps: np.ndarray,
    lr: float,
    b1: float,
    b2: float,
    eps: float,
) -> None:
    """In place: Adam with per-row bias correction on the rows of p, m, v (rows, width) whose gradient g (rows,
    width) has a non-zero absolute sum; steps (rows,) counts each row's updates. Contiguous float32 arrays (views
    of the torch tensors), float32 arithmetic throughout, as the torch path."""
    one = np.float32(1.0)
    b1_, b2_, lr_, eps_ = np.float32(b1), np.float32(b2), np.float32(lr), np.float32(eps)
    for r in range(p.shape[0]):
        total = np.float32(0.0)
        for c in range(p.shape[1]):
            total += abs(g[r, c])
        if not total > 0:
            continue
        steps[r] += one
        t = steps[r]
        bc1, bc2 = one - b1_**t, one - b2_**t
        for c in range(p.shape[1]):
            gr = g[r, c]
            m[r, c] = m[r, c] * b1_ + gr * (one - b1_)
            v[r, c] = v[r, c] * b2_ + gr * gr * (one - b2_)
            p[r, c] -= lr_ * (m[r, c] / bc1) / (np.sqrt(v[r, c] / bc2) + eps_)
