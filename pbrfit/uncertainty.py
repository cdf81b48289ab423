"""Per-texel standard errors from the Gauss-Newton normal matrix at the solution.

Near the optimum of a least-squares problem with independent residual noise of variance σ², the
covariance of the estimate is σ² (JᵀJ)⁻¹ (e.g. Nocedal & Wright, "Numerical Optimization",
2nd ed., section 10.3; Hartley & Zisserman, section 5.2). We keep the per-texel 5 × 5 diagonal
blocks D_t of JᵀJ (`pbrfit.solvers.normal_blocks`) restricted to the fitted channels, invert
them, and scale by the residual variance σ̂² = 2 E / (residuals - parameters). Inverting a block
ignores the coupling between neighbouring texels through shared pixels, which makes the errors
somewhat optimistic; `experiments/solvers.py` checks their calibration (the fraction of texels
within 2σ of the truth).

A direction the images do not constrain (a channel no view separates, e.g. roughness where no
highlight is ever seen) has a tiny eigenvalue: its σ is large, and +inf when the eigenvalue is
below `EIGEN_FLOOR` of the block's largest. Fixed channels get 0, unobserved texels +inf.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EIGEN_FLOOR", "block_standard_errors", "residual_variance"]

#: Eigenvalues below this fraction of a block's largest count as unconstrained (float32 round-off
#: of JᵀJ sits near 1e-7 relative; 1e-10 in the float64 inversion keeps only exact degeneracies).
EIGEN_FLOOR = 1e-10


def residual_variance(loss: float, residual_count: int, parameter_count: int) -> float:
    """σ̂² = 2 E / (n - p): the unbiased noise estimate of a least-squares fit."""
    dof = max(residual_count - parameter_count, 1)
    return 2.0 * float(loss) / dof


def block_standard_errors(blocks: np.ndarray, channels: np.ndarray, seen: np.ndarray, sigma2: float) -> np.ndarray:
    """(T, K) one-sigma errors from (T, K, K) normal-matrix blocks, the (K,) fitted-channel mask
    and the (T,) observed-texel mask (K = 5, or 7 with normals).

    σ_c² = σ̂² Σ_k V_ck² / e_k over the eigenpairs (e_k, V_k) of the block restricted to the
    fitted channels; 0 for fixed channels; +inf for fitted channels of texels no pixel reads.
    """
    blocks = np.asarray(blocks, np.float64)
    free = np.broadcast_to(np.asarray(channels, bool), blocks.shape[:2])
    seen = np.asarray(seen, bool)
    mask2 = free[:, :, None] & free[:, None, :]
    eye = np.eye(blocks.shape[1])
    b = np.where(mask2, blocks, 0.0) + np.where(free, 0.0, 1.0)[:, :, None] * eye
    e, v = np.linalg.eigh(b)
    top = np.max(np.abs(e), axis=1, keepdims=True)
    ok = e > EIGEN_FLOOR * np.maximum(top, np.finfo(np.float64).tiny)
    inv_e = np.where(ok, 1.0 / np.where(ok, e, 1.0), np.inf)
    # Σ_k V_ck² / e_k, with 0 · inf taken as 0 (a degenerate direction that misses channel c).
    with np.errstate(invalid="ignore"):
        contrib = np.where(v * v > 0, v * v * inv_e[:, None, :], 0.0)
    out = np.sqrt(sigma2 * np.sum(contrib, axis=2))
    out = np.where(seen[:, None], out, np.inf)
    return np.where(free, out, 0.0).astype(np.float32)
