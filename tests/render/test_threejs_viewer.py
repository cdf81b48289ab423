"""A material.glb as three.js renders it agrees with `pbrfit render` of the same view.

`experiments/viewer_check.py` on a small capture (a textured sphere, +Z up, three point lights,
one 64^2 view) with its truth maps as the material: three.js (npm ``three``, GLTFLoader,
MeshStandardMaterial) in headless Chromium with software WebGL, against pbrfit's render of the
view. Tolerances, over the pixels both cover (experiments/viewer_check.md):

- three.js as it is, against pbrfit's render of the float maps: median relative difference
  below 10%, and the canvas (sRGB 8-bit) within 3 codes at the median (measured here: 6.0% and
  2 codes; three.js's specular anti-aliasing, the largest share, grows with the change of the
  normal across a pixel, so a 64^2 sphere parts more than the experiment's 128^2 one);
- three.js with its own approximations turned off (specular anti-aliasing, the exp2 Fresnel fit,
  multiple-scattering compensation, the diffuse's Fresnel weight, mipmaps), against pbrfit's
  render of the GLB's 8-bit maps, outside the pixels where the two are known to part (n·v <= 0,
  and pbrfit's shadow rays at a light's terminator): median below 0.5%, 99th percentile below 3%
  (measured: 0.13% and 1.5%; light intensities off by a factor pi give 68% and 68%).

The camera, the light units and positions, the +Z-up rotation, the texture orientation and the
sRGB decoding all have to be right for the second to hold. Skipped without Chromium
(``chromium`` on PATH or $CHROMIUM) or three.js (``npm install --no-save --prefix . three@0.187.0``,
or $PBRFIT_THREE naming the package's folder); .ci/run installs neither.
"""

import importlib.util
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _viewer_check():
    spec = importlib.util.spec_from_file_location("viewer_check", ROOT / "experiments" / "viewer_check.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("viewer_check", module)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def checked(tmp_path_factory):
    vc = _viewer_check()
    three = Path(os.environ.get("PBRFIT_THREE", ROOT / "node_modules" / "three"))
    if vc.chromium_binary() is None:
        pytest.skip("no chromium on PATH (apt-get install chromium, or set $CHROMIUM)")
    if not (three / "build" / "three.module.js").is_file():
        pytest.skip(f"no three.js at {three} (npm install --no-save --prefix . three@{vc.THREE_VERSION})")
    from data_synth.writer import synthesize

    root = tmp_path_factory.mktemp("viewer")
    synthesize(vc.make_scene(64, 1), root / "capture", write_contact_sheet=False)
    c = vc.check(root / "capture", root / "capture" / "truth", 0, three, root)
    return vc, c, vc.tables(c)


def test_three_js_covers_the_pixels_pbrfit_renders(checked):
    _, c, _ = checked
    cov = c["coverage"]
    assert cov["both"] >= 0.99 * cov["pbrfit"] and cov["both"] >= 0.99 * cov["three"], cov


def test_three_js_as_is_within_tolerance(checked):
    _, _, t = checked
    row = next(r for r in t["rows"] if r["three"] == "as_is" and r["pbrfit"] == "float maps" and r["pixels"] == "all")
    assert row["rel_median"] < 0.10, row
    assert t["canvas"]["srgb8_median"] <= 3, t["canvas"]


def test_three_js_without_its_approximations_matches_pbrfit(checked):
    vc, _, t = checked
    last = vc.VARIANTS[-1][0]
    row = next(r for r in t["rows"] if r["three"] == last and r["pbrfit"] == "8-bit maps" and r["pixels"] == "unclassed")
    assert row["rel_median"] < 0.005, row
    assert row["rel_p99"] < 0.03, row
