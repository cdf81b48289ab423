"""data_synth: synthetic captures with ground truth for pbrfit's tests, experiments and demo.

Procedural pieces, each reproducible from a `numpy.random.Generator`:

- `textures`: ground-truth maps (patches, gradients, value noise / fBm, binary metal masks,
  scratches; the metallic x roughness chart) as `TruthMaps`;
- `environments`: HDR equirect skies and studios in the capture spec's orientation;
- `meshes`: plane, UV sphere, rounded box, torus with glTF-oriented uv, a user's mesh;
- `rigs`: orbit, hemisphere and handheld camera rigs (OpenGL camera-to-world);
- `noise`: supersampling, Gaussian and Poisson-Gaussian noise, 8/16-bit quantisation;
- `presets`: the scenes (`make_scene`), `writer`: rendering and writing a capture folder;
- `mitsuba_render`: a second renderer, Mitsuba 3's path tracer (the ``mitsuba`` extra), with the
  BRDF and punctual lights as Mitsuba plugins in `mitsuba_plugins`.

    from data_synth import make_scene, synthesize
    synthesize(make_scene("plane-flash", seed=0), "captures/plane-flash")
"""

from . import environments, meshes, noise, presets, rigs, textures
from .meshes import MeshData
from .presets import PRESETS, Scene, make_scene, preset_names
from .textures import TruthMaps

__all__ = [
    "environments",
    "meshes",
    "noise",
    "presets",
    "rigs",
    "textures",
    "writer",
    "MeshData",
    "TruthMaps",
    "Scene",
    "PRESETS",
    "make_scene",
    "preset_names",
    "synthesize",
]


def __getattr__(name):  # the writer pulls in the renderer (jax): load it on first use
    if name in ("writer", "synthesize"):
        import importlib

        writer = importlib.import_module(f"{__name__}.writer")
        return writer if name == "writer" else writer.synthesize
    raise AttributeError(f"module 'data_synth' has no attribute {name!r}")
