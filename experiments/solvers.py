"""Solver and strategy comparison: per-map RMSE against run time on data_synth captures.

Every configuration fits the same capture (synthesised, loaded and ray-cast once per scene) at
the truth maps' resolution, and records per-map RMSE over observed texels, the steps taken, and
the time split into compile and run (grid start + coordinate search + solve). All fits run in
one process, and a configuration reuses the compilations of the ones before it in that process
(the first structured row of a scene and each optimistix row pay for compiling; most others read
about 0), so the plot
puts RMSE against run time, compile excluded; the JSON keeps the whole wall time of each
`fit_observations` call as well. Besides the RMSE over all observed texels (``rmse``), a row holds
the RMSE over well-observed texels (``rmse_well``, coverage >= `WELL_OBSERVED` pixel samples) and
the fraction of texels whose error is within the fit's reported 2σ (``within_2sigma``).

The optimistix solvers start from the grid start, without the continuation and the midway
coordinate search (``continuation=(), search=False``), so they compare with "structured (grid,
no search)".

    python experiments/solvers.py [--scenes peer-plane plane-flash] [--configs NAME ...] [--merge]

Writes experiments/results/solvers.json and solvers.png. ``--merge`` keeps the rows already in
solvers.json and replaces those of the (scene, config) pairs just run; the plot is redrawn from
all rows. ``--plot-only`` redraws the plot from solvers.json; ``--tables`` prints the markdown
tables of experiments/solvers.md from it. The whole run takes about an hour on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

import pbrfit  # noqa: F401  (sets the XLA flags pbrfit needs before JAX starts)

GRID = dict(solver="structured", init="grid", search=False, continuation=())
DEFAULT = "structured (default: grid + continuation + search)"
NO_CHECK = "structured (default, no uniform check)"
NO_CONTINUATION = "structured (grid + search, no continuation)"
NO_REPAIR = "structured (default, no repair)"
CONFIGS = {
    # name: fit_observations keyword arguments
    DEFAULT: dict(solver="structured"),
    "structured (default, 100 steps)": dict(solver="structured", max_steps=100),
    # the default without the uniform check (pbrfit.fitting.stages.selection): what the check changes, on one host
    NO_CHECK: dict(solver="structured", uniform_check=False),
    # the default without the repair of texels left in a wrong basin (pbrfit.fitting.stages.repair)
    NO_REPAIR: dict(solver="structured", repair=False),
    NO_CONTINUATION: dict(solver="structured", continuation=()),
    "structured (grid + continuation, no search)": dict(solver="structured", search=False),
    "structured (grid, no search)": dict(GRID),
    "structured (prior init)": dict(GRID, init="prior"),
    "structured (coarse-to-fine)": dict(GRID, init="prior", coarse_to_fine=True),
    "structured (default + coarse-to-fine)": dict(solver="structured", coarse_to_fine=True),
    "lm (optimistix)": dict(GRID, solver="lm", max_steps=20),
    "gn (optimistix)": dict(GRID, solver="gn", max_steps=20),
    "dogleg (optimistix)": dict(GRID, solver="dogleg", max_steps=20),
    "lbfgs (optimistix)": dict(GRID, solver="lbfgs", max_steps=400),
    "ncg (optimistix)": dict(GRID, solver="ncg", max_steps=400),
    "adam (optimistix)": dict(GRID, solver="adam", max_steps=300),
    # supersampled captures: the pixel footprint modelled by 2 x 2 samples per pixel
    "structured (default, 2 × 2 pixel samples)": dict(solver="structured", pixel_samples=2),
    # what `pbrfit fit` does on sRGB images (pixel_samples="auto"): the last steps both ways, the
    # better match kept
    "structured (default, auto footprint)": dict(solver="structured", pixel_samples=2, select_footprint=True),
    # the noisy scene only: the default with the smoothness prior kept to the end
    "structured (default, smooth=0.003)": dict(solver="structured", smooth=0.003),
    "structured (default, smooth=0.03)": dict(solver="structured", smooth=0.03),
}
#: Not a solver: structured LM started from the true maps (no grid start, no search): the
#: objective's minimum nearest the truth (on the noisy scene, the maximum-likelihood estimate a
#: perfect start would give; on noiseless ones, how far the data and model pin the maps down).
#: Cheap: one solve.
ORACLE = "oracle (start at the truth)"
#: The oracle of the model with 2 x 2 samples per pixel.
ORACLE_FOOTPRINT = "oracle, 2 × 2 pixel samples"
FOOTPRINT = "structured (default, 2 × 2 pixel samples)"
AUTO = "structured (default, auto footprint)"
#: What the noiseless scenes run: every configuration but the smoothness priors and the
#: footprints, and the oracle.
COMPARISON = [c for c in CONFIGS if "smooth=" not in c and c not in (FOOTPRINT, AUTO, NO_CHECK, NO_REPAIR)] + [ORACLE]
#: name: (data_synth preset, make_scene overrides, configurations to run)
SCENES = {
    "peer-plane": ("peer-plane", {}, COMPARISON + [NO_CHECK, NO_REPAIR]),
    "plane-flash": ("plane-flash", {}, COMPARISON + [FOOTPRINT, ORACLE_FOOTPRINT, AUTO]),
    # the flash capture without noise: what is left is the model's (pixel centres against the
    # 2 x 2 supersampled images) and the solver's
    "plane-flash-noiseless": ("plane-flash", dict(noise=0.0),
                              [DEFAULT, FOOTPRINT, ORACLE, ORACLE_FOOTPRINT, AUTO, NO_REPAIR]),
    # the peer layout as 16-bit sRGB PNGs rendered at pixel centres: what the automatic footprint
    # costs where the centres are right
    "peer-plane-png": ("peer-plane", dict(image_format="png16"), [DEFAULT, FOOTPRINT, AUTO, NO_CHECK]),
    "sphere-env": ("sphere-env", {}, COMPARISON + [NO_REPAIR]),
    "spheres-grid": ("spheres-grid", {}, COMPARISON + [NO_REPAIR]),
    "peer-plane-noisy": ("peer-plane", dict(noise=0.01),
                         [DEFAULT, NO_CHECK, NO_CONTINUATION, "structured (grid, no search)",
                          "structured (default, smooth=0.003)", "structured (default, smooth=0.03)", ORACLE]),
    # plane-flash with a third of the noise: three times the signal-to-noise
    "plane-flash-quiet": ("plane-flash", dict(noise=0.01 / 3),
                          [DEFAULT, NO_CONTINUATION, "structured (grid, no search)", ORACLE, FOOTPRINT, AUTO]),
    # the same noise with lights π times brighter (intensity 6π): three times the signal-to-noise
    "peer-plane-noisy-bright": ("peer-plane", dict(noise=0.01, light_intensity=6.0 * math.pi),
                                [DEFAULT, NO_CHECK, NO_CONTINUATION, "structured (grid, no search)", ORACLE]),
    # "1% noise" read as 1% of each value (std proportional to the signal) rather than 1% of a value of 1
    "peer-plane-noisy-relative": ("peer-plane", dict(noise=0.01, noise_model="relative"),
                                  [DEFAULT, NO_CHECK, NO_CONTINUATION, ORACLE]),
    "plane-flash-relative": ("plane-flash", dict(noise=0.01, noise_model="relative"),
                             [DEFAULT, NO_CONTINUATION, ORACLE, FOOTPRINT, AUTO]),
}


#: ``rmse_well`` is the RMSE over texels read by at least this many pixel samples (coverage):
#: on the spheres, texels near the poles, the uv seams and the silhouettes are read by a handful
#: of pixels and pinned down by little, and carry most of the error.
WELL_OBSERVED = 16


def _metrics(truth, material, coverage, sigma=None) -> dict:
    from pbrfit.fitting.api import map_rmse

    coverage = np.asarray(coverage)
    out = dict(rmse=map_rmse(truth, material, coverage),
               rmse_well=map_rmse(truth, material, np.where(coverage >= WELL_OBSERVED, coverage, 0)),
               well_fraction=float(np.mean(coverage[coverage > 0] >= WELL_OBSERVED)))
    if sigma is not None:  # fraction of observed texels whose error is within the reported 2σ
        seen = coverage > 0
        cover = {}
        for name, sl in (("base_color", slice(0, 3)), ("metallic", slice(3, 4)), ("roughness", slice(4, 5))):
            err = np.abs(np.asarray(getattr(material, name), np.float32) - np.asarray(getattr(truth, name), np.float32))
            cover[name] = float(np.mean((err <= 2 * np.asarray(sigma)[..., sl] + 1e-6)[seen]))
        out["within_2sigma"] = cover
    return out


def _result_message(code: int) -> str:
    try:
        import optimistix as optx

        return str(optx.RESULTS._index_to_message[code]).strip().split("\n")[0]  # private; best effort
    except Exception:
        return ""


def run_time(times: dict) -> float:
    """Seconds spent running (grid start + coordinate search + solve), compile excluded."""
    return float(sum(times.get(k, 0.0) for k in ("init", "search", "solve")))


def _oracle(obs, model, ibl, truth, resolution, max_steps=40):
    """Structured LM from the true maps: where the objective's minimum near the truth lies."""
    import jax
    import jax.numpy as jnp

    from pbrfit.physics.material import Material
    from pbrfit.fitting.observations import coverage_counts, neighbour_pairs, texel_layout
    from pbrfit.fitting.parameters import channel_mask
    from pbrfit.fitting.objective import Problem, objective
    from pbrfit.fitting.solvers.structured import StructuredLM, solve

    layout = texel_layout(obs, resolution, "repeat")
    seen = coverage_counts(layout).reshape(-1) > 0
    channels = channel_mask(("base_color", "metallic", "roughness"))
    if not model.metallic:
        channels[3] = 0.0
    free = (seen[:, None] * channels[None, :]).astype(np.float32)
    x0 = np.concatenate([np.asarray(truth.base_color), np.asarray(truth.metallic), np.asarray(truth.roughness)],
                        -1).reshape(-1, 5).astype(np.float32)
    e = neighbour_pairs(resolution).shape[0]
    problem = Problem(obs, layout.index, layout.weight, jnp.asarray(free), jnp.zeros((e, 2), jnp.int32),
                      jnp.zeros(e, jnp.float32), jnp.asarray(0.0, jnp.float32), jnp.asarray(0.05, jnp.float32),
                      ibl, model, "l2")
    args = (jnp.asarray(x0), problem, StructuredLM(), jnp.asarray(max_steps, jnp.int32))
    t0 = time.perf_counter()
    compiled = solve.lower(*args).compile()
    t1 = time.perf_counter()
    out = compiled(*args)
    x = np.asarray(jax.block_until_ready(out[0])).reshape(tuple(resolution) + (5,))
    t2 = time.perf_counter()
    material = Material(base_color=jnp.asarray(x[..., 0:3]), metallic=jnp.asarray(x[..., 3:4]),
                        roughness=jnp.asarray(x[..., 4:5]))
    coverage = coverage_counts(layout, obs.samples)
    loss = float(jax.jit(objective)(out[0], problem))  # the fit's final_loss: 1/2 Σ residuals²
    return material, coverage, dict(compile=t1 - t0, solve=t2 - t1), int(out[1].steps), loss


def run(scenes, configs):
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.fitting.api import _ibl_for_capture, fit_observations
    from pbrfit.render.views import model_for_capture
    from pbrfit.io.material_files import read_material
    from pbrfit.fitting.observations import observations_from_capture
    from pbrfit.scene.capture import load_capture

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            preset, overrides, allowed = SCENES[scene]
            names = [c for c in configs if c in allowed]
            if not names:
                continue
            cap_dir = Path(tmp) / scene
            t0 = time.perf_counter()
            synthesize(make_scene(preset, seed=0, **overrides), cap_dir)
            synth = time.perf_counter() - t0
            t0 = time.perf_counter()
            capture = load_capture(cap_dir)
            model = model_for_capture(capture)
            ibl = _ibl_for_capture(capture, model)
            obs = observations_from_capture(capture)
            setup = time.perf_counter() - t0
            truth = read_material(cap_dir / "truth")
            resolution = tuple(truth.resolution)
            print(f"== {scene}: {preset} {overrides}, maps {resolution}, {obs.num_pixels} pixels, "
                  f"synthesis {synth:.1f}s, setup {setup:.1f}s", flush=True)
            base = dict(scene=scene, preset=preset, overrides=overrides, resolution=list(resolution),
                        pixels=int(obs.num_pixels), setup=setup)
            sampled = {1: obs}

            def observations(n):  # with n x n samples per pixel, ray-cast on first use (in the row's wall time)
                if n not in sampled:
                    sampled[n] = observations_from_capture(capture, pixel_samples=n)
                return sampled[n]

            for name in names:
                t1 = time.perf_counter()
                if name in (ORACLE, ORACLE_FOOTPRINT):
                    n = 2 if name == ORACLE_FOOTPRINT else 1
                    material, coverage, times, steps, loss = _oracle(observations(n), model, ibl, truth, resolution)
                    wall = time.perf_counter() - t1
                    row = dict(base, config=name, kwargs=dict(solver="structured", start="truth", search=False,
                                                              pixel_samples=n),
                               **_metrics(truth, material, coverage), wall=wall, run=run_time(times),
                               compile=times["compile"], times=times, steps=steps, final_loss=loss)
                else:
                    kwargs = dict(CONFIGS[name])
                    try:
                        # every compile where it is first needed: no compile thread shares the cores with the run
                        call = dict(kwargs, background_compile=False)
                        n = call.pop("pixel_samples", 1)
                        if n > 1:  # as `pbrfit.fitting.api.fit` does: start, continuation and search on pixel centres
                            call["centres"] = obs
                        res = fit_observations(observations(n), model=model, ibl=ibl, resolution=resolution, **call)
                    except Exception as exc:  # a solver that fails is a result too
                        rows.append(dict(base, config=name, kwargs=kwargs,
                                         error=f"{type(exc).__name__}: {exc}"[:300]))
                        print(scene, name, "failed:", rows[-1]["error"], flush=True)
                        continue
                    wall = time.perf_counter() - t1
                    times = res.report["times"]
                    row = dict(base, config=name, kwargs=kwargs,
                               **_metrics(truth, res.material, res.coverage, res.uncertainty), wall=wall,
                               run=run_time(times), compile=times["compile"], times=times, steps=res.report["steps"],
                               levels=res.report["levels"], final_loss=res.report["final_loss"])
                    if "footprint" in res.report:
                        row["footprint"] = res.report["footprint"]
                    if "uniform_check" in res.report:
                        row["uniform_check"] = res.report["uniform_check"]
                    if "result" in row["levels"][-1]:
                        row["result_message"] = _result_message(row["levels"][-1]["result"])
                rows.append(row)
                print(f"{scene} | {name} | " + " ".join(f"{k} {v:.4g}" for k, v in row["rmse"].items())
                      + " | well-observed " + " ".join(f"{v:.4g}" for v in row["rmse_well"].values())
                      + f" | run {row['run']:.1f}s compile {row['compile']:.1f}s wall {wall:.1f}s"
                      + f" | steps {row['steps']} | " + json.dumps({k: round(v, 1) for k, v in row["times"].items()}),
                      flush=True)
    return rows


SHORT = {
    DEFAULT: "default",
    "structured (default, 100 steps)": "default (100 steps)",
    NO_CHECK: "no uniform check",
    NO_REPAIR: "no repair",
    NO_CONTINUATION: "no continuation",
    "structured (grid + continuation, no search)": "continuation, no search",
    "structured (grid, no search)": "no search",
    "structured (prior init)": "prior init",
    "structured (coarse-to-fine)": "c2f",
    "structured (default + coarse-to-fine)": "default+c2f",
    "lm (optimistix)": "lm",
    "gn (optimistix)": "gn",
    "dogleg (optimistix)": "dogleg",
    "lbfgs (optimistix)": "lbfgs",
    "ncg (optimistix)": "ncg",
    "adam (optimistix)": "adam",
    "structured (default, smooth=0.003)": "smooth 0.003",
    "structured (default, smooth=0.03)": "smooth 0.03",
    ORACLE: "oracle",
    FOOTPRINT: "2 × 2 pixel samples",
    AUTO: "auto footprint",
    ORACLE_FOOTPRINT: "oracle, 2 × 2 samples",
}
#: Sums of RMSE below this are drawn at it (a log axis has no 0).
FLOOR = 1e-7


def _place_labels(ax, points, fontsize=7):
    """Label (x, y, text, bold) points, merging coincident ones and nudging labels apart."""
    ax.figure.canvas.draw()  # fixes the limits, so data -> pixel transforms are final
    to_px = ax.transData.transform
    groups = []  # points within a few pixels of each other share one label ("a, b")
    for x, y, text, bold in sorted(points, key=lambda p: p[0]):
        px = to_px((x, y))
        for g in groups:
            if not (bold or g["bold"]) and min(np.hypot(*(q - px)) for q, _ in g["members"]) < 14:
                for q, names in g["members"]:
                    if np.hypot(*(q - px)) < 4:
                        names.append(text)
                        break
                else:
                    g["members"].append((px, [text]))
                break
        else:
            groups.append(dict(x=x, y=y, px=px, bold=bold, members=[(px, [text])]))
    for g in groups:
        g["text"] = ", ".join(", ".join(names) for _, names in g["members"])
    placed = []
    char_w, h = 0.62 * fontsize, 1.25 * fontsize  # rough label size in pixels (dpi 100 ≈ 1.4 px/pt)
    offsets = [(4, 3), (4, -10), (-4, 3), (-4, -10), (4, 11), (4, -18), (-4, 11), (-4, -18), (4, 19), (4, -26)]
    for g in sorted(groups, key=lambda g: (g["px"][0], g["px"][1])):
        w = char_w * len(g["text"]) * 1.4
        best = None
        for dx, dy in offsets:
            x0 = g["px"][0] + (dx * 1.4 if dx > 0 else dx * 1.4 - w)
            y0 = g["px"][1] + dy * 1.4
            box = (x0, y0, x0 + w, y0 + h * 1.4)
            hits = sum(not (box[2] < b[0] or b[2] < box[0] or box[3] < b[1] or b[3] < box[1]) for b in placed)
            if best is None or hits < best[0]:
                best = (hits, dx, dy, box)
            if hits == 0:
                break
        _, dx, dy, box = best
        placed.append(box)
        ax.annotate(g["text"], (g["x"], g["y"]), xytext=(dx, dy), textcoords="offset points", fontsize=fontsize,
                    ha="left" if dx > 0 else "right", fontweight="bold" if g["bold"] else "normal")


def plot(rows, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if "rmse" in r]
    # a panel per scene with a row to draw (the oracle is drawn as a line, not a point)
    scenes = [s for s in SCENES if any(r["scene"] == s and r["config"] != ORACLE for r in ok)]
    configs = [c for c in SHORT if c != ORACLE and any(r["config"] == c for r in ok)]
    cmap = plt.get_cmap("tab20")
    markers = "o*sDv^<>phXP"
    style = {c: (cmap(2 * i % 20 + (i >= 10)), markers[i % len(markers)]) for i, c in enumerate(configs)}
    n = len(scenes) + 1  # the last panel holds the legend
    cols = 3
    nrows = (n + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(5.6 * cols, 4.4 * nrows), squeeze=False)
    axes = axes.ravel()
    total = lambda r: r["rmse"]["base_color"] + r["rmse"]["roughness"] + r["rmse"]["metallic"]  # noqa: E731
    for ax, scene in zip(axes, scenes):
        sel = [r for r in ok if r["scene"] == scene and r["config"] != ORACLE]
        points = []
        for r in sel:
            y = max(total(r), FLOOR)
            color, marker = style[r["config"]]
            big = r["config"] == configs[0]
            ax.scatter(r["run"], y, s=120 if big else 40, color=color, marker=marker, edgecolor="k",
                       linewidth=0.5, zorder=3)
            points.append((r["run"], y, SHORT[r["config"]], big))
        oracle = [r for r in ok if r["scene"] == scene and r["config"] == ORACLE]
        note = ""
        if oracle and total(oracle[0]) >= 1e-4:
            ax.axhline(total(oracle[0]), color="0.4", linestyle="--", linewidth=0.8, zorder=1)
            ax.annotate("started at the truth", (0, total(oracle[0])), xytext=(3, -9), textcoords="offset points",
                        fontsize=7, color="0.3", xycoords=("axes fraction", "data"))
        elif oracle:
            v = total(oracle[0])
            note = f"; started at the truth: {v:.0e}" if v > 0 else "; started at the truth: 0"
        r0 = sel[0]
        ax.set_title(f"{scene}: {r0['resolution'][0]}×{r0['resolution'][1]} maps, {r0['pixels']:,} px{note}",
                     fontsize=9)
        ax.set_xlabel("run time, s (grid start + search + solve; compile excluded)", fontsize=8)
        ax.set_ylabel("RMSE base + metallic + roughness", fontsize=8)
        ax.set_yscale("log")
        ax.set_xlim(left=0, right=1.25 * max(r["run"] for r in sel))
        ys = [p[1] for p in points] + [total(r) for r in oracle if total(r) >= 1e-4]
        ax.set_ylim(min(ys) / 1.4, max(ys) * 1.4)
        ax.grid(True, which="both", alpha=0.25)
        ax.tick_params(labelsize=8)
        _place_labels(ax, points)
    for ax in axes[len(scenes):]:
        ax.axis("off")
    handles = [plt.Line2D([], [], linestyle="", marker=style[c][1], color=style[c][0], markeredgecolor="k",
                          markersize=8, label=f"{SHORT[c]}: {c}" if SHORT[c] not in c else c) for c in configs]
    handles.append(plt.Line2D([], [], linestyle="--", color="0.4", label="structured LM started at the true maps"))
    axes[len(scenes)].legend(handles=handles, loc="center", fontsize=8, frameon=False,
                             title=f"shared 2-core CPU; sums below {FLOOR:g} drawn at {FLOOR:g}",
                             title_fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


#: Packages whose versions can move the fits: the float programs (jax), the data (numpy, trimesh,
#: OpenImageIO) and the optimistix rows; and the start-up's time (ml_dtypes, `pyproject.toml`).
VERSIONED = ("jax", "jaxlib", "ml_dtypes", "numpy", "scipy", "trimesh", "OpenImageIO", "equinox", "lineax",
             "optimistix", "optax")


def machine() -> dict:
    """Where a run was taken: the platform, the CPU model and the versions of `VERSIONED`. On
    scenes whose objective is flat or multimodal in places (the spheres) the last digits of a
    float program, which the CPU's instruction set and these versions decide, can move which
    minimum a texel ends in, so RMSE there is comparable only between runs of one environment."""
    from importlib import metadata

    import jax

    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        pass
    versions = {}
    for name in VERSIONED:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return dict(platform=platform.platform(), processor=platform.processor() or cpu, cpu_count=os.cpu_count(),
                backend=jax.default_backend(), device=jax.devices()[0].device_kind, versions=versions,
                note="all rows of a run in one process")


def write_rows(path, rows: list) -> None:
    """Write ``{"machine": machine(), "rows": rows}`` to the JSON file `path`, whole or not at all
    (a temporary file renamed into place)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(dict(machine=machine(), rows=rows), indent=1))
    tmp.replace(path)


def _fmt(v: float) -> str:
    """3 significant digits; below 1e-4 one (``6e-7``); 0 as ``0``."""
    if v == 0:
        return "0"
    if abs(v) < 1e-4:
        m, e = f"{v:.0e}".split("e")
        return f"{m}e{int(e)}"
    return f"{v:.3g}"


def tables(rows) -> str:
    """The per-scene markdown tables of experiments/solvers.md, from solvers.json's rows."""
    out = []
    maps = ("base_color", "metallic", "roughness")
    for scene in dict.fromkeys(r["scene"] for r in rows):
        mine = [r for r in rows if r["scene"] == scene and "error" not in r]
        head = mine[0]
        res = "×".join(str(v) for v in head["resolution"])
        out.append(f"### {scene} ({res} maps, {head['pixels']:,} pixels; "
                   f"{100 * head['well_fraction']:.1f}% of observed texels well observed)\n")
        out.append("| configuration | base | metallic | roughness | well-observed: base / metallic / roughness "
                   "| within 2σ (%) | final loss | steps | run s | compile s | wall s |")
        out.append("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        for r in mine:
            name = f"**{r['config']}**" if r["config"] == DEFAULT else r["config"]
            cover = r.get("within_2sigma")
            cover = " / ".join(f"{100 * cover[m]:.0f}" for m in maps) if cover else "–"
            loss = f"{r['final_loss']:.4g}" if "final_loss" in r else "–"
            out.append(f"| {name} | " + " | ".join(_fmt(r["rmse"][m]) for m in maps)
                       + " | " + " / ".join(_fmt(r["rmse_well"][m]) for m in maps)
                       + f" | {cover} | {loss} | {r['steps']} | {r['run']:.1f} | {r['compile']:.1f} | {r['wall']:.1f} |")
        for r in rows:
            if r["scene"] == scene and "error" in r:
                out.append(f"| {r['config']} | failed: {r['error']} | | | | | | | | | |")
        out.append("")
    return "\n".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS) + [ORACLE, ORACLE_FOOTPRINT],
                        choices=list(CONFIGS) + [ORACLE, ORACLE_FOOTPRINT])
    parser.add_argument("--out", default=str(Path(__file__).parent / "results"))
    parser.add_argument("--merge", action="store_true", help="keep the other rows already in solvers.json")
    parser.add_argument("--plot-only", action="store_true", help="redraw solvers.png from solvers.json")
    parser.add_argument("--tables", action="store_true", help="print solvers.md's tables from solvers.json")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "solvers.json"
    if args.plot_only:
        plot(json.loads(path.read_text())["rows"], out / "solvers.png")
        return
    if args.tables:
        print(tables(json.loads(path.read_text())["rows"]))
        return
    rows = run(args.scenes, args.configs)
    here = machine()
    for r in rows:  # each row names its host: merged runs may come from different ones
        r["machine"] = here
    if args.merge and path.exists():
        old = json.loads(path.read_text())
        for r in old.get("rows", []) if isinstance(old, dict) else []:
            r.setdefault("machine", old.get("machine"))
        old = old["rows"] if isinstance(old, dict) else old
        new = {(r["scene"], r["config"]) for r in rows}
        kept = [r for r in old if (r["scene"], r["config"]) not in new]
        order = {s: i for i, s in enumerate(SCENES)}
        conf = {c: i for i, c in enumerate(SHORT)}
        rows = sorted(kept + rows, key=lambda r: (order.get(r["scene"], len(order)), conf.get(r["config"], len(conf))))
    doc = dict(machine=here, rows=rows)  # this run's host; every row also has its own
    path.write_text(json.dumps(doc, indent=1))
    plot(rows, out / "solvers.png")


if __name__ == "__main__":
    main()
