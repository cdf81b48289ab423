"""Independent reference renderer for pbrfit-capture/1 captures (numpy, float64).

Written from the capture spec (`shared/spec/capture-format.md`), the glTF 2.0 specification
(Appendix B: BRDF implementation) and KHR_lights_punctual, without importing pbrfit, so that
rendering a capture here and with `pbrfit render` checks pbrfit's reading of the spec rather
than pbrfit against itself. It ray-casts pixel centres (no antialiasing), samples textures
bilinearly, and sums punctual lights exactly and an environment pixel by pixel (every
non-black environment pixel as a directional light of its solid angle: exact for the sparse
environments of the conformance cases, no split-sum or importance sampling).

Where the spec is silent the renderer takes the readings the pbrfit README lists: textures
repeat (glTF's default sampler), surfaces are two-sided, `fl_x` intrinsics put pixel centres at
i + 0.5, a frame's EV is `images.exposure + frames[].exposure`, and `world_up` +z turns the +y
environment convention with the world. `Conventions` holds the choices that a slip could change,
so that the size of each slip can be measured.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio


@dataclass(frozen=True)
class Conventions:
    """Convention choices; the defaults are the spec's (`run.py` perturbs them one at a time).

    pixel_centre: pixel (i, j) is sampled at (j + pixel_centre, i + pixel_centre) (spec: 0.5).
    texel_centre: texel (i, j) has its centre at uv ((j + c)/W, (i + c)/H) (spec: 0.5).
    wrap: "repeat" (glTF's default sampler, REPEAT 10497) or "clamp" (CLAMP_TO_EDGE).
    flip_v: read texel row 0 as v = 1 (the OBJ/OpenGL image convention) instead of glTF's v = 0.
    """

    pixel_centre: float = 0.5
    texel_centre: float = 0.5
    wrap: str = "repeat"
    flip_v: bool = False


SPEC = Conventions()

# ----------------------------------------------------------------------------- images


def write_image(path, arr):
    """Write an H x W x C float image: EXR as float32 (linear values as given); any other
    extension as 16-bit unsigned integers of the values clipped to [0, 1] (already display
    encoded). Four channels are written as RGBA with alpha marked."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.asarray(arr, float)
    arr = arr[:, :, None] if arr.ndim == 2 else arr
    h, w, c = arr.shape
    if path.suffix == ".exr":
        spec, data = oiio.ImageSpec(w, h, c, oiio.FLOAT), arr.astype(np.float32)
    else:
        spec = oiio.ImageSpec(w, h, c, oiio.UINT16)
        data = np.round(np.clip(arr, 0, 1) * 65535).astype(np.uint16)
    spec.channelnames = {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}[c]
    if c == 4:
        spec.alpha_channel = 3
    out = oiio.ImageOutput.create(str(path))
    assert out and out.open(str(path), spec), oiio.geterror()
    assert out.write_image(data), out.geterror()
    out.close()


def read_image(path):
    """Read an image as float64 H x W x C (OpenImageIO normalises integer formats to [0, 1])."""
    inp = oiio.ImageInput.open(str(path))
    assert inp, oiio.geterror()
    spec = inp.spec()
    data = np.asarray(inp.read_image(oiio.FLOAT), float).reshape(spec.height, spec.width, spec.nchannels)
    inp.close()
    return data


def srgb_encode(x):
    """IEC 61966-2-1: 12.92 x below 0.0031308, else 1.055 x^(1/2.4) - 0.055 (x clipped to [0, 1])."""
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def srgb_decode(y):
    """Inverse of `srgb_encode`: y / 12.92 below 0.04045, else ((y + 0.055) / 1.055)^2.4."""
    y = np.clip(y, 0, 1)
    return np.where(y <= 0.04045, y / 12.92, np.power((y + 0.055) / 1.055, 2.4))


def color_space(cap, path):
    """`images.color_space`, defaulting by file type (spec: linear for EXR/HDR, else sRGB)."""
    default = "linear" if str(path).endswith((".exr", ".hdr")) else "srgb"
    return cap.get("images", {}).get("color_space", default)


def encode(radiance, alpha, cap, path):
    """Exposed radiance -> stored pixel values: the tone map (`images.tonemap`; `reinhard` is
    x / (1 + x) per channel, `none` the identity), then sRGB encoding where the color space
    is sRGB; alpha appended as a fourth channel."""
    tm = cap.get("images", {}).get("tonemap", "none")
    if tm not in ("none", "reinhard"):
        raise NotImplementedError(tm)
    x = radiance / (1 + radiance) if tm == "reinhard" else radiance
    if color_space(cap, path) == "srgb":
        x = srgb_encode(x)
    return np.concatenate([x, alpha[..., None]], -1)


def decode(img, cap, path):
    """Stored pixel values -> exposed linear radiance (inverse of `encode`, RGB only)."""
    x = img[..., :3]
    if color_space(cap, path) == "srgb":
        x = srgb_decode(x)
    if cap.get("images", {}).get("tonemap", "none") == "reinhard":
        x = x / np.maximum(1 - x, 1e-6)
    return x


# ----------------------------------------------------------------------------- cameras


def look_at(eye, target, up):
    """Camera-to-world 4x4 looking from `eye` at `target`: the camera looks down its -Z axis,
    +Y up, +X right (spec: `transform_matrix`, OpenGL/Blender/NeRF)."""
    eye, target, up = (np.asarray(a, float) for a in (eye, target, up))
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(right, fwd), -fwd, eye
    return m


def intrinsics(cap, frame, width, height):
    """(fx, fy, cx, cy) in pixels. A frame's own `fl_x`, `fl_y`, `cx`, `cy` override the
    capture's (spec: "a frame may carry its own"); `fl_y` defaults to `fl_x`, the principal
    point to the image centre. Without them, fx = fy = (W / 2) / tan(camera_angle_x / 2)."""
    keys = ("fl_x", "fl_y", "cx", "cy", "camera_angle_x")
    k = {**{n: cap[n] for n in keys if n in cap}, **{n: frame[n] for n in keys if n in frame}}
    if "fl_x" in k:
        fx = k["fl_x"]
        return fx, k.get("fl_y", fx), k.get("cx", width / 2), k.get("cy", height / 2)
    fx = 0.5 * width / np.tan(0.5 * k["camera_angle_x"])
    return fx, fx, width / 2, height / 2


def camera_rays(c2w, width, height, fx, fy, cx, cy, conv=SPEC):
    """World ray origins and unit directions of every pixel, (H, W, 3) each. Pixel (i, j)
    (row i from the top) is sampled at image point (j + 0.5, i + 0.5); its camera-space
    direction is ((x - cx) / fx, -(y - cy) / fy, -1): image rows grow downwards, camera +Y up."""
    c2w = np.asarray(c2w, float)
    x, y = np.meshgrid(np.arange(width) + conv.pixel_centre, np.arange(height) + conv.pixel_centre)
    d = np.stack([(x - cx) / fx, -(y - cy) / fy, -np.ones_like(x)], -1) @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.broadcast_to(c2w[:3, 3], d.shape).copy(), d


# ----------------------------------------------------------------------------- geometry


def trace_triangles(o, d, vertices, faces, uvs):
    """Nearest hit of each ray with a triangle mesh (Moller-Trumbore, one triangle at a time:
    for the few-triangle meshes of the plane cases). Returns t (inf where missed), hit mask,
    interpolated glTF uv and the unit geometric normal (e1 x e2)."""
    shape = o.shape[:-1]
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t_best = np.full(len(o), np.inf)
    uv, normal = np.zeros((len(o), 2)), np.zeros((len(o), 3))
    for f in faces:
        a = vertices[f[0]]
        e1, e2 = vertices[f[1]] - a, vertices[f[2]] - a
        p = np.cross(d, e2)
        det = p @ e1
        inv = np.where(np.abs(det) > 1e-12, 1 / np.where(det == 0, 1, det), 0)
        s = o - a
        q = np.cross(s, e1)
        b1, b2, t = (s * p).sum(-1) * inv, (d * q).sum(-1) * inv, (q @ e2) * inv
        hit = (inv != 0) & (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1) & (t > 1e-9) & (t < t_best)
        t_best[hit] = t[hit]
        uv[hit] = ((1 - b1 - b2)[:, None] * uvs[f[0]] + b1[:, None] * uvs[f[1]] + b2[:, None] * uvs[f[2]])[hit]
        n = np.cross(e1, e2)
        normal[hit] = n / np.linalg.norm(n)
    hit = np.isfinite(t_best)
    return t_best.reshape(shape), hit.reshape(shape), uv.reshape(shape + (2,)), normal.reshape(shape + (3,))


def trace_sphere(o, d, centre, radius):
    """Nearest hit of each ray with an analytic sphere: t = -b - sqrt(b^2 - c) with
    b = (o - centre).d, c = |o - centre|^2 - r^2. Returns t, hit, uv (zeros: the sphere cases
    use a uniform material) and the outward normal."""
    oc = o - np.asarray(centre, float)
    b = (oc * d).sum(-1)
    disc = b * b - (oc * oc).sum(-1) + radius ** 2
    t = -b - np.sqrt(np.maximum(disc, 0))
    hit = (disc > 0) & (t > 0)
    normal = (oc + t[..., None] * d) / radius
    return np.where(hit, t, np.inf), hit, np.zeros(o.shape[:-1] + (2,)), normal


# ----------------------------------------------------------------------------- textures


def sample_bilinear(tex, uv, conv=SPEC):
    """Bilinear lookup of an H x W (x C) texture at glTF uv. Spec: texel row 0 is v = 0, texel
    (i, j) has its centre at ((j + 0.5) / W, (i + 0.5) / H); so x = u W - 0.5, y = v H - 0.5 and
    the four texels around (x, y) are blended. Wrap: repeat (glTF's default sampler)."""
    tex = tex[:, :, None] if tex.ndim == 2 else tex
    h, w, _ = tex.shape
    v = 1 - uv[..., 1] if conv.flip_v else uv[..., 1]
    x, y = uv[..., 0] * w - conv.texel_centre, v * h - conv.texel_centre
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    x0, y0 = x0.astype(int), y0.astype(int)
    if conv.wrap == "repeat":
        x1, y1, x0, y0 = (x0 + 1) % w, (y0 + 1) % h, x0 % w, y0 % h
    else:
        x1, y1 = np.clip(x0 + 1, 0, w - 1), np.clip(y0 + 1, 0, h - 1)
        x0, y0 = np.clip(x0, 0, w - 1), np.clip(y0, 0, h - 1)
    return ((1 - fx) * (1 - fy) * tex[y0, x0] + fx * (1 - fy) * tex[y0, x1]
            + (1 - fx) * fy * tex[y1, x0] + fx * fy * tex[y1, x1])


# ----------------------------------------------------------------------------- BRDF


def _dot(a, b):
    return (a * b).sum(-1, keepdims=True)


def brdf(n, v, l, base, metal, rough):
    """glTF 2.0 Appendix B metallic-roughness BRDF f(v, l) (arrays (..., 3); metal, rough (..., 1)),
    in the Appendix's combined form (f0 mixed by metallic, one Fresnel term for both lobes).

    alpha = roughness^2 (perceptual roughness, spec: "alpha = roughness^2"), h = (v + l) / |v + l|;
    D = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2)                         (Trowbridge-Reitz)
    V = G / (4 |n.l| |n.v|) with the separable Smith G = G1(l) G1(v),
        G1(x) = 2 |n.x| / (|n.x| + sqrt(alpha^2 + (1 - alpha^2)(n.x)^2)), so
    V = 1 / ((|n.l| + sqrt(alpha^2 + (1 - alpha^2)(n.l)^2)) (|n.v| + sqrt(alpha^2 + (1 - alpha^2)(n.v)^2)))
    F = f0 + (1 - f0) (1 - |v.h|)^5,  f0 = mix(0.04, base, metallic)                 (Schlick)
    f = (1 - F) base (1 - metallic) / pi + F D V.
    """
    a2 = (rough ** 2) ** 2
    h = v + l
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    nl, nv, nh, vh = _dot(n, l), _dot(n, v), _dot(n, h), _dot(v, h)
    d = a2 / (np.pi * (nh ** 2 * (a2 - 1) + 1) ** 2)
    vis = 1 / ((np.abs(nl) + np.sqrt(a2 + (1 - a2) * nl ** 2)) * (np.abs(nv) + np.sqrt(a2 + (1 - a2) * nv ** 2)))
    f0 = 0.04 * (1 - metal) + base * metal
    f = f0 + (1 - f0) * (1 - np.abs(vh)) ** 5
    return (1 - f) * base * (1 - metal) / np.pi + f * d * vis


# ----------------------------------------------------------------------------- lights


def light_terms(light, p):
    """Unit direction to the light and irradiance at normal incidence for points p (..., 3).

    KHR_lights_punctual: directional: l = -direction, E = color * intensity (lux);
    point: E = color * intensity * window(d) / d^2 (intensity in candela), window(d) =
    clamp(1 - (d / range)^4, 0, 1) when range > 0 else 1 (spec, as glTF-Sample-Viewer);
    spot: the point term times t^2, t = clamp((cos_d - cos_outer) / (cos_inner - cos_outer), 0, 1),
    cos_d the cosine between the spot's direction and the direction from light to point
    (inner_cone_angle default 0, outer_cone_angle default pi/4).
    """
    color = np.asarray(light.get("color", [1, 1, 1]), float) * float(light.get("intensity", 1.0))
    if light["type"] == "directional":
        travel = np.asarray(light["direction"], float)
        return np.broadcast_to(-travel / np.linalg.norm(travel), p.shape), np.broadcast_to(color, p.shape)
    to_light = np.asarray(light["position"], float) - p
    dist = np.linalg.norm(to_light, axis=-1, keepdims=True)
    l = to_light / dist
    rng = float(light.get("range", 0) or 0)
    window = np.clip(1 - (dist / rng) ** 4, 0, 1) if rng > 0 else 1.0
    e = color * window / dist ** 2
    if light["type"] == "spot":
        axis = np.asarray(light["direction"], float)
        cos_in = np.cos(light.get("inner_cone_angle", 0.0))
        cos_out = np.cos(light.get("outer_cone_angle", np.pi / 4))
        t = np.clip((_dot(-l, axis / np.linalg.norm(axis)) - cos_out) / max(cos_in - cos_out, 1e-3), 0, 1)
        e = e * t * t
    return l, e


def frame_lights(cap, frame):
    """The lights on in a frame: the global `lights`, the frame's own `lights` (added, spec),
    and the `flash`: a point light at the camera centre plus `offset` in camera space."""
    lights = list(cap.get("lights", [])) + list(frame.get("lights", []))
    if "flash" in cap:
        fl, c2w = cap["flash"], np.asarray(frame["transform_matrix"], float)
        pos = c2w[:3, :3] @ np.asarray(fl.get("offset", [0, 0, 0]), float) + c2w[:3, 3]
        lights.append({"type": "point", "position": pos, "color": fl.get("color", [1, 1, 1]),
                       "intensity": fl.get("intensity", 1.0), "range": 0})
    return lights


# ----------------------------------------------------------------------------- environment

ENV_VARIANTS = ("spec", "mirror", "flip", "rot90", "rot180", "rot270")


def env_directions(height, width, world_up="+y", rotation_deg=0.0, variant="spec"):
    """World direction (unit) and solid angle of each pixel centre of an equirectangular image.

    Spec: the top row looks along `world_up`; with +y the image centre looks along -Z and u grows
    with azimuth atan2(x, -z). So row r has polar angle theta = pi (r + 0.5) / H from up, column
    c azimuth phi = 2 pi ((c + 0.5) / W - 0.5), direction (sin theta sin phi, cos theta,
    -sin theta cos phi), solid angle (2 pi / W)(pi / H) sin theta. `rotation_deg` turns the
    environment counter-clockwise seen from above (pbrfit README), which lowers phi. With +z the
    same directions are turned with the world, (x, y, z)_+y = (x, z, -y)_+z: the centre looks
    along +Y and u grows with atan2(x, y).

    `variant` gives the wrong readings to compare against: "mirror" (u grows with -phi),
    "flip" (top row looks along -up), "rot90"/"rot180"/"rot270" (phi offset by that many degrees).
    """
    theta, phi = np.meshgrid(np.pi * (np.arange(height) + 0.5) / height,
                             2 * np.pi * ((np.arange(width) + 0.5) / width - 0.5), indexing="ij")
    solid_angle = (2 * np.pi / width) * (np.pi / height) * np.sin(theta)
    if variant == "mirror":
        phi = -phi
    elif variant == "flip":
        theta = np.pi - theta
    elif variant.startswith("rot"):
        phi = phi + np.deg2rad(float(variant[3:]))
    phi = phi - np.deg2rad(rotation_deg)
    x, y, z = np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)
    if world_up == "+y":
        return np.stack([x, y, z], -1), solid_angle
    if world_up == "+z":
        return np.stack([x, -z, y], -1), solid_angle
    raise ValueError(world_up)


def env_radiance(n, v, base, metal, rough, env, cap, variant="spec", chunk=64):
    """Light reflected from `environment` at points with normal n, view v (flattened (P, 3)):
    sum over environment pixels k of f(v, l_k) max(n.l_k, 0) L_k dOmega_k * intensity. Black
    pixels are skipped, so a sparse environment costs a few directions."""
    info = cap["environment"]
    dirs, dom = env_directions(env.shape[0], env.shape[1], cap.get("world_up", "+y"),
                               float(info.get("rotation_deg", 0.0)), variant)
    rad = env[..., :3].reshape(-1, 3) * dom.reshape(-1, 1) * float(info.get("intensity", 1.0))
    keep = rad.max(-1) > 0
    dirs, rad = dirs.reshape(-1, 3)[keep], rad[keep]
    out = np.zeros(n.shape)
    for k in range(0, len(dirs), chunk):
        l = np.broadcast_to(dirs[None, k:k + chunk], (len(n), len(dirs[k:k + chunk]), 3))
        f = brdf(n[:, None], v[:, None], l, base[:, None], metal[:, None], rough[:, None])
        out += (f * np.maximum(_dot(n[:, None], l), 0) * rad[None, k:k + chunk]).sum(1)
    return out


# ----------------------------------------------------------------------------- render


def render(cap, frame, geom, material, width, height, env=None, variant="spec", conv=SPEC):
    """Exposed linear radiance (H, W, 3) and coverage (H, W) of one frame.

    geom: {"kind": "tris", "V", "F", "UV"} or {"kind": "sphere", "center", "r"}.
    material: maps {"base" (h, w, 3), "metal" (h, w), "rough" (h, w)}, or
    {"uniform": True, "base": rgb, "metal": m, "rough": r}.
    Outgoing radiance L = sum over lights f(v, l) E max(n.l, 0) (+ the environment term), with the
    normal turned towards the camera (two-sided), times 2^(images.exposure + frame.exposure).
    """
    fx, fy, cx, cy = intrinsics(cap, frame, width, height)
    o, d = camera_rays(frame["transform_matrix"], width, height, fx, fy, cx, cy, conv)
    if geom["kind"] == "tris":
        t, hit, uv, n = trace_triangles(o, d, geom["V"], geom["F"], geom["UV"])
    else:
        t, hit, uv, n = trace_sphere(o, d, geom["center"], geom["r"])
    p, v = o + np.where(hit, t, 0)[..., None] * d, -d
    n = np.where(_dot(n, v) < 0, -n, n)
    if material.get("uniform"):
        base = np.broadcast_to(np.asarray(material["base"], float), p.shape)
        metal = np.full(p.shape[:-1] + (1,), float(material["metal"]))
        rough = np.full(p.shape[:-1] + (1,), float(material["rough"]))
    else:
        base, metal, rough = (sample_bilinear(material[k], uv, conv) for k in ("base", "metal", "rough"))
    radiance = np.zeros(p.shape)
    for light in frame_lights(cap, frame):
        l, e = light_terms(light, p)
        radiance += brdf(n, v, l, base, metal, rough) * e * np.maximum(_dot(n, l), 0)
    if env is not None:
        flat = radiance.reshape(-1, 3)
        m = hit.reshape(-1)
        flat[m] += env_radiance(n.reshape(-1, 3)[m], v.reshape(-1, 3)[m], base.reshape(-1, 3)[m],
                                metal.reshape(-1, 1)[m], rough.reshape(-1, 1)[m], env, cap, variant)
    ev = float(cap.get("images", {}).get("exposure", 0.0)) + float(frame.get("exposure", 0.0))
    radiance = radiance * 2.0 ** ev
    radiance[~hit] = 0
    return radiance, hit.astype(float)
