"""Conformance captures: pbrfit-capture/1 folders rendered by the reference renderer.

Plane cases: a 2 x 2 plane (two triangles) at the origin with a 32 x 32 material of smooth
ramps and asymmetric patches (a flipped or shifted reading of u or v shows), six cameras on an
orbit at 45 degrees elevation, and by default four point lights. Environment cases: a white
diffuse unit sphere (uniform material; the mesh is a 48 x 96 UV sphere, the reference traces the
analytic sphere) under a black 64 x 32 environment with one bright 2 x 2 pixel patch, seen by a
camera on the patch's direction and four around the sphere. Every case holds `truth/` (the maps
that rendered it), so `pbrfit render CAP --material CAP/truth` should reproduce its images.

    build(name, root) -> the capture folder root/name
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

import reference as ref

SIZE = 96  # image width and height unless a case says otherwise
EXPOSURES = [1.0, -0.5, 2.0, 0.5, 1.5, -1.0]  # per-frame EV of the exposure cases

# ----------------------------------------------------------------------------- scene pieces


def from_zup(world_up, p):
    """A point or direction authored in a +z world, in the requested world: +y maps
    (x, y, z) -> (x, z, -y), the glTF/Blender exporter's turn."""
    p = np.asarray(p, float)
    return p if world_up == "+z" else np.array([p[0], p[2], -p[1]])


def plane_geometry(world_up):
    """The plane [-1, 1]^2 on the ground of either world, uv covering [0, 1]^2 with the same
    texels at the same world points in both worlds (v = 0 at authored y = +1)."""
    vz = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    uv = np.stack([(vz[:, 0] + 1) / 2, (1 - vz[:, 1]) / 2], -1)
    verts = np.array([from_zup(world_up, p) for p in vz])
    return dict(kind="tris", V=verts, F=np.array([[0, 1, 2], [0, 2, 3]]), UV=uv)


def texel_positions(world_up, res=32):
    """World position of each texel centre of a res x res map on the plane (inverse of the uv of
    `plane_geometry`: authored x = 2u - 1, y = 1 - 2v)."""
    i, j = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    x, y = 2 * (j + 0.5) / res - 1, 1 - 2 * (i + 0.5) / res
    return np.stack([x, y, np.zeros_like(x)], -1) if world_up == "+z" else np.stack([x, np.zeros_like(x), -y], -1)


def truth_material(res=32):
    """Base colour ramps in u and v with red, green and blue blocks in three corners, a metal
    block, roughness ramping from 0.2 to 0.8 with two constant blocks."""
    i, j = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    u, v = (j + 0.5) / res, (i + 0.5) / res
    base = np.stack([0.15 + 0.6 * u, np.full_like(u, 0.5), 0.7 - 0.5 * v], -1)
    base[2:10, 3:12] = [0.9, 0.1, 0.1]
    base[20:30, 22:29] = [0.1, 0.8, 0.2]
    base[4:9, 24:30] = [0.05, 0.1, 0.85]
    metal = np.zeros((res, res))
    metal[14:24, 4:14] = 1.0
    rough = 0.2 + 0.6 * (0.7 * u + 0.3 * v)
    rough[2:10, 3:12] = 0.3
    rough[20:30, 22:29] = 0.75
    return dict(base=base, metal=metal, rough=rough)


def orbit_cameras(world_up, n=6, elevation_deg=45.0, dist=3.5, az0_deg=15.0):
    """n cameras on a circle around the origin, all looking at it."""
    up, el = from_zup(world_up, [0, 0, 1]), np.deg2rad(elevation_deg)
    mats = []
    for k in range(n):
        az = np.deg2rad(az0_deg + 360 * k / n)
        eye = dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        mats.append(ref.look_at(from_zup(world_up, eye), [0, 0, 0], up))
    return mats


def point_lights(world_up):
    """Four coloured point lights above the plane (candela)."""
    spec = [([2.0, 1.0, 2.5], [1.0, 0.95, 0.9], 12.0), ([-2.0, 1.5, 2.0], [0.9, 0.95, 1.0], 10.0),
            ([0.5, -2.2, 2.2], [1.0, 1.0, 1.0], 9.0), ([-1.0, -1.0, 3.0], [1.0, 0.9, 1.0], 8.0)]
    return [{"type": "point", "position": from_zup(world_up, p).tolist(), "color": c, "intensity": i, "range": 0}
            for p, c, i in spec]


# ----------------------------------------------------------------------------- files


def write_truth(folder, material):
    """truth/ in the fit-output layout: base_color.exr (RGB), metallic.exr, roughness.exr."""
    if material.get("uniform"):
        material = dict(base=np.asarray(material["base"], float)[None, None],
                        metal=np.full((1, 1), material["metal"]), rough=np.full((1, 1), material["rough"]))
    folder = Path(folder)
    ref.write_image(folder / "base_color.exr", material["base"])
    ref.write_image(folder / "metallic.exr", material["metal"])
    ref.write_image(folder / "roughness.exr", material["rough"])


def read_glb(path):
    """POSITION and TEXCOORD_0 of the first primitive of a GLB, read from the binary chunk."""
    b = Path(path).read_bytes()
    (jlen,) = struct.unpack_from("<I", b, 12)
    js = json.loads(b[20:20 + jlen])
    buf = b[20 + jlen + 8:]
    assert all(np.allclose(nd.get("matrix", np.eye(4).ravel()), np.eye(4).ravel()) and
               not {"rotation", "translation", "scale"} & set(nd) for nd in js.get("nodes", []))

    def accessor(i):
        a = js["accessors"][i]
        view = js["bufferViews"][a["bufferView"]]
        ncomp = {"VEC2": 2, "VEC3": 3}[a["type"]]
        start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
        return np.frombuffer(buf, np.float32, a["count"] * ncomp, start).reshape(-1, ncomp).astype(float)

    attrs = js["meshes"][0]["primitives"][0]["attributes"]
    return accessor(attrs["POSITION"]), accessor(attrs["TEXCOORD_0"])


def write_mesh(path, verts, faces, uv):
    """Write the mesh with glTF uv (v = 0 at the top of the image) through trimesh, which keeps
    OBJ-style uv (v up): it is handed v_obj = 1 - v. The written file is read back without
    trimesh to check that the GLB holds glTF TEXCOORD_0 and the OBJ holds OBJ vt = (u, 1 - v)."""
    import trimesh
    from PIL import Image

    uv_obj = uv * [1, -1] + [0, 1]
    visual = trimesh.visual.TextureVisuals(uv=uv_obj, material=trimesh.visual.material.SimpleMaterial(
        image=Image.fromarray(np.full((4, 4, 3), 200, np.uint8))))
    trimesh.Trimesh(vertices=verts, faces=faces, process=False, visual=visual).export(path)
    if str(path).endswith(".glb"):
        pos, stored, expect = *read_glb(path), uv
    else:
        lines = Path(path).read_text().splitlines()
        pos = np.array([[float(x) for x in ln.split()[1:4]] for ln in lines if ln.startswith("v ")])
        stored = np.array([[float(x) for x in ln.split()[1:3]] for ln in lines if ln.startswith("vt ")])
        expect = uv_obj
    for k, p in enumerate(verts):
        m = np.flatnonzero(np.all(np.abs(pos - p) < 1e-6, 1))
        assert len(m) and np.allclose(stored[m[0]], expect[k], atol=1e-6), (path, k)


def write_capture(folder, cap, geom, material, width, height, ext=".exr", mesh_file="mesh.glb", env=None):
    """Render every frame with the reference renderer and write the capture folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cap["mesh"] = mesh_file
    if geom["kind"] == "tris":
        write_mesh(folder / mesh_file, geom["V"], geom["F"], geom["UV"])
    else:
        write_mesh(folder / mesh_file, *sphere_mesh())
    if env is not None:
        ref.write_image(folder / cap["environment"]["file"], env)
    for k, frame in enumerate(cap["frames"]):
        frame["file_path"] = f"images/{k:03d}{ext}"
        radiance, alpha = ref.render(cap, frame, geom, material, width, height, env=env)
        ref.write_image(folder / frame["file_path"], ref.encode(radiance, alpha, cap, frame["file_path"]))
    (folder / "capture.json").write_text(json.dumps(cap, indent=1))
    write_truth(folder / "truth", material)
    return folder


# ----------------------------------------------------------------------------- plane cases


def plane_case(folder, world_up="+z", width=SIZE, height=SIZE, lights=None, frame_keys=None,
               ext=".exr", mesh_file="mesh.glb", **cap_keys):
    """A plane capture; frame_keys(k) gives extra keys of frame k, cap_keys extra capture keys
    (camera_angle_x 0.75 unless intrinsics are given)."""
    frames = [{"transform_matrix": m.tolist(), **(frame_keys(k) if frame_keys else {})}
              for k, m in enumerate(orbit_cameras(world_up))]
    if "fl_x" not in cap_keys:
        cap_keys.setdefault("camera_angle_x", 0.75)
    cap = {"format": "pbrfit-capture/1", "mesh": mesh_file, "world_up": world_up, "frames": frames,
           "lights": point_lights(world_up) if lights is None else lights, **cap_keys}
    return write_capture(folder, cap, plane_geometry(world_up), truth_material(), width, height, ext, mesh_file)


def intrinsics_case(folder):
    """128 x 96 images, per-frame fl_x, fl_y, cx, cy (off-centre) overriding global ones."""
    return plane_case(folder, "+y", width=128, height=96,
                      frame_keys=lambda k: {"fl_x": 150.0 + 5 * k, "fl_y": 140.0 + 3 * k,
                                            "cx": 52.0 + 4 * k, "cy": 40.0 + 2 * k},
                      fl_x=999.0, fl_y=999.0, cx=64.0, cy=48.0, w=128, h=96)


def spot_lights(wu):
    """One spot light above the plane, tilted, cones 0.15 / 0.45 rad: part of the plane is dark."""
    return [{"type": "spot", "position": from_zup(wu, [0.4, 0.3, 2.5]).tolist(),
             "direction": from_zup(wu, [-0.15, -0.1, -1]).tolist(), "color": [1, 1, 1], "intensity": 30.0,
             "range": 0, "inner_cone_angle": 0.15, "outer_cone_angle": 0.45}]


def frame_light(k):
    """One extra point light per frame, at a different place in each frame (+y world)."""
    return {"lights": [{"type": "point", "position": from_zup("+y", [np.cos(k), np.sin(k), 1.5]).tolist(),
                        "color": [1, 1, 1], "intensity": 5.0, "range": 0}]}


PNG_REINHARD = {"color_space": "srgb", "tonemap": "reinhard"}

PLANE_CASES = {
    # name: (what it exercises, builder(folder))
    "c1_plane_zup": ("+z world, camera_angle_x, linear EXR, 4 point lights",
                     lambda f: plane_case(f, "+z")),
    "c1_plane_yup": ("the same scene in a +y world", lambda f: plane_case(f, "+y")),
    "c2_intrinsics": ("per-frame fl_x/fl_y/cx/cy overriding global ones, 128x96 images",
                      intrinsics_case),
    "c3_png_reinhard": ("16-bit sRGB PNG, Reinhard tone map, per-frame exposure",
                        lambda f: plane_case(f, frame_keys=lambda k: {"exposure": EXPOSURES[k]},
                                             ext=".png", images=dict(PNG_REINHARD))),
    "c3b_png_reinhard_globalev": ("as c3 plus images.exposure 0.7 (EV = global + frame)",
                                  lambda f: plane_case(f, frame_keys=lambda k: {"exposure": EXPOSURES[k]},
                                                       ext=".png", images={**PNG_REINHARD, "exposure": 0.7})),
    "c5_obj": ("c1_plane_zup with an OBJ mesh (vt = (u, 1 - v))",
               lambda f: plane_case(f, mesh_file="mesh.obj")),
    "c6_spot": ("one spot light (cone falloff), +y world", lambda f: plane_case(f, "+y", lights=spot_lights("+y"))),
    "c6_directional": ("one directional light (lux), +y world",
                       lambda f: plane_case(f, "+y", lights=[{
                           "type": "directional", "direction": from_zup("+y", [-0.5, 0.3, -1]).tolist(),
                           "color": [1, 0.9, 0.8], "intensity": 2.0}])),
    "c6_range": ("one point light with range 2.2 (window falloff), +y world",
                 lambda f: plane_case(f, "+y", lights=[{
                     "type": "point", "position": from_zup("+y", [0.8, 0.5, 1.2]).tolist(), "color": [1, 1, 1],
                     "intensity": 6.0, "range": 2.2}])),
    "c6_flash": ("flash only, offset (0.6, 0.4, 0) in camera space, +y world",
                 lambda f: plane_case(f, "+y", lights=[],
                                      flash={"color": [1, 1, 1], "intensity": 20.0, "offset": [0.6, 0.4, 0.0]})),
    "c6_framelights": ("one global point light plus a different per-frame light in each frame",
                       lambda f: plane_case(f, "+y", lights=point_lights("+y")[:1], frame_keys=frame_light)),
}

# ----------------------------------------------------------------------------- environment cases

ENV_H, ENV_W = 32, 64
PATCH = (slice(9, 11), slice(40, 42))  # rows, columns of the bright patch
ENV_MATERIAL = dict(uniform=True, base=[0.8, 0.8, 0.8], metal=0.0, rough=1.0)
SPHERE = dict(kind="sphere", center=[0.0, 0.0, 0.0], r=1.0)


def environment_image():
    """Black 64 x 32 environment with a 2 x 2 patch of radiance 100 above the horizon."""
    env = np.zeros((ENV_H, ENV_W, 3))
    env[PATCH] = 100.0
    return env


def patch_direction(world_up, rotation_deg=0.0, variant="spec"):
    """Solid-angle weighted mean direction of the patch under a reading of the spec."""
    dirs, dom = ref.env_directions(ENV_H, ENV_W, world_up, rotation_deg, variant)
    d = (dirs[PATCH] * dom[PATCH][..., None]).sum((0, 1))
    return d / np.linalg.norm(d)


def sphere_mesh(count=(48, 96)):
    """UV sphere of radius 1 with equirectangular uv in the +y convention."""
    import trimesh

    m = trimesh.creation.uv_sphere(radius=1.0, count=list(count))
    v = np.asarray(m.vertices, float)
    uv = np.stack([0.5 + np.arctan2(v[:, 0], -v[:, 2]) / (2 * np.pi), np.arccos(np.clip(v[:, 1], -1, 1)) / np.pi], -1)
    return v, np.asarray(m.faces), uv


def env_case(folder, world_up, rotation_deg=0.0):
    """The sphere under the patch environment: frame 0 looks at the sphere from the patch's
    direction (so the brightest point is at its image centre), frames 1-4 from around it."""
    up = from_zup(world_up, [0, 0, 1])
    mats = [ref.look_at(3.5 * patch_direction(world_up, rotation_deg), [0, 0, 0], up)]
    for az in np.deg2rad([10, 100, 190, 280]):
        mats.append(ref.look_at(from_zup(world_up, [3.3 * np.cos(az), 3.3 * np.sin(az), 1.2]), [0, 0, 0], up))
    cap = {"format": "pbrfit-capture/1", "mesh": "mesh.glb", "world_up": world_up, "camera_angle_x": 0.75,
           "frames": [{"transform_matrix": m.tolist()} for m in mats], "lights": [],
           "environment": {"file": "env.exr", "intensity": 1.0, "rotation_deg": rotation_deg}}
    return write_capture(folder, cap, SPHERE, ENV_MATERIAL, SIZE, SIZE, env=environment_image())


ENV_CASES = {
    "c4_env_yup": ("+y world, rotation_deg 0", lambda f: env_case(f, "+y")),
    "c4_env_zup": ("+z world, rotation_deg 0", lambda f: env_case(f, "+z")),
    "c4_env_yup_rot90": ("+y world, rotation_deg 90", lambda f: env_case(f, "+y", 90.0)),
    "c4_env_zup_rot-90": ("+z world, rotation_deg -90 (Blender's mapping)", lambda f: env_case(f, "+z", -90.0)),
}

CASES = {**PLANE_CASES, **ENV_CASES}


def build(name, root):
    """Write case `name` under root/name and return the folder."""
    return CASES[name][1](Path(root) / name)
