"""Conformance check: pbrfit against a renderer written from the capture spec alone.

Builds every case of `cases.py` with the independent reference renderer (`reference.py`), then
for each case runs pbrfit through its command line, one process at a time:

- render: `pbrfit render CAP --material CAP/truth --no-cache --quiet`, compared image by image
  with the capture (both decoded to linear radiance): per-pixel relative error over the pixels
  both cover, less a one-pixel border, and the number of pixels whose coverage differs;
- environment cases: the same render compared with the reference under the spec's reading of
  the environment and under mirrored, flipped and rotated readings, and the angle between the
  sphere normal at the brightest pixel and the patch's direction;
- fits (`FITS`): `pbrfit fit CAP --out ... --resolution 32 --no-cache --quiet` (`--maps none` for
  the environment sphere), reading the per-map RMSE against `truth/` and the final loss from
  report.json, and the same RMSE over the texels some light reaches.

It also measures, with the reference renderer alone, how far plausible convention slips move
the images of c1_plane_zup, to show that the render match is far below them.

    python experiments/conformance/run.py [--cases NAME ...] [--keep DIR] [--no-fit] [--merge]

Writes experiments/results/conformance.json (``--merge`` keeps the cases already there and
replaces those just run) and prints its tables in markdown (``--print`` prints them alone). The
whole run takes about 8 minutes on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import cases  # noqa: E402
import reference as ref  # noqa: E402

RESULTS = HERE.parent / "results" / "conformance.json"
FITS = {  # case: extra fit arguments
    "c1_plane_zup": ["--resolution", "32"], "c1_plane_yup": ["--resolution", "32"],
    "c2_intrinsics": ["--resolution", "32"], "c3_png_reinhard": ["--resolution", "32"],
    "c5_obj": ["--resolution", "32"], "c6_spot": ["--resolution", "32"],
    "c4_env_zup": ["--maps", "none"],
}
SLIPS = {
    "clamp-to-edge instead of repeat": ref.Conventions(wrap="clamp"),
    "texel corners (uv = j / W, no 0.5)": ref.Conventions(texel_centre=0.0),
    "v flipped (row 0 at v = 1)": ref.Conventions(flip_v=True),
    "pixel centres at (i, j), no 0.5": ref.Conventions(pixel_centre=0.0),
}

# ----------------------------------------------------------------------------- measures


def erode(mask):
    """Drop the pixels of `mask` with a 4-neighbour outside it (silhouettes, where a float32
    and a float64 ray cast may disagree about a grazing hit)."""
    out = mask.copy()
    out[1:] &= mask[:-1]
    out[:-1] &= mask[1:]
    out[:, 1:] &= mask[:, :-1]
    out[:, :-1] &= mask[:, 1:]
    return out


def compare(ours, theirs, alpha_ours, alpha_theirs):
    """Relative error of `theirs` against `ours` (linear H x W x 3) over eroded common coverage:
    per channel |a - b| / max(|a|, 0.02 * p99 of a's brightest channel), the pixel's largest."""
    cov_o, cov_t = alpha_ours > 0.5, alpha_theirs > 0.5
    both = erode(cov_o & cov_t)
    a, b = ours[both], theirs[both]
    floor = 0.02 * max(np.percentile(a.max(-1), 99), 1e-8)
    rel = (np.abs(a - b) / np.maximum(np.abs(a), floor)).max(-1)
    return dict(max_rel=float(rel.max()), mean_rel=float(rel.mean()), pixels=int(both.sum()),
                coverage_mismatch=int((cov_o != cov_t).sum()))


def alpha_of(img):
    """The image's alpha channel (coverage), or all ones without one."""
    return img[..., 3] if img.shape[-1] == 4 else np.ones(img.shape[:2])


def rel_rms(x, target):
    """RMS of x - target relative to the RMS of target."""
    return float(np.sqrt(np.mean((x - target) ** 2)) / max(np.sqrt(np.mean(target ** 2)), 1e-12))


def angle_deg(a, b):
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


# ----------------------------------------------------------------------------- pbrfit


def pbrfit(*args):
    """Run the pbrfit command line; return its wall time in seconds."""
    exe = shutil.which("pbrfit") or str(Path(sys.executable).parent / "pbrfit")
    t = time.perf_counter()
    r = subprocess.run([exe, *map(str, args), "--no-cache", "--quiet"], capture_output=True, text=True)
    if r.returncode:
        raise RuntimeError(f"pbrfit {' '.join(map(str, args))} failed:\n{r.stderr[-3000:]}")
    return time.perf_counter() - t


def render_check(cap_dir, out):
    """Render the capture with its truth maps and compare every frame with the capture's image."""
    seconds = pbrfit("render", cap_dir, "--material", cap_dir / "truth", "--out", out)
    cap = json.loads((cap_dir / "capture.json").read_text())
    rcap = json.loads((out / "capture.json").read_text())
    rows = []
    for fr, rfr in zip(cap["frames"], rcap["frames"]):
        a, b = ref.read_image(cap_dir / fr["file_path"]), ref.read_image(out / rfr["file_path"])
        rows.append(compare(ref.decode(a, cap, fr["file_path"]), ref.decode(b, rcap, rfr["file_path"]),
                            alpha_of(a), alpha_of(b)))
    return dict(max_rel=max(r["max_rel"] for r in rows), mean_rel=float(np.mean([r["mean_rel"] for r in rows])),
                coverage_mismatch=sum(r["coverage_mismatch"] for r in rows),
                pixels=sum(r["pixels"] for r in rows), frames=len(rows), seconds=round(seconds, 1))


def env_check(cap_dir, out):
    """Compare pbrfit's render of an environment case (`out`, already rendered) with the
    reference under each reading of the environment (luminance, RMS difference relative to
    pbrfit's RMS over eroded common coverage, mean over frames), and locate the highlight."""
    cap = json.loads((cap_dir / "capture.json").read_text())
    env = ref.read_image(cap_dir / cap["environment"]["file"])
    d = cases.patch_direction(cap["world_up"], cap["environment"].get("rotation_deg", 0.0))
    errors = {v: [] for v in ref.ENV_VARIANTS}
    normals, weights, brightest = [], [], None
    for k, fr in enumerate(cap["frames"]):
        img = ref.read_image(out / fr["file_path"])
        fx, fy, cx, cy = ref.intrinsics(cap, fr, cases.SIZE, cases.SIZE)
        o, dirs = ref.camera_rays(fr["transform_matrix"], cases.SIZE, cases.SIZE, fx, fy, cx, cy)
        _, hit, _, n = ref.trace_sphere(o, dirs, cases.SPHERE["center"], cases.SPHERE["r"])
        both = erode(hit & (alpha_of(img) > 0.5))
        lum = img[..., :3].mean(-1)
        for v in ref.ENV_VARIANTS:
            ours, _ = ref.render(cap, fr, cases.SPHERE, cases.ENV_MATERIAL, cases.SIZE, cases.SIZE, env, v)
            errors[v].append(rel_rms(ours[..., :3].mean(-1)[both], lum[both]))
        if k == 0:  # the camera on the patch direction
            brightest = n[np.unravel_index(np.argmax(np.where(both, lum, -1)), lum.shape)]
        normals.append(n[both])
        weights.append(lum[both] ** 8)
    centroid = (np.concatenate(normals) * np.concatenate(weights)[:, None]).sum(0)
    return dict(rel_rms={v: float(np.mean(e)) for v, e in errors.items()}, patch_direction=d.round(4).tolist(),
                brightest_angle_deg=angle_deg(brightest, d), weighted_normal_angle_deg=angle_deg(centroid, d))


def lit_texels(cap, res):
    """Plane texels that some light of some frame reaches (irradiance > 0 and n.l > 0): the
    others are black in every image, so their base colour, metallic and roughness are free."""
    p = cases.texel_positions(cap["world_up"], res)
    up = cases.from_zup(cap["world_up"], [0, 0, 1])
    lit = np.zeros(p.shape[:-1], bool)
    for frame in cap["frames"]:
        for light in ref.frame_lights(cap, frame):
            l, e = ref.light_terms(light, p)
            lit |= (e.max(-1) > 0) & (l @ up > 0)
    return lit


def fit_errors(cap_dir, out):
    """Truth RMSE per map and final loss from report.json; for map fits also the RMSE over the
    texels a light reaches and the base colour RMSE of the fitted map read upside down (which
    shows that the orientation is pinned down)."""
    report = json.loads((out / "report.json").read_text())
    row = dict(rmse=report.get("truth_rmse"), final_loss=report.get("final_loss"))
    if "material" in report:
        row["material"] = report["material"]
        return row
    fitted = {m: ref.read_image(out / f"{m}.exr") for m in ("base_color", "metallic", "roughness")}
    truth = {m: ref.read_image(cap_dir / "truth" / f"{m}.exr") for m in fitted}
    lit = lit_texels(json.loads((cap_dir / "capture.json").read_text()), truth["metallic"].shape[0])
    row["unlit_texels"] = int((~lit).sum())
    row["rmse_lit"] = {m: float(np.sqrt(np.mean((fitted[m] - truth[m])[lit] ** 2))) for m in fitted}
    row["base_color_rmse_v_flipped"] = float(np.sqrt(np.mean((fitted["base_color"][::-1] - truth["base_color"]) ** 2)))
    return row


def fit_check(cap_dir, out, extra):
    """Fit the capture with pbrfit and measure the result (`fit_errors`)."""
    seconds = pbrfit("fit", cap_dir, "--out", out, *extra)
    return dict(fit_errors(cap_dir, out), seconds=round(seconds, 1))


def sensitivity(cap_dir):
    """Relative error of each convention slip against the spec reading, reference renderer only
    (frame 0 of c1_plane_zup)."""
    cap = json.loads((cap_dir / "capture.json").read_text())
    geom, material, frame = cases.plane_geometry("+z"), cases.truth_material(), cap["frames"][0]
    radiance, alpha = ref.render(cap, frame, geom, material, cases.SIZE, cases.SIZE)
    rows = {}
    for name, conv in SLIPS.items():
        slipped, slipped_alpha = ref.render(cap, frame, geom, material, cases.SIZE, cases.SIZE, conv=conv)
        rows[name] = compare(radiance, slipped, alpha, slipped_alpha)
    return rows


# ----------------------------------------------------------------------------- driver


def run_case(name, root):
    """Build one case and run its checks; return its row."""
    t = time.perf_counter()
    cap_dir = cases.build(name, root / "captures")
    row = dict(what=cases.CASES[name][0], build_seconds=round(time.perf_counter() - t, 1))
    row["render"] = render_check(cap_dir, root / "renders" / name)
    if name in cases.ENV_CASES:
        row["environment"] = env_check(cap_dir, root / "renders" / name)
    return row


def _g(x, digits=2):
    """A number in a table cell, blank for None."""
    return "" if x is None else f"{x:.{digits}g}"


def tables(results):
    """The results as markdown tables: renders and fits, environment readings, slips."""
    out = ["| case | render max rel | mean rel | coverage mismatch | base RMSE | metallic RMSE | "
           "roughness RMSE | final loss | unlit texels |", "| --- |" + " ---: |" * 8]
    for name, r in results["cases"].items():
        fit = r.get("fit") or {}
        rmse = fit.get("rmse") or {}
        cells = [_g(r["render"]["max_rel"]), _g(r["render"]["mean_rel"]), str(r["render"]["coverage_mismatch"]),
                 *(_g(rmse.get(m)) for m in ("base_color", "metallic", "roughness")), _g(fit.get("final_loss")),
                 str(fit.get("unlit_texels", ""))]
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    env = {n: r["environment"] for n, r in results["cases"].items() if "environment" in r}
    if env:
        out += ["", "| environment case | " + " | ".join(ref.ENV_VARIANTS) + " | brightest pixel ° | weighted ° |",
                "| --- |" + " ---: |" * (len(ref.ENV_VARIANTS) + 2)]
        for name, e in env.items():
            cells = [f"{e['rel_rms'][v]:.3f}" for v in ref.ENV_VARIANTS]
            cells += [f"{e['brightest_angle_deg']:.1f}", f"{e['weighted_normal_angle_deg']:.1f}"]
            out.append(f"| {name} | " + " | ".join(cells) + " |")
    out += ["", "| convention slip (reference renderer only) | max rel | mean rel | coverage mismatch |",
            "| --- | ---: | ---: | ---: |"]
    for name, s in results.get("sensitivity", {}).items():
        out.append(f"| {name} | {s['max_rel']:.3g} | {s['mean_rel']:.3g} | {s['coverage_mismatch']} |")
    return "\n".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", nargs="+", choices=list(cases.CASES), default=list(cases.CASES))
    parser.add_argument("--keep", type=Path, help="build captures and pbrfit outputs here and keep them")
    parser.add_argument("--no-fit", action="store_true", help="skip the fits")
    parser.add_argument("--merge", action="store_true", help="keep the other cases already in the results")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--print", action="store_true", help="only print the tables of the results file")
    args = parser.parse_args()
    if args.print:
        print(tables(json.loads(args.out.read_text())))
        return

    results = json.loads(args.out.read_text()) if args.merge and args.out.exists() else {"cases": {}}
    with tempfile.TemporaryDirectory(prefix="pbrfit-conformance-") as tmp:
        root = (args.keep or Path(tmp)).resolve()
        t0 = time.perf_counter()
        for name in args.cases:
            row = run_case(name, root)
            if name in FITS and not args.no_fit:
                row["fit"] = fit_check(root / "captures" / name, root / "fits" / name, FITS[name])
            results["cases"][name] = row
            print(f"{name}: done ({time.perf_counter() - t0:.0f} s)", flush=True)
        c1 = root / "captures" / "c1_plane_zup"
        if not c1.exists():
            cases.build("c1_plane_zup", root / "captures")
        results["sensitivity"] = sensitivity(c1)
    results.update(date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), machine=platform.platform(),
                   processor=platform.processor() or platform.machine())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print()
    print(tables(results))


if __name__ == "__main__":
    main()
