"""The fit as three.js shows it: a fit's ``material.glb`` rendered by three.js beside ``pbrfit render``.

Two captures under point lights and no environment, both +Z up (so the GLB's root rotation
into +Y up is exercised): a textured sphere (smoothly varying metallic, 64^2 maps) under three
white point lights (`make_scene`), and the ``peer-plane`` preset (a flat plane, metallic 0, four
lights). Each is synthesized and fitted (``pbrfit fit``). One view is then rendered twice:

- by pbrfit (`pbrfit.render.views.render_capture`, the view's pixel centres, linear radiance),
  from the fit's float maps, from the 8-bit maps the GLB holds, and with
  ``multiscatter=true``;
- by three.js (npm ``three``, `GLTFLoader`, `MeshStandardMaterial` as the loader makes it) in
  headless Chromium with software WebGL (SwiftShader), with the capture's camera (its
  camera-to-world matrix and pinhole intrinsics as a projection matrix) and its point lights
  (``PointLight(color, candela, distance 0, decay 2)``: three.js's physical units, those of
  KHR_lights_punctual), both turned into glTF's frame by the root rotation the GLB carries
  (`pbrfit.io.gltf_export.WORLD_TO_GLTF_ROTATION`), exposure 2^EV on the lights, no tone
  mapping. The page (``viewer_check.html``) renders into a float render target (linear, no 8-bit
  rounding) and once to the canvas (sRGB 8-bit, what a viewer shows), and posts the pixels to a
  local HTTP server.

three.js is rendered as it is and then with its own approximations turned off one after the
other (each a shader edit that must find its text): the specular anti-aliasing that adds the
screen-space change of the normal to the roughness, the spherical-Gaussian fit of Schlick's
Fresnel, the multiple-scattering compensation of direct light, the diffuse lobe's Fresnel weight
(the dielectric's F, glTF's fresnel_mix, where pbrfit takes glTF's "simplified" form with the
metallic-blended F) and the trilinear mipmaps. Pixels where the two are known to part are
counted apart (`classify`): the interpolated normal turned from the camera, and pbrfit's shadow
rays at a light's terminator.

Over the pixels both renders cover: the median and 99th percentile of the relative difference
|three - pbrfit| / max(pbrfit, REL_FLOOR) over the pixels' R, G, B values, and of the absolute
difference of the 8-bit sRGB codes. Writes ``experiments/results/viewer_check.json`` and
``viewer_check.png`` (pbrfit, three.js, the relative difference; as is and with the edits).

    npm install --no-save --prefix . three@0.187.0      # ./node_modules/three (git-ignored)
    apt-get install chromium                            # Debian's headless-capable Chromium
    python experiments/viewer_check.py [--scenes sphere plane] [--size 128] [--views 6] [--view 0]
                                       [--quality draft] [--three node_modules/three]

tests/render/test_threejs_viewer.py runs `check` on a small sphere with its truth maps (skipped
without Chromium or three.js). The page's shader edits are written against three.js
`THREE_VERSION`; another release may fail them loudly (the text they replace is gone).
"""

from __future__ import annotations

import argparse
import dataclasses
import http.server
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

import pbrfit  # noqa: F401  (sets the XLA flags pbrfit needs before JAX starts)

ROOT = Path(__file__).resolve().parent.parent
PAGE = Path(__file__).resolve().parent / "viewer_check.html"
RESULTS = Path(__file__).resolve().parent / "results"
#: The three.js release the page's shader edits were written against (``npm install three@...``).
THREE_VERSION = "0.187.0"
#: Floor of the relative difference's denominator, in linear radiance (a white Lambertian surface
#: facing one of the scene's lights at its distance reflects about 0.25): the darkest pixels
#: (faces turned from every light) are compared in absolute terms below it.
REL_FLOOR = 0.01
#: Seconds to wait for the page's pixels.
PAGE_TIMEOUT = 300.0
#: three.js variants, cumulative: (name, shader edits (viewer_check.html's EDITS) turned on, mipmaps).
VARIANTS = (
    ("as_is", (), True),
    ("no_specular_aa", ("no_specular_aa",), True),
    ("exact_schlick", ("no_specular_aa", "exact_schlick"), True),
    ("no_multiscatter", ("no_specular_aa", "exact_schlick", "no_multiscatter"), True),
    ("blended_fresnel_diffuse", ("no_specular_aa", "exact_schlick", "no_multiscatter", "blended_fresnel_diffuse"), True),
    ("no_mipmaps", ("no_specular_aa", "exact_schlick", "no_multiscatter", "blended_fresnel_diffuse"), False),
)


# --- the scene -----------------------------------------------------------------------------------
def make_scene(size: int, views: int, seed: int = 0):
    """A sphere of radius 1 at the origin, +Z up, textured truth with smooth metallic, three white
    point lights of 8 cd at 3 units and 40 degrees elevation, `views` cameras at 3.6 units
    between 10 and 60 degrees elevation, 40 degree field of view, linear EXR, no noise."""
    from data_synth import meshes, presets, rigs, textures
    from pbrfit.physics.model import Model

    up = "+z"
    rng = np.random.default_rng(seed)
    truth = textures.textured_maps(64, rng, metal="smooth")
    mesh = meshes.to_world_up(meshes.uv_sphere(1.0, 96, 48), up)
    cams = rigs.hemisphere(views, 3.6, world_up=up, min_elevation_deg=10.0, max_elevation_deg=60.0, rng=rng)
    lights = presets._light_ring(3, 3.0, 40.0, 8.0, up)
    return presets.Scene(name="viewer-sphere", seed=seed, mesh=mesh, truth=truth, cameras=cams,
                         camera_angle_x=math.radians(40.0), width=size, height=size, lights=lights, world_up=up,
                         model=Model())  # fmt: skip


# --- pbrfit's render -----------------------------------------------------------------------------
def pbrfit_render(capture, view: int, material_dir: Path, **model_changes):
    """View `view` of `capture` rendered by pbrfit with the material in `material_dir`: (linear
    radiance × 2^EV (H, W, 3), alpha (H, W)), before any tone map."""
    from pbrfit.io.material_files import read_material
    from pbrfit.render.views import model_for_capture, render_capture

    frame = dataclasses.replace(capture.frames[view], color_space="linear")
    one = dataclasses.replace(capture, frames=[frame], tonemap="none")
    material = read_material(material_dir)
    model = model_for_capture(one, material, **model_changes)
    (image, alpha), = render_capture(one, material, model, cache_dir=None)
    return np.asarray(image, np.float32), np.asarray(alpha, np.float32)


def eight_bit_material(fit_dir: Path, out: Path) -> Path:
    """A material folder holding only the fit's 8-bit PNG maps (those the GLB carries), which
    `read_material` then reads (sRGB-decoded base color; metallic B, roughness G)."""
    out.mkdir(parents=True, exist_ok=True)
    for name in ("base_color.png", "metallic_roughness.png"):
        shutil.copy2(fit_dir / name, out / name)
    return out


# --- three.js ------------------------------------------------------------------------------------
def _rotation(world_up: str) -> np.ndarray:
    """4 x 4 matrix of the GLB's root rotation, capture world -> glTF's +Y up."""
    from pbrfit.io.gltf_export import WORLD_TO_GLTF_ROTATION

    m = np.eye(4)
    q = WORLD_TO_GLTF_ROTATION[world_up]
    if q is None:
        return m
    x, y, z, w = q
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]  # fmt: skip
    return m


def projection(camera, near: float, far: float) -> np.ndarray:
    """OpenGL projection of a pinhole camera (fx, fy, cx, cy in pixels, pixel centres at k + 0.5,
    row 0 at the top): pixel x = cx + fx X / -Z maps to NDC 2 x / W - 1, pixel y = cy - fy Y / -Z
    to NDC 1 - 2 y / H; depth as ``THREE.PerspectiveCamera``'s."""
    W, H = camera.width, camera.height
    return np.array([
        [2 * camera.fx / W, 0.0, 1.0 - 2 * camera.cx / W, 0.0],
        [0.0, 2 * camera.fy / H, 2 * camera.cy / H - 1.0, 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0],
    ])  # fmt: skip


def scene_json(capture, view: int) -> dict:
    """What the page needs: image size, camera and lights in glTF's frame, the variants."""
    frame = capture.frames[view]
    cam = frame.camera
    rot = _rotation(capture.world_up)
    c2w = rot @ cam.c2w
    radius = float(np.max(np.linalg.norm(np.asarray(capture.mesh.vertices) - cam.c2w[:3, 3], axis=1)))
    scale = 2.0 ** float(frame.exposure)
    lights = []
    for light in frame.lights:
        color = [float(c) for c in np.asarray(light.color)]
        intensity = float(light.intensity) * scale
        if light.kind == "point":
            if float(light.range) > 0:
                raise SystemExit("viewer_check: a point light with a range (three.js squares the window, "
                                 "glTF-Sample-Viewer does not): only range 0 is compared")
            lights.append(dict(type="point", position=list(rot[:3, :3] @ np.asarray(light.position, np.float64)),
                               color=color, intensity=intensity))
        elif light.kind == "directional":
            lights.append(dict(type="directional", direction=list(rot[:3, :3] @ np.asarray(light.direction, np.float64)),
                               color=color, intensity=intensity))
        else:
            raise SystemExit(f"viewer_check: a {light.kind} light (three.js's spot falloff is not glTF's): "
                             "point and directional lights only")
    return dict(width=cam.width, height=cam.height, camera_to_world=list(c2w.reshape(-1)),
                projection=list(projection(cam, 0.01, 2.0 * radius + 1.0).reshape(-1)), lights=lights,
                variants=[dict(name=n, edits=list(e), mipmaps=m, display=(i == 0))
                          for i, (n, e, m) in enumerate(VARIANTS)])


class _Server(http.server.ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, routes: dict[str, Path]):
        self.routes, self.posted, self.done = routes, {}, threading.Event()
        super().__init__(("127.0.0.1", 0), _Handler)


class _Handler(http.server.BaseHTTPRequestHandler):
    TYPES = {".js": "text/javascript", ".html": "text/html", ".json": "application/json",
             ".glb": "model/gltf-binary"}

    def log_message(self, *args):  # quiet
        pass

    def do_GET(self):
        for prefix, folder in self.server.routes.items():
            if self.path.startswith(prefix):
                path = (folder / self.path[len(prefix):].split("?")[0]).resolve()
                if folder.resolve() in path.parents and path.is_file():
                    data = path.read_bytes()
                    self.send_response(200)
                    self.send_header("Content-Type", self.TYPES.get(path.suffix, "application/octet-stream"))
                    self.send_header("Content-Length", str(len(data)))
                    self.end_headers()
                    self.wfile.write(data)
                    return
        self.send_error(404)

    def do_POST(self):
        body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
        self.server.posted[self.path] = body
        self.send_response(204)
        self.end_headers()
        if self.path in ("/done", "/error"):
            self.server.done.set()


def chromium_binary() -> str | None:
    """The Chromium to run headless: $CHROMIUM, else ``chromium`` or ``chromium-browser`` on PATH."""
    return os.environ.get("CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")


def three_js_render(glb: Path, scene: dict, three_dir: Path, work: Path) -> dict:
    """Run the page in headless Chromium (SwiftShader WebGL): per variant, linear RGBA (H, W, 4)
    float32 and, for the first, the canvas's sRGB RGBA (H, W, 4) uint8; row 0 at the top."""
    browser = chromium_binary()
    if browser is None:
        raise SystemExit("viewer_check: no chromium on PATH (apt-get install chromium, or set $CHROMIUM)")
    if not (three_dir / "build" / "three.module.js").is_file():
        raise SystemExit(f"viewer_check: {three_dir}: no three.js (npm install --no-save --prefix . three@{THREE_VERSION})")
    site = work / "site"
    site.mkdir(parents=True, exist_ok=True)
    shutil.copy2(glb, site / "material.glb")
    shutil.copy2(PAGE, site / "page.html")
    (site / "scene.json").write_text(json.dumps(scene))
    server = _Server({"/three/": three_dir, "/scene/": site})
    threading.Thread(target=server.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{server.server_address[1]}/scene/page.html"
    cmd = [browser, "--headless=new", "--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader",
           "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "--no-first-run", "--disable-extensions",
           f"--user-data-dir={work / 'profile'}", url]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        if not server.done.wait(PAGE_TIMEOUT):
            raise SystemExit(f"viewer_check: the page sent no pixels within {PAGE_TIMEOUT:.0f} s")
    finally:
        try:
            os.killpg(proc.pid, signal.SIGTERM)  # the browser we started, and its children
        except ProcessLookupError:
            pass
        proc.wait(timeout=30)
        server.shutdown()
        server.server_close()
    if "/error" in server.posted:
        raise SystemExit("viewer_check: the page failed: " + server.posted["/error"].decode(errors="replace"))
    W, H = scene["width"], scene["height"]
    out = dict(revision=json.loads(server.posted["/done"])["revision"])
    for key, body in server.posted.items():
        if key.startswith("/result/"):
            name = key[len("/result/"):]
            dtype = np.float32 if name.endswith(".f32") else np.uint8
            out[name] = np.frombuffer(body, dtype).reshape(H, W, 4)[::-1].copy()  # GL rows run bottom-up
    return out


# --- the comparison --------------------------------------------------------------------------------
def srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear values -> 8-bit sRGB codes (clipped to [0, 1], rounded), as a canvas holds them."""
    from pbrfit.physics.color import linear_to_srgb_host

    return np.round(np.clip(linear_to_srgb_host(np.clip(linear, 0.0, 1.0)), 0.0, 1.0) * 255.0).astype(np.int32)


def compare(three: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> dict:
    """Over `mask`'s pixels and their R, G, B values: the relative difference |three - ref| /
    max(ref, REL_FLOOR) (median, 99th percentile, max), the signed mean of three / ref - 1 over
    values above REL_FLOOR, and the absolute difference of the 8-bit sRGB codes (median, p99,
    max)."""
    t, r = three[mask], ref[mask]
    rel = np.abs(t - r) / np.maximum(r, REL_FLOOR)
    lit = r > REL_FLOOR
    codes = np.abs(srgb8(t) - srgb8(r))
    return dict(rel_median=float(np.median(rel)), rel_p99=float(np.percentile(rel, 99)), rel_max=float(rel.max()),
                signed_mean=float(np.mean(t[lit] / r[lit] - 1.0)),
                srgb8_median=float(np.median(codes)), srgb8_p99=float(np.percentile(codes, 99)),
                srgb8_max=int(codes.max()))  # fmt: skip


def picture(rows, path: Path) -> None:
    """One row per (label, pbrfit linear, three linear, mask): the two renders (sRGB) and the
    relative difference (colour map, 0 to 10%)."""
    from PIL import Image, ImageDraw

    from pbrfit.io.pictures import colormap, enlarge

    panels = []
    for label, ref, three, mask in rows:
        rel = np.where(mask[..., None], np.abs(three - ref) / np.maximum(ref, REL_FLOOR), 0.0).max(axis=-1)
        row = [srgb8(ref) / 255.0, srgb8(three) / 255.0, colormap(rel / 0.1) * mask[..., None]]
        panels.append((label, np.concatenate([enlarge(p.astype(np.float32), 256) for p in row], axis=1)))
    band = 18
    h, w = panels[0][1].shape[:2]
    canvas = Image.new("RGB", (w, len(panels) * (h + band)), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for i, (label, image) in enumerate(panels):
        y = i * (h + band)
        draw.text((4, y + 3), f"{label}: pbrfit | three.js | relative difference (black 0, yellow >= 10%)",
                  fill=(0, 0, 0))
        canvas.paste(Image.fromarray(np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)), (0, y + band))
    tmp = path.with_suffix(".tmp.png")
    canvas.save(tmp)
    os.replace(tmp, path)


def classify(capture, view: int) -> dict:
    """Pixel classes of `view` where the two renderers are known to part, from pbrfit's G-buffer:
    ``grazing``: the interpolated normal turns from the camera (n·v <= 0: pbrfit shades 0,
    three.js clamps n·v to 0 and its V term stays finite, so a highlight remains);
    ``terminator``: a light with n·l > 0 on the interpolated normal is blocked by pbrfit's shadow
    ray, which the faceted mesh stops near the light's terminator (three.js casts no shadow
    without shadow maps)."""
    from pbrfit.scene.gbuffer import compute_gbuffer

    frame = capture.frames[view]
    g = compute_gbuffer(capture.mesh, frame.camera, frame.lights)
    n_dot_v = np.sum(g.normal * g.view, axis=-1)
    terminator = np.zeros(n_dot_v.shape, bool)
    for k, light in enumerate(frame.lights):
        if light.kind == "directional":
            to_light = -np.asarray(light.direction, np.float64)
        else:
            to_light = np.asarray(light.position, np.float64) - g.position
            to_light = to_light / np.linalg.norm(to_light, axis=-1, keepdims=True)
        n_dot_l = np.sum(g.normal * to_light, axis=-1)
        terminator |= (n_dot_l > 0) & (g.visibility[..., k] < 0.5)
    return dict(grazing=n_dot_v <= 0, terminator=terminator)


def check(capture_dir: Path, material_dir: Path, view: int, three_dir: Path, work: Path) -> dict:
    """Everything compared for one view: pbrfit's renders (float maps, 8-bit maps,
    multiscatter), three.js's (every variant, and the canvas), the mask both cover, the pixel
    classes (`classify`) and the seconds each took."""
    from pbrfit.scene.capture import load_capture

    capture = load_capture(capture_dir)
    times = {}
    t = time.perf_counter()
    ref, alpha = pbrfit_render(capture, view, material_dir)
    ref8, _ = pbrfit_render(capture, view, eight_bit_material(material_dir, work / "material8"))
    ref_ms, _ = pbrfit_render(capture, view, material_dir, multiscatter=True)
    times["pbrfit_render"] = time.perf_counter() - t
    t = time.perf_counter()
    three = three_js_render(material_dir / "material.glb", scene_json(capture, view), three_dir, work)
    times["three_js"] = time.perf_counter() - t
    mask = (alpha > 0.5) & (three["as_is.f32"][..., 3] > 0.5)
    coverage = dict(pbrfit=int((alpha > 0.5).sum()), three=int((three["as_is.f32"][..., 3] > 0.5).sum()),
                    both=int(mask.sum()))
    return dict(ref=ref, ref8=ref8, ref_ms=ref_ms, three=three, mask=mask, coverage=coverage,
                classes=classify(capture, view), seconds=times)


def tables(c: dict) -> dict:
    """`compare` rows of a `check`: each three.js variant against pbrfit's float and 8-bit maps
    (over every pixel both cover, and over those outside the known classes), three.js as is
    against pbrfit with multiscatter, and the canvas against pbrfit encoded to sRGB 8-bit."""
    mask, three = c["mask"], c["three"]
    known = c["classes"]["grazing"] | c["classes"]["terminator"]
    rows = []
    for name, edits, mipmaps in VARIANTS:
        img = three[f"{name}.f32"][..., :3]
        for label, ref in (("float maps", c["ref"]), ("8-bit maps", c["ref8"])):
            rows.append(dict(three=name, edits=list(edits), mipmaps=mipmaps, pbrfit=label, pixels="all",
                             **compare(img, ref, mask)))
            rows.append(dict(three=name, edits=list(edits), mipmaps=mipmaps, pbrfit=label, pixels="unclassed",
                             **compare(img, ref, mask & ~known)))
    rows.append(dict(three="as_is", edits=[], mipmaps=True, pbrfit="float maps, multiscatter=true", pixels="all",
                     **compare(three["as_is.f32"][..., :3], c["ref_ms"], mask)))
    canvas = three["as_is.u8"][..., :3].astype(np.int32)
    codes = np.abs(canvas - srgb8(c["ref"]))[mask]
    display = dict(srgb8_median=float(np.median(codes)), srgb8_p99=float(np.percentile(codes, 99)),
                   srgb8_max=int(codes.max()),
                   canvas_vs_float_target_max=int(np.abs(canvas - srgb8(three["as_is.f32"][..., :3]))[mask].max()))
    classes = {k: int((v & mask).sum()) for k, v in c["classes"].items()}
    return dict(rows=rows, canvas=display, classes=classes, coverage=c["coverage"])


SCENES = ("sphere", "plane")


def scene_for(name: str, size: int, views: int, seed: int):
    """``sphere``: `make_scene`; ``plane``: the ``peer-plane`` preset (a flat, +Z-up 2 x 2 plane
    under four point lights, metallic 0), where three.js's specular anti-aliasing adds nothing."""
    if name == "sphere":
        return make_scene(size, views, seed)
    from data_synth.presets import make_scene as preset

    return preset("peer-plane", seed=seed, size=size, views=views)


def run(args) -> dict:
    from data_synth.writer import synthesize

    out, pictures = {}, []
    for name in args.scenes:
        times = {}
        with tempfile.TemporaryDirectory(prefix="viewer_check_") as tmp:
            work = Path(tmp)
            t = time.perf_counter()
            synthesize(scene_for(name, args.size, args.views, args.seed), work / "capture", write_contact_sheet=False)
            times["synth"] = time.perf_counter() - t
            t = time.perf_counter()
            subprocess.run([sys.executable, "-m", "pbrfit.cli.main", "fit", str(work / "capture"), "--out",
                            str(work / "fit"), "--quality", args.quality, "--no-cache", "--quiet"], check=True,
                           cwd=ROOT)  # fmt: skip
            times["fit"] = time.perf_counter() - t
            c = check(work / "capture", work / "fit", args.view, args.three, work)
        times.update(c["seconds"])
        out[name] = dict(tables(c), seconds=times)
        last = VARIANTS[-1][0]
        pictures += [(f"{name}: three.js as is vs pbrfit (float maps)", c["ref"], c["three"]["as_is.f32"][..., :3],
                      c["mask"]),
                     (f"{name}: three.js with its approximations off ({last}) vs pbrfit (8-bit maps)", c["ref8"],
                      c["three"][f"{last}.f32"][..., :3], c["mask"])]  # fmt: skip
        revision = c["three"]["revision"]
    picture(pictures, RESULTS / "viewer_check.png")
    def shown(v):  # paths inside the repository as relative ones
        if not isinstance(v, Path):
            return v
        v = v.resolve()
        return str(v.relative_to(ROOT)) if ROOT in v.parents else str(v)

    params = {k: shown(v) for k, v in vars(args).items()}
    return dict(three_revision=revision, chromium=chromium_version(), params=params, rel_floor=REL_FLOOR,
                scenes=out)


def chromium_version() -> str:
    try:
        return subprocess.run([chromium_binary(), "--version"], capture_output=True, text=True, timeout=60).stdout.strip()
    except (OSError, subprocess.SubprocessError, TypeError):
        return ""


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=128, help="image width and height (default 128)")
    ap.add_argument("--views", type=int, default=6, help="views of the capture that is fitted (default 6)")
    ap.add_argument("--view", type=int, default=0, help="the view compared (default 0)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenes", nargs="+", choices=SCENES, default=list(SCENES))
    ap.add_argument("--quality", default="draft", help="the fit's --quality (default draft: the fit's accuracy is not measured here)")
    ap.add_argument("--three", type=Path, default=ROOT / "node_modules" / "three", help="the three package's folder")
    ap.add_argument("--out", type=Path, default=RESULTS / "viewer_check.json")
    args = ap.parse_args()
    result = run(args)
    text = json.dumps(result, indent=1)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(text + "\n")
    os.replace(tmp, args.out)
    for scene, r in result["scenes"].items():
        print(f"{scene}: pixels {r['coverage']}, classes {r['classes']}, seconds "
              + ", ".join(f"{k} {v:.1f}" for k, v in r["seconds"].items()))
        for row in r["rows"]:
            print(f"  {row['three']:24s} vs {row['pbrfit']:30s} {row['pixels']:9s} rel median {row['rel_median']:.4f}"
                  f" p99 {row['rel_p99']:.4f} max {row['rel_max']:.3f} signed {row['signed_mean']:+.4f} | sRGB8 median"
                  f" {row['srgb8_median']:.0f} p99 {row['srgb8_p99']:.0f} max {row['srgb8_max']}")
        print("  canvas (sRGB 8-bit) vs pbrfit float maps:", r["canvas"])


if __name__ == "__main__":
    main()
