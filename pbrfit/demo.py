"""`pbrfit demo`: synthesize a capture on the embedded defaults, fit it, print what came back.

The scene is data_synth's ``demo`` preset: a textured sphere on a textured floor under a
procedural sky and a sun-like point light, a few noisy views. Nothing is downloaded. The
capture goes to ``OUT/capture`` and the fit to ``OUT/fit``.
"""

from __future__ import annotations

import time
from pathlib import Path

__all__ = ["run_demo"]


def _table(errors: dict, sigma: dict) -> str:
    rows = [f"{'map':<12}{'RMSE vs truth':>15}{'median 1-sigma':>16}"]
    for name, value in errors.items():
        rows.append(f"{name:<12}{value:>15.4f}{sigma[name]:>16.4f}")
    return "\n".join(rows)


def run_demo(out: str = "pbrfit-demo", quiet: bool = False, seed: int = 0) -> int:
    """Synthesize, fit and report; returns the exit status."""
    import numpy as np

    from data_synth.presets import make_scene
    from data_synth.writer import synthesize

    from .cli import run_fit
    from .scene import load_capture
    from .views import default_cache_dir

    def say(message: str) -> None:
        if not quiet:
            print(message, flush=True)

    out = Path(out)
    start = time.perf_counter()
    scene = make_scene("demo", seed=seed)
    say(f"pbrfit demo: synthesizing '{scene.name}' ({scene.num_views} views of {scene.width}x{scene.height}) ...")
    synthesize(scene, out / "capture")
    t_synth = time.perf_counter() - start
    capture = load_capture(out / "capture")
    say(f"  capture written to {out / 'capture'} in {t_synth:.1f} s; fitting ...")
    result, errors = run_fit(capture, out / "fit", {}, default_cache_dir(), quiet)
    sig = np.asarray(result.uncertainty)
    seen = np.asarray(result.coverage) > 0
    sigma = {
        "base_color": float(np.median(sig[seen][:, 0:3])) if seen.any() else float("nan"),
        "metallic": float(np.median(sig[seen][:, 3])) if seen.any() else float("nan"),
        "roughness": float(np.median(sig[seen][:, 4])) if seen.any() else float("nan"),
    }
    r = result.report
    h, w = r["resolution"]
    say("")
    say(_table(errors, sigma))
    say("")
    say(
        f"{h}x{w} maps, {r['steps']} solver steps, fit {r['wall_time']:.1f} s "
        f"(compile {r['times'].get('compile', 0.0):.1f} s), total {time.perf_counter() - start:.1f} s; "
        f"{int(seen.sum())} of {seen.size} texels observed"
    )
    say(f"wrote {out / 'fit'} (maps, uncertainty.exr, material.glb, report.json, views/)")
    return 0
