"""The radiance the capture's pixels saw (what blocked directions of the environment bring,
`pbrfit.lighting.visibility.Bounce`): the images' values undone to linear radiance."""

import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit.fitting.observations import Observations, linear_radiance
from pbrfit.physics.color import encode


@pytest.mark.parametrize("color_space, tonemap", [("linear", "none"), ("srgb", "none"), ("srgb", "reinhard")])
def test_rows_give_back_the_radiance_they_saw(color_space, tonemap):
    radiance = np.array([[0.2, 0.1, 0.05], [0.4, 0.3, 0.15], [0.05, 0.06, 0.07]])
    exposure = np.array([0.0, -1.0, 1.0])
    p = len(radiance)
    target = encode(jnp.asarray(radiance, jnp.float32), jnp.asarray(exposure, jnp.float32)[:, None], tonemap,
                    color_space)
    zeros = lambda *shape: jnp.zeros((p,) + shape, jnp.float32)  # noqa: E731
    obs = Observations(normal=zeros(3), tangent=zeros(4), view=zeros(3), light_l=zeros(0, 3),
                       light_radiance=zeros(0, 3), uv=zeros(2), exposure=jnp.asarray(exposure, jnp.float32),
                       target=jnp.asarray(target), residual_weight=jnp.ones((p, 3), jnp.float32),
                       view_index=jnp.zeros(p, jnp.int32), pixel=jnp.arange(p, dtype=jnp.int32), shapes=((1, p),),
                       tonemap=tonemap, color_space=color_space)
    np.testing.assert_allclose(linear_radiance(obs), radiance, rtol=1e-5 if color_space == "linear" else 1e-4)
