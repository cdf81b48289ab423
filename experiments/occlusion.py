"""Environment occlusion: how well direction cells stand for shadow rays, and fits with and without it.

Two measurements on the sphere-floor preset (a sphere on a textured floor under a sky with a sun,
no other light):

1. Cells. The irradiance E(p) = Σ_t L_t Ω_t (n·d_t)+ V(p, d_t) over the upper half of the
   environment's texels t, with V from one shadow ray per texel ("texels": the reference) and
   from the direction cells of `pbrfit.lighting.visibility` at several ``rows`` (one ray per
   cell), at points spread over the views' pixels: the mean and largest error relative to the
   reference, the cells and the seconds they took.
2. Fits. The capture is rendered with its environment light by the Monte Carlo reference with
   occlusion (`pbrfit.lighting.montecarlo.monte_carlo_radiance` with the pixels' `Visibility`:
   ground truth with the shadows in, as a path tracer renders it) and fitted with
   ``ibl="per_pixel"`` and ``"split_sum"``, each with ``occlusion="off"`` and ``"on"``. Per fit:
   per-map RMSE over the observed texels and over the well-observed ones (`solvers.py`), the
   occlusion's precompute time and the per-pixel integrals' time.

    python experiments/occlusion.py [--size 48] [--views 8] [--texture-size 32] [--mc-samples 256]
                                    [--ibl-samples 128] [--ibl-levels 9]

Writes experiments/results/occlusion.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import pbrfit  # noqa: F401  (sets the XLA flags pbrfit needs before JAX starts)

sys.path.insert(0, str(Path(__file__).parent))
from solvers import _metrics, machine  # noqa: E402

SCENE = "sphere-floor"
#: Monte Carlo renders: points per compiled call (the tail padded).
CHUNK = 16384


def _frame_hits(capture):
    """Per frame: (G-buffer, flat indices of its hit pixels)."""
    from pbrfit.scene.gbuffer import compute_gbuffer

    out = []
    for frame in capture.frames:
        g = compute_gbuffer(capture.mesh, frame.camera, frame.lights)
        out.append((g, np.flatnonzero(g.hit.reshape(-1))))
    return out


def render_occluded(capture, truth, samples: int) -> None:
    """Overwrite the capture's images with renders of ``truth`` whose environment light is the Monte
    Carlo reference's with occlusion (linear EXR, exposure 0, no punctual light: the preset's)."""
    import jax
    import jax.numpy as jnp

    from pbrfit.io.images import write_image
    from pbrfit.lighting.environment import environment_lookup
    from pbrfit.lighting.montecarlo import monte_carlo_radiance
    from pbrfit.lighting.visibility import visibility_rows
    from pbrfit.physics.material import material_at
    from pbrfit.render.views import capture_environment
    from pbrfit.scene.occlusion import cast_visibility

    env = capture_environment(capture)
    hits = _frame_hits(capture)
    flat = lambda name: np.concatenate([getattr(g, name).reshape(-1, getattr(g, name).shape[-1])[i]  # noqa: E731
                                        for g, i in hits])
    points, ng, n, v, uv = (flat(k) for k in ("position", "geometric_normal", "normal", "view", "uv"))
    vis, _ = cast_visibility(capture.mesh, env, points, ng)
    s = material_at(truth, jnp.asarray(uv, jnp.float32), "repeat")
    rad = []
    total = len(points)
    for start in range(0, total, CHUNK):
        stop = min(start + CHUNK, total)
        pad = CHUNK - (stop - start) if total > CHUNK else 0
        grow = lambda a: jnp.concatenate([jnp.asarray(a[start:stop], jnp.float32),  # noqa: E731
                                          jnp.repeat(jnp.asarray(a[stop - 1:stop], jnp.float32), pad, 0)])
        r = monte_carlo_radiance(env, grow(n), grow(v), grow(s.base_color), grow(s.metallic), grow(s.roughness),
                                 samples=samples, key=jax.random.PRNGKey(start),
                                 visibility=visibility_rows(vis, start, stop, pad))
        rad.append(np.asarray(r)[: stop - start])
    rad = np.concatenate(rad)
    start = 0
    for frame, (g, idx) in zip(capture.frames, hits):
        _, dirs = frame.camera.rays()
        img = np.asarray(environment_lookup(env, jnp.asarray(dirs.reshape(-1, 3), jnp.float32))).copy()
        img[idx] = rad[start:start + len(idx)]
        start += len(idx)
        write_image(frame.file_path, img.reshape(frame.camera.height, frame.camera.width, 3), "float")


def cells_error(capture, rows_list, count: int) -> list:
    """Measurement 1 (module docstring) at ``count`` points."""
    from pbrfit.lighting.environment import from_environment_frame, texel_directions, texel_solid_angles
    from pbrfit.lighting.visibility import OcclusionSettings, direction_cells
    from pbrfit.render.views import capture_environment
    from pbrfit.scene.occlusion import environment_visibility

    env = capture_environment(capture)
    hits = _frame_hits(capture)
    points = np.concatenate([g.position.reshape(-1, 3)[i] for g, i in hits])
    ng = np.concatenate([g.geometric_normal.reshape(-1, 3)[i] for g, i in hits]).astype(np.float64)
    pick = np.unique(np.linspace(0, len(points) - 1, count).round().astype(np.int64))
    points, ng = points[pick], ng[pick]
    radiance = np.asarray(env.radiance, np.float64)
    h, w, _ = radiance.shape
    luminance = radiance @ [0.2126, 0.7152, 0.0722]
    power = (luminance * texel_solid_angles(h, w))[: h // 2].reshape(-1)  # the upper half: the floor's sky
    dirs = np.asarray(from_environment_frame(texel_directions(h, w)[: h // 2].reshape(-1, 3), env.world_up,
                                             env.rotation_deg), np.float64)
    t = time.perf_counter()
    exact = np.unpackbits(environment_visibility(capture.mesh, points, ng, dirs), axis=1, count=len(dirs),
                          bitorder="little")
    reference_s = time.perf_counter() - t
    weight = power * np.maximum(ng @ dirs.T, 0.0)
    e_ref = np.sum(weight * exact, 1)
    out = []
    for rows in rows_list:
        settings = OcclusionSettings(rows=rows)
        t = time.perf_counter()
        cells = direction_cells(env, settings)
        bits = environment_visibility(capture.mesh, points, ng, cells.directions)
        seconds = time.perf_counter() - t
        texel_cell = cells.labels[: h // 2].reshape(-1)
        v = np.unpackbits(bits, axis=1, count=cells.count, bitorder="little")[:, texel_cell]
        e = np.sum(weight * v, 1)
        rel = np.abs(e - e_ref) / np.maximum(e_ref, 1e-6 * e_ref.max())
        out.append(dict(rows=rows, cells=cells.count, seconds=seconds, points=len(points),
                        mean_rel_error=float(rel.mean()), max_rel_error=float(rel.max()),
                        p95_rel_error=float(np.quantile(rel, 0.95))))
        print(f"  cells rows {rows:3d}: {cells.count:5d} cells, irradiance error mean {rel.mean():.4f} "
              f"p95 {np.quantile(rel, 0.95):.4f} max {rel.max():.4f} ({seconds:.1f} s; texels {reference_s:.0f} s)",
              flush=True)
    return out


def run(args) -> None:
    import jax

    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.fitting.api import fit
    from pbrfit.io.material_files import read_material
    from pbrfit.lighting.pixel_ibl import PixelIBLSettings
    from pbrfit.scene.capture import load_capture

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        scene = make_scene(SCENE, 0, size=args.size, views=args.views, texture_size=args.texture_size)
        synthesize(scene, Path(tmp) / "cap", write_contact_sheet=False)
        capture = load_capture(Path(tmp) / "cap")
        truth = read_material(Path(tmp) / "cap" / "truth")
        cells = cells_error(capture, args.rows, args.cell_points)
        t = time.perf_counter()
        render_occluded(capture, truth, args.mc_samples)
        render_s = time.perf_counter() - t
        print(f"{SCENE}: rendered with occlusion by the Monte Carlo reference ({args.mc_samples} samples) "
              f"in {render_s:.0f} s", flush=True)
        capture = load_capture(Path(tmp) / "cap")
        cache = Path(tmp) / "cache"
        settings = PixelIBLSettings(levels=args.ibl_levels, samples=args.ibl_samples)
        for mode in ("per_pixel", "split_sum"):
            for occlusion in ("off", "on"):
                result = fit(capture, ibl=mode, occlusion=occlusion, pixel_ibl_settings=settings,
                             resolution=tuple(truth.resolution), cache_dir=cache)
                m = _metrics(truth, result.material, result.coverage)
                report = result.report
                row = dict(ibl=mode, occlusion=occlusion, **m, occlusion_s=report["occlusion"]["seconds"],
                           ibl_s=report["ibl"]["seconds"], wall_s=report["wall_time"], final_loss=report["final_loss"],
                           psnr=report["psnr"])
                rows.append(row)
                print(f"  {mode:9s} occlusion {occlusion:3s}  rmse {_fmt(m['rmse'])}  well {_fmt(m['rmse_well'])}  "
                      f"occlusion {row['occlusion_s']:.1f} s  ibl {row['ibl_s']:.1f} s  wall {row['wall_s']:.0f} s",
                      flush=True)
    results = dict(description=__doc__.splitlines()[0], scene=SCENE, size=args.size, views=args.views,
                   texture_size=args.texture_size, mc_samples=args.mc_samples, render_s=render_s,
                   pixel_ibl=dict(samples=args.ibl_samples, levels=args.ibl_levels), cells=cells, fits=rows,
                   devices=[str(d) for d in jax.devices()], machine=machine())
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "occlusion.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {args.out / 'occlusion.json'}")


def _fmt(r: dict) -> str:
    return " / ".join(f"{r[k]:.3f}" for k in ("base_color", "metallic", "roughness"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--texture-size", type=int, default=32)
    ap.add_argument("--mc-samples", type=int, default=256, help="Monte Carlo steps per pixel of the rendered images")
    ap.add_argument("--ibl-samples", type=int, default=128, help="per-pixel integrals' sample steps")
    ap.add_argument("--ibl-levels", type=int, default=9, help="per-pixel integrals' roughness levels")
    ap.add_argument("--rows", type=int, nargs="+", default=[8, 16, 32], help="cell grids to measure")
    ap.add_argument("--cell-points", type=int, default=400, help="points of the cells' measurement")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    run(ap.parse_args(argv))


if __name__ == "__main__":
    main()
