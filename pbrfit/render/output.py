"""`pbrfit render`'s output: a capture folder holding the renders (capture spec, "The render output").

The renders keep each frame's file type, color space and relative path, with the coverage as
alpha; the mesh (with the files a ``.gltf`` names) and the environment are copied beside them,
and capture.json names them where they landed.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
from pathlib import Path
from typing import Optional, Sequence
from urllib.parse import quote

import numpy as np

from ..errors import CaptureError
from ..scene.gltf_read import gltf_file_uris
from ..io.atomic import atomic_dir
from ..io.images import write_image
from ..scene.capture import CAPTURE_FORMAT

__all__ = ["NO_ALPHA_SUFFIXES", "write_rendered_capture"]

#: Image file types that hold no alpha channel: a render to one writes its coverage as a mask file.
NO_ALPHA_SUFFIXES = (".hdr", ".jpg", ".jpeg")


def _image_dtype(frame) -> str:
    info = frame.info
    if info is None or not info.is_ldr:
        return "half" if info is not None and info.format == "half" else "float"
    return "uint16" if info.bits > 8 else "uint8"


def _inside(rel: str, fallback: str) -> str:
    """`rel` when it names a path inside the output folder, else `fallback`: the spec lets a
    capture's paths leave its folder (``../images/0.png``) or be absolute, and written as they are
    they would land outside the output, over the input's own files."""
    norm = os.path.normpath(rel)
    if os.path.isabs(norm) or norm == os.pardir or norm.startswith(os.pardir + os.sep):
        return fallback
    return norm


def _copy_into(src: Path, root_out: Path, rel: str) -> None:
    dst = root_out / rel
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)


def _copy_mesh(src: Path, root_out: Path, rel: str) -> list[str]:
    """Copy the capture's mesh to ``rel`` in the output, with the files a ``.gltf`` refers to
    (buffers, images: URIs relative to it, percent-encoded): each lands at the same place relative
    to the copy, or, where that would leave the output folder, in ``<stem>_files/`` beside it
    with its URI rewritten. Returns the output paths written (relative to ``root_out``)."""
    if src.suffix.lower() != ".gltf":
        _copy_into(src, root_out, rel)
        return [rel]

    try:
        doc = json.loads(src.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CaptureError(f"{src}: cannot read the glTF file to copy it: {err}") from None
    here = os.path.dirname(rel)
    written = [rel]
    for kind, i, entry, name in list(gltf_file_uris(doc)):
        source = src.parent / name
        if not source.is_file():  # an image the mesh loader did without: left as it was
            continue
        target = _inside(os.path.join(here, name), "")
        if not target:
            target = os.path.join(here, f"{src.stem}_files", f"{kind}_{i}_{source.name}")
            entry["uri"] = quote(os.path.relpath(target, here or ".").replace(os.sep, "/"))
        _copy_into(source, root_out, target)
        written.append(target)
    dst = root_out / rel
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(json.dumps(doc), encoding="utf-8")
    return written


def write_rendered_capture(
    capture,
    renders: Sequence[tuple[np.ndarray, np.ndarray]],
    out_dir: os.PathLike,
    environment_file: Optional[os.PathLike] = None,
    lights_json: Optional[list] = None,
) -> Path:
    """Write a capture folder at `out_dir` holding `renders` (capture spec, "The render output").

    capture.json keeps the cameras, lights and environment (with the overrides applied), each
    image goes to the frame's relative ``file_path`` in the same file type and color space as
    the input frame, with an alpha channel of 1 where the mesh covers the pixel; file types
    that hold no alpha (`NO_ALPHA_SUFFIXES`: Radiance HDR, JPEG) get RGB and the same coverage
    as an 8-bit mask at ``masks/<file_path>.png`` (suffix kept: ``masks/images/0.jpg.png``),
    named by the frame's ``mask_path``. The mesh and environment files are copied beside it,
    a ``.gltf`` mesh with the buffers and images it names (`_copy_mesh`).
    A path that leaves the capture's folder (``..``) or is absolute is written inside the output
    instead (frame i at ``frames/<i>_<name>``, the mesh at ``mesh<suffix>``, the environment at
    ``environment<suffix>``) and capture.json names it there; so is a frame whose path another
    frame (or the mesh or environment) already took. A NeRF-style ``transforms.json``
    without ``format`` gets it, so the output loads as a capture. The folder is built under a
    temporary name and renamed into place, so a failure leaves nothing.
    """

    raw = copy.deepcopy(capture.raw)
    raw["format"] = CAPTURE_FORMAT
    out_dir = Path(out_dir)
    with atomic_dir(out_dir, kind="capture") as tmp:
        tmp = Path(tmp)
        mesh_rel = _inside(raw.get("mesh", capture.mesh_path.name), "mesh" + capture.mesh_path.suffix)
        raw["mesh"] = mesh_rel
        mesh_files = _copy_mesh(capture.mesh_path, tmp, mesh_rel)
        if environment_file is not None:
            env_rel = "environment" + Path(environment_file).suffix
            _copy_into(Path(environment_file), tmp, env_rel)
            env = dict(raw.get("environment") or {})
            env["file"] = env_rel
            raw["environment"] = env
        elif capture.environment is not None:
            env_file = Path(capture.environment.file)
            env_rel = _inside(raw["environment"]["file"], "environment" + env_file.suffix)
            raw["environment"]["file"] = env_rel
            _copy_into(env_file, tmp, env_rel)
        if lights_json is not None:
            raw["lights"] = lights_json
        taken = {os.path.normcase(f) for f in mesh_files}
        if raw.get("environment"):
            taken.add(os.path.normcase(raw["environment"]["file"]))
        for i, (frame, entry, (image, alpha)) in enumerate(zip(capture.frames, raw["frames"], renders)):
            found = Path(frame.file_path)
            own = os.path.join("frames", f"{i:03d}_{found.name}")
            rel = _inside(os.path.relpath(found, capture.root), own)
            if os.path.normcase(rel) in taken:  # two frames of one file, or a frame named like the mesh
                rel = own
            taken.add(os.path.normcase(rel))
            entry["file_path"] = rel
            entry.pop("mask_path", None)  # the alpha channel is the mask
            dst = tmp / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            if Path(rel).suffix.lower() in NO_ALPHA_SUFFIXES:  # RGB, and the coverage as a mask file
                mask_rel = os.path.join("masks", rel + ".png")  # a.jpg and a.hdr keep apart
                entry["mask_path"] = mask_rel
                (tmp / mask_rel).parent.mkdir(parents=True, exist_ok=True)
                write_image(tmp / mask_rel, alpha[..., None], "uint8", color_space="linear")
                write_image(dst, image, _image_dtype(frame), color_space=frame.color_space)
            else:
                write_image(dst, np.concatenate([image, alpha[..., None]], axis=-1), _image_dtype(frame),
                            color_space=frame.color_space)
        (tmp / "capture.json").write_text(json.dumps(raw, indent=2) + "\n")
    return out_dir
