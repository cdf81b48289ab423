"""Finite differences for gradient checks: Richardson-extrapolated central differences, float64.

Our own, not ``jax.test_util``: central differences with one step of Richardson extrapolation, so
the truncation error is O(h^4):

    D1(h)  = (f(x + h e_i) - f(x - h e_i)) / 2h                                  (d/dx_i)
    D2(h)  = (f(x + h e_i) - 2 f(x) + f(x - h e_i)) / h^2                         (d^2/dx_i^2)
    D11(h) = (f(x+h e_i+h e_j) - f(x+h e_i-h e_j) - f(x-h e_i+h e_j) + f(x-h e_i-h e_j)) / 4h^2
    estimate = (4 D(h/2) - D(h)) / 3

with h = `STEP_1` for the gradient and `STEP_2` for the Hessian. Clamps and branch switches are
kinks where no derivative exists: a point closer than `KINK_MARGIN` to one, in any input, is not
compared. The relative error at a point and derivative component is
|autodiff - fd| / max(|autodiff|, |fd|, SCALE_FLOOR[order] (1 + |f(x)|)) (`rel_error`).

`stencil_points` lays out where f is evaluated; `fd_estimates` turns those values into the gradient
and Hessian estimates. Everything here is numpy: the values come from one jitted program.
"""

from __future__ import annotations

import itertools

import numpy as np

__all__ = ["STEP_1", "STEP_2", "KINK_MARGIN", "SCALE_FLOOR", "stencil_points", "fd_estimates", "rel_error"]

#: Finite-difference step for the gradient (float64: roundoff ~ eps |f| / h ~ 1e-12 |f|).
STEP_1 = 1e-4
#: Finite-difference step for the Hessian (roundoff ~ eps |f| / h^2 ~ 1e-10 |f|).
STEP_2 = 1e-3
#: Points closer than this to a clamp or branch switch (in any input) are skipped: the stencils
#: reach STEP_2 along one input and STEP_2 along another, and must not straddle the kink.
KINK_MARGIN = 2.0 * STEP_2
#: Relative errors are measured against max(|autodiff|, |fd|, SCALE_FLOOR[order] (1 + |f(x)|)), so a
#: derivative that is exactly zero (or negligible next to the function) is compared with the
#: function's own scale. The floors sit well above the finite differences' roundoff in float64,
#: ~1e-12 |f| (1st order) and ~1e-9 |f| (2nd order, Richardson-amplified).
SCALE_FLOOR = {1: 1e-6, 2: 1e-3}


# --- Finite differences --------------------------------------------------------------------------
def offsets(k: int):
    """Unit stencil offsets: first-order (2k), second-order diagonal (2k) and mixed (4 per pair)."""
    eye = np.eye(k)
    first = np.concatenate([eye, -eye])  # +e_i for i, then -e_i
    pairs = list(itertools.combinations(range(k), 2))
    mixed = []
    for i, j in pairs:
        for si, sj in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            mixed.append(si * eye[i] + sj * eye[j])
    mixed = np.array(mixed).reshape(-1, k) if mixed else np.zeros((0, k))
    return first, mixed, pairs


def fd_estimates(values, x_count, k, pairs, h1, h2):
    """Richardson-extrapolated gradient (N, k) and Hessian (N, k, k) from stencil values."""

    def unpack(v):
        v = v.reshape(x_count, -1)
        f0 = v[:, 0]
        v = v[:, 1:]
        # layout per point: [f(x)] + for step in (h1, h1/2): first (2k) + for step in (h2, h2/2): first (2k) + mixed
        return f0, v

    f0, rest = unpack(values)
    n_first = 2 * k
    n_mixed = 4 * len(pairs)
    blocks = []
    pos = 0
    for size in (n_first, n_first, n_first + n_mixed, n_first + n_mixed):
        blocks.append(rest[:, pos : pos + size])
        pos += size

    def grad_est(block, h):
        return (block[:, :k] - block[:, k : 2 * k]) / (2.0 * h)

    def hess_est(block, h):
        hess = np.zeros((x_count, k, k))
        diag = (block[:, :k] - 2.0 * f0[:, None] + block[:, k : 2 * k]) / (h * h)
        hess[:, np.arange(k), np.arange(k)] = diag
        mixed = block[:, 2 * k :].reshape(x_count, len(pairs), 4)
        for p, (i, j) in enumerate(pairs):
            m = mixed[:, p]
            val = (m[:, 0] - m[:, 1] - m[:, 2] + m[:, 3]) / (4.0 * h * h)
            hess[:, i, j] = hess[:, j, i] = val
        return hess

    g = (4.0 * grad_est(blocks[1], h1 / 2) - grad_est(blocks[0], h1)) / 3.0
    hm = (4.0 * hess_est(blocks[3], h2 / 2) - hess_est(blocks[2], h2)) / 3.0
    return f0, g, hm


def stencil_points(x: np.ndarray, h1: float, h2: float):
    n, k = x.shape
    first, mixed, pairs = offsets(k)
    offs = [np.zeros((1, k))]
    for h in (h1, h1 / 2):
        offs.append(first * h)
    for h in (h2, h2 / 2):
        offs.append(np.concatenate([first, mixed]) * h)
    offs = np.concatenate(offs)  # (P, k)
    return (x[:, None, :] + offs[None]).reshape(-1, k), pairs


def rel_error(ad, fd, fval, order):
    floor = SCALE_FLOOR[order] * (1.0 + np.abs(fval))
    floor = floor.reshape(floor.shape + (1,) * (ad.ndim - 1))
    den = np.maximum(np.maximum(np.abs(ad), np.abs(fd)), floor)
    err = np.abs(ad - fd) / den
    return np.where(np.isfinite(ad) & np.isfinite(fd), err, np.inf)
