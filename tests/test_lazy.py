"""`import pbrfit` and importing a room load no JAX; a room's modules and pbrfit's names are
imported on first access (`pbrfit.lazy`)."""

import json
import subprocess
import sys

import pytest

import pbrfit
from pbrfit.lazy import submodules_on_access

ROOMS = ("physics", "io", "lighting", "scene", "render", "fitting", "checks", "cli")

# imports pbrfit and every room, prints which of JAX's and the files' libraries came with them
_CHILD = """
import importlib, json, sys
import pbrfit
for room in json.loads(sys.argv[1]):
    importlib.import_module("pbrfit." + room)
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in ("jax", "optimistix", "equinox", "OpenImageIO", "trimesh"))))
"""


def test_importing_pbrfit_and_its_rooms_loads_no_jax():
    proc = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(ROOMS)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads(proc.stdout) == []


def test_rooms_modules_and_names_resolve_on_access():
    from pbrfit.fitting.solvers import structured
    from pbrfit.physics import brdf
    from pbrfit.physics.model import Model

    assert pbrfit.physics.brdf is brdf and pbrfit.brdf is brdf
    assert pbrfit.fitting.solvers.structured is structured
    assert pbrfit.Model is Model
    with pytest.raises(AttributeError, match="pbrfit.physics' has no attribute 'nothing'"):
        pbrfit.physics.nothing
    with pytest.raises(AttributeError, match="'pbrfit' has no attribute 'nothing'"):
        pbrfit.nothing


def test_submodules_on_access_knows_only_the_packages_modules(tmp_path, monkeypatch):
    package = tmp_path / "lazypkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "leaf.py").write_text("VALUE = 7\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    getattr_ = submodules_on_access("lazypkg", [str(package)])
    assert "lazypkg.leaf" not in sys.modules
    assert getattr_("leaf").VALUE == 7 and "lazypkg.leaf" in sys.modules
    with pytest.raises(AttributeError, match="'lazypkg' has no attribute 'other'"):
        getattr_("other")
    monkeypatch.delitem(sys.modules, "lazypkg.leaf")
    monkeypatch.delitem(sys.modules, "lazypkg")
