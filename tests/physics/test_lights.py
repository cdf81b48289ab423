import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pbrfit.errors import CaptureError
from pbrfit.io.lights import light_from_json, light_to_json
from pbrfit.physics.lights import (
    MIN_DISTANCE,
    directional_light,
    flash_light,
    incident,
    point_light,
    range_window,
    spot_falloff,
    spot_light,
)

incident_jit = jax.jit(incident)


def _point_sum(points, position):
    l, e = incident(point_light(position, [1, 1, 1], 5.0, 2.0), points)
    return jnp.sum(e) + jnp.sum(l)


_grad_point = jax.jit(jax.grad(_point_sum, argnums=(0, 1)))


def _khr_spot(cos_outer, cos_inner, cd):
    # KHR_lights_punctual's reference code, written out as it is there
    light_angle_scale = 1.0 / max(0.001, cos_inner - cos_outer)
    light_angle_offset = -cos_outer * light_angle_scale
    attenuation = min(max(cd * light_angle_scale + light_angle_offset, 0.0), 1.0)
    return attenuation * attenuation


def test_point_light_inverse_square_and_direction():
    light = point_light([0.0, 3.0, 0.0], [1.0, 0.5, 0.25], 40.0)
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [4.0, 3.0, 0.0]], np.float32)
    l, e = incident_jit(light, pts)
    np.testing.assert_allclose(l, [[0, 1, 0], [0, 1, 0], [-1, 0, 0]], atol=1e-6)
    d2 = np.array([9.0, 4.0, 16.0])
    np.testing.assert_allclose(e, 40.0 * np.array([1.0, 0.5, 0.25])[None] / d2[:, None], rtol=1e-6)


def test_incident_keeps_the_points_batch_shape():
    """E has the shape of l: one point gives (3,), a batch (P, 3), under vmap too."""
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0]], np.float32)
    for light in (point_light([0.0, 0.0, 3.0]), spot_light([0.0, 0.0, 3.0], [0.0, 0.0, -1.0])):
        l, e = incident(light, pts[0])
        assert l.shape == e.shape == (3,), (light.kind, l.shape, e.shape)
        l, e = jax.vmap(incident, in_axes=(None, 0))(light, pts)
        assert l.shape == e.shape == (2, 3)
        np.testing.assert_allclose(e, incident_jit(light, pts)[1], rtol=1e-6)


def test_range_window_matches_spec_formula():
    # window(d) = clamp(1 - (d/range)^4, 0, 1), 1/d^2 outside the window
    light = point_light([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], 10.0, range=2.0)
    ds = np.array([0.5, 1.0, 1.9, 2.0, 3.0])
    pts = np.stack([ds, np.zeros_like(ds), np.zeros_like(ds)], -1).astype(np.float32)
    _, e = incident_jit(light, pts)
    expected = 10.0 * np.clip(1 - (ds / 2.0) ** 4, 0, 1) / ds**2
    np.testing.assert_allclose(e[:, 0], expected, rtol=1e-5, atol=1e-7)
    assert float(range_window(jnp.asarray(5.0), jnp.asarray(0.0))) == 1.0


def test_spot_falloff_matches_khr_reference_code():
    inner, outer = 0.3, 0.6
    light = spot_light([0.0, 0.0, 0.0], [0.0, -2.0, 0.0], [1, 1, 1], 1.0, 0.0, inner, outer)
    angles = np.array([0.0, 0.2, 0.31, 0.45, 0.59, 0.7])
    pts = np.stack([np.sin(angles), -np.cos(angles), np.zeros_like(angles)], -1).astype(np.float32)
    l, e = incident_jit(light, pts)
    # cd = dot(spotDir, -l) = cos(angle)
    expected = [_khr_spot(math.cos(outer), math.cos(inner), math.cos(a)) for a in angles]
    np.testing.assert_allclose(e[:, 0], expected, atol=1e-5)
    assert e[0, 0] == pytest.approx(1.0) and e[-1, 0] == 0.0
    np.testing.assert_allclose(l, -pts, atol=1e-6)


def test_spot_hard_edge_finite():
    """inner = outer = 0.3 (cos 0.9553): a step, finite on both sides."""
    v = spot_falloff(jnp.array([0.9, 0.95, 0.96, 1.0]), jnp.asarray(0.3), jnp.asarray(0.3))
    np.testing.assert_array_equal(np.asarray(v), [0.0, 0.0, 1.0, 1.0])


def test_directional_light_lux_and_direction():
    light = directional_light([0.0, -1.0, -1.0], [1.0, 1.0, 1.0], 2.0)
    pts = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
    l, e = incident_jit(light, pts)
    np.testing.assert_allclose(l, np.broadcast_to([0, 1 / math.sqrt(2), 1 / math.sqrt(2)], (5, 3)), atol=1e-6)
    np.testing.assert_allclose(e, 2.0)


def test_incident_finite_at_light_position_values_and_gradients():
    light = point_light([1.0, 2.0, 3.0], [1, 1, 1], 5.0, range=0.0)
    pts = jnp.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0 + 1e-7]], jnp.float32)
    l, e = incident_jit(light, pts)
    assert np.all(np.isfinite(l)) and np.all(np.isfinite(e))
    assert float(e[0, 0]) == pytest.approx(5.0 / MIN_DISTANCE**2, rel=1e-4)

    gp, gpos = _grad_point(pts, jnp.array([1.0, 2.0, 3.0]))
    assert np.all(np.isfinite(gp)) and np.all(np.isfinite(gpos))
    sl = spot_light([0.0, 0.0, 0.0], [0, 0, -1], [1, 1, 1], 1.0)
    l, e = incident_jit(sl, jnp.zeros((1, 3)))
    assert np.all(np.isfinite(e)) and np.all(np.isfinite(l))


def test_flash_light_position_in_camera_space():
    c2w = np.eye(4)
    c2w[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # rotate 90 deg about +Y
    c2w[:3, 3] = [1.0, 2.0, 3.0]
    light = flash_light(c2w, [1, 1, 1], 5.0, [0.1, 0.2, 0.0])
    assert light.kind == "point"
    np.testing.assert_allclose(light.position, [1.0, 2.2, 2.9], atol=1e-6)
    assert float(light.intensity) == 5.0


@pytest.mark.parametrize(
    "d",
    [
        {"type": "point", "position": [0, 3, 2], "color": [1, 0.5, 1], "intensity": 40.0, "range": 0},
        {"type": "point", "position": [0, 3, 2], "color": [1, 1, 1], "intensity": 40.0, "range": 5.0},
        {"type": "directional", "direction": [0, -1, 0], "color": [1, 1, 1], "intensity": 2.0},
        {"type": "spot", "position": [0, 3, 0], "direction": [0, -1, 0], "color": [1, 1, 1],
         "intensity": 40.0, "range": 0, "inner_cone_angle": 0.25, "outer_cone_angle": 0.5},
    ],
)
def test_json_round_trip(d):
    light = light_from_json(d, "lights[0]")
    out = light_to_json(light)
    json.dumps(out)
    assert out["type"] == d["type"]
    for key, value in d.items():
        if key != "type":
            np.testing.assert_allclose(out[key], value, rtol=1e-6)
    again = light_from_json(out, "x")
    for a, b in zip(jax.tree.leaves(light), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)


def test_json_defaults_follow_khr():
    spot = light_from_json({"type": "spot", "position": [0, 0, 0], "direction": [0, 0, -1]}, "l")
    assert float(spot.inner_cone_angle) == 0.0
    assert float(spot.outer_cone_angle) == pytest.approx(math.pi / 4)
    np.testing.assert_array_equal(spot.color, [1, 1, 1])
    assert float(spot.intensity) == 1.0 and float(spot.range) == 0.0


def test_directional_light_ignores_range():
    """KHR_lights_punctual: range is defined for point and spot lights only; a directional light
    that carries one (exporters write it for every light) is the same light without it."""
    with_range = light_from_json({"type": "directional", "direction": [0, -1, 0], "intensity": 2.0, "range": 3}, "l")
    without = light_from_json({"type": "directional", "direction": [0, -1, 0], "intensity": 2.0}, "l")
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 50.0, 0.0]], np.float32)
    from pbrfit.render.shade import light_arrays

    for a, b in zip(light_arrays([with_range], pts), light_arrays([without], pts)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize(
    "d, fragment",
    [
        ({"type": "area", "position": [0, 0, 0]}, "lights[1].type: unknown light type 'area'"),
        ({"position": [0, 0, 0]}, "lights[1]: missing key 'type'"),
        ({"type": "point", "position": [0, 0, 0], "intensity": -1}, "lights[1].intensity: negative intensity"),
        ({"type": "point", "position": [0, 0, 0], "power": 3}, "lights[1]: unknown key 'power'"),
        ({"type": "point"}, "lights[1]: missing key 'position'"),
        ({"type": "point", "position": [0, 0]}, "lights[1].position: expected 3 numbers"),
        ({"type": "point", "position": [0, 0, 0], "range": -2}, "lights[1].range: negative range"),
        ({"type": "directional", "direction": [0, 0, 0]}, "lights[1].direction: zero vector"),
        ({"type": "directional", "direction": [0, 0, 1], "range": -3}, "lights[1].range: negative range"),
        ({"type": "spot", "position": [0, 0, 0], "direction": [0, 0, 1], "inner_cone_angle": 0.5,
          "outer_cone_angle": 0.4}, "cone angles must satisfy"),
        ({"type": "point", "position": [0, 0, 0], "intensity": "x"}, "lights[1].intensity: expected a finite number"),
        ({"type": "point", "position": [0, 0, 0], "color": [1, -1, 1]}, "lights[1].color: negative color"),
        ([1, 2], "lights[1]: expected a light object"),
    ],
)
def test_json_errors(d, fragment):
    with pytest.raises(CaptureError) as info:
        light_from_json(d, "lights[1]")
    assert fragment in str(info.value)
    assert "\n" not in str(info.value)


def test_lights_built_from_traced_values_differentiate():
    # a light built inside a traced function (a list holding a tracer) stays differentiable
    pts = np.array([[0.0, 0.0, 0.0]], np.float32)

    def irradiance(s):
        light = point_light([s, 0.0, 1.0], [1.0, 1.0, 1.0], 3.0)
        spot = spot_light([0.0, 0.0, 2.0], [s, 0.0, -1.0], [1.0, 1.0, 1.0], 3.0, 0.0, 0.2, 0.6)
        return incident(light, pts)[1].sum() + incident(spot, pts)[1].sum()

    g = jax.grad(irradiance)(0.3)
    assert np.isfinite(float(g)) and float(g) != 0.0
