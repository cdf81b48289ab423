"""A per-texel starting point: grid search over (metallic, roughness) with closed-form base colour.

The objective is not convex in roughness: a texel that starts far from its highlight's width
sees almost no gradient towards it, and Levenberg-Marquardt from a constant start leaves a few
percent of texels in such basins. But for metallic fixed at 0 or 1 and a given roughness, the
outgoing radiance is affine in base colour, channel by channel (glTF BRDF: the diffuse lobe is
(1 - F) b / π with F independent of b at metallic 0; the metal lobe's F = b + (1 - b)(1 - v·h)⁵
at metallic 1), so

    L_p(b) = L_p(0) + b (L_p(1) - L_p(0)).

For every candidate (m, r) we render each pixel twice (b = 0 and b = 1), solve each texel's base
colour in closed form from the pixels that read it (weighted by their bilinear weights, in linear
radiance, the targets decoded from sRGB), score the candidate by the image-space residual of
those pixels, and keep each texel's best candidate. Channels held fixed keep their values. This
costs 2 × candidates forward renders and no solve; the structured solver refines from there.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .color import encode, srgb_to_linear
from .brdf import MIN_ROUGHNESS
from .parameters import LOWER, UPPER
from .render import shade
from .solvers import Problem, _scatter, sample_texels

__all__ = ["ROUGHNESS_CANDIDATES", "METALLIC_CANDIDATES", "grid_initialise"]

#: Roughness values tried per texel: geometric from the BRDF's floor to 1 (highlight widths scale
#: with alpha = r², so equal steps in log r are equal steps in highlight width). The spacing
#: matters: seen from a few directions, a texel's objective has spurious minima in roughness
#: (one off-specular sample of D is matched by two alphas) and the true basin is only about
#: ±8% of r wide on the peer scene, so a 12-value grid started a few percent of texels in
#: the wrong basin; `ROUGHNESS_RATIO` steps of 6% do not (experiments/solvers.md).
ROUGHNESS_RATIO = 1.06
ROUGHNESS_CANDIDATES = tuple(
    min(float(MIN_ROUGHNESS * ROUGHNESS_RATIO**k), 1.0) for k in range(int(np.ceil(np.log(1 / MIN_ROUGHNESS) / np.log(ROUGHNESS_RATIO))) + 1)
)
#: Metallic values tried (the two at which radiance is affine in base colour).
METALLIC_CANDIDATES = (0.0, 1.0)
#: Floor on Σ w A² when solving a texel's base colour (a texel whose pixels see no light).
_NORMAL_FLOOR = 1e-12


def _linear_targets(problem: Problem):
    obs = problem.obs
    y = obs.target
    if obs.color_space == "srgb":
        y = srgb_to_linear(y)
    return y * jnp.exp2(-obs.exposure)[:, None]  # tone maps are not inverted: this is only a start


@eqx.filter_jit
def grid_initialise(x_fixed, problem: Problem):
    """(T, 5) starting values: each observed texel's best (metallic, roughness) candidate with its
    closed-form base colour; channels that are not free keep `x_fixed`."""
    obs = problem.obs
    free = problem.free
    seen = jnp.max(free, axis=1) > 0
    fixed_m = sample_texels(x_fixed, problem)  # (P, 5) sampled values of the fixed channels
    y = _linear_targets(problem)
    metal_free = jnp.max(free[:, 3]) > 0
    rough_free = jnp.max(free[:, 4]) > 0
    base_free = jnp.max(free[:, 0]) > 0

    def candidate(metal, rough):
        m_p = jnp.where(metal_free, metal, fixed_m[:, 3:4])
        r_p = jnp.where(rough_free, rough, fixed_m[:, 4:5])

        def render(b):
            return shade(obs.normal, obs.view, obs.light_l, obs.light_radiance, b, m_p, r_p, problem.model, problem.ibl)

        l0 = render(jnp.zeros_like(fixed_m[:, :3]))
        a = render(jnp.ones_like(fixed_m[:, :3])) - l0
        w = problem.weight[:, :, None]
        num = _scatter(w * (a * (y - l0))[:, None, :], problem)
        den = _scatter(w * (a * a)[:, None, :], problem)
        base_t = jnp.clip(num / jnp.maximum(den, _NORMAL_FLOOR), 0.0, 1.0)
        base_t = jnp.where(base_free, base_t, x_fixed[:, :3])
        b_p = sample_texels(jnp.concatenate([base_t, x_fixed[:, 3:]], axis=1), problem)[:, :3]
        value = encode(l0 + b_p * a, obs.exposure[:, None], obs.tonemap, obs.color_space)
        err = jnp.sum((value - obs.target) ** 2, axis=1)
        score = _scatter((problem.weight * err[:, None])[:, :, None], problem)[:, 0]
        return base_t, score

    metals = jnp.asarray(METALLIC_CANDIDATES, jnp.float32)
    roughs = jnp.clip(jnp.asarray(ROUGHNESS_CANDIDATES, jnp.float32), LOWER[4], UPPER[4])
    mm, rr = jnp.meshgrid(metals, roughs, indexing="ij")
    mm, rr = mm.reshape(-1), rr.reshape(-1)
    bases, scores = jax.lax.map(lambda mr: candidate(mr[0], mr[1]), jnp.stack([mm, rr], axis=1))
    best = jnp.argmin(scores, axis=0)  # (T,)
    base = jnp.take_along_axis(bases, best[None, :, None], axis=0)[0]
    x = jnp.concatenate([base, mm[best][:, None], rr[best][:, None]], axis=1)
    x = jnp.where(free > 0, x, x_fixed)
    return jnp.where(seen[:, None], x, x_fixed)
