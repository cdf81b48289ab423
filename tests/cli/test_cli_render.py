"""`pbrfit synth` then `pbrfit render` with the truth material reproduces the capture."""

import json
from pathlib import Path

import numpy as np
import pytest

from pbrfit.cli.main import main
from pbrfit.io.images import read_image


def _frames(folder):
    return json.loads((folder / "capture.json").read_text())["frames"]


@pytest.mark.parametrize(
    "preset,extra,supersample,tolerance",
    [
        # linear EXR under a split-sum environment: float32 rounding only
        ("sphere-env", ["--format", "exr"], 1, 1e-5),
        # 16-bit sRGB PNG under a flash and lamps: at most one code of rounding
        ("plane-flash", ["--noise", "0", "--supersample", "1"], 1, 1.0 / 65535 + 1e-7),
        # supersampled as synth renders it (mean linear radiance of k x k samples, then encoded;
        # the silhouette's pixels mix in the sky, alpha 1 where every sample hits the mesh)
        ("plane-flash", ["--noise", "0", "--supersample", "2"], 2, 1.0 / 65535 + 1e-7),
        ("sphere-env", ["--format", "exr", "--supersample", "3"], 3, 1e-5),
    ],
)
def test_render_with_truth_reproduces_synth(tmp_path, monkeypatch, preset, extra, supersample, tolerance):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap, out = tmp_path / "cap", tmp_path / "out"
    assert main(["synth", preset, "--out", str(cap), "--size", "24", "--views", "2", "--quiet", *extra]) == 0
    import pbrfit.render.views  # the one caller of load_environment: every read goes through it

    reads, load = [], pbrfit.render.views.load_environment
    monkeypatch.setattr(pbrfit.render.views, "load_environment", lambda *a, **kw: reads.append(a[0]) or load(*a, **kw))
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(out), "--quiet",
                 "--supersample", str(supersample)]) == 0
    # the environment file is read once, also where it is the only light and so is checked first
    assert reads == ([cap / "env.exr"] if preset == "sphere-env" else [])
    frames = _frames(out)
    assert len(frames) == 2
    for frame in _frames(cap):
        want, want_info = read_image(cap / frame["file_path"])
        got, got_info = read_image(out / frame["file_path"])
        assert got_info.format == want_info.format  # same file type and depth
        assert got.shape[-1] == 4  # RGBA: alpha = where the mesh covers the pixel
        mask, _ = read_image(cap / frame["mask_path"])
        np.testing.assert_array_equal(got[..., 3] > 0.5, mask[..., 0] > 0.5)
        np.testing.assert_allclose(got[..., :3], want[..., :3], atol=tolerance, rtol=1e-5)


def test_render_relights_with_lights_override(tmp_path, monkeypatch):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap, out = tmp_path / "cap", tmp_path / "out"
    assert main(["synth", "plane-flash", "--out", str(cap), "--size", "16", "--views", "1", "--noise", "0",
                 "--supersample", "1", "--quiet"]) == 0
    lights = tmp_path / "lights.json"
    lights.write_text(json.dumps([{"type": "directional", "direction": [0, 0, -1], "intensity": 3.0}]))
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(out), "--lights", str(lights),
                 "--quiet"]) == 0
    raw = json.loads((out / "capture.json").read_text())
    assert raw["lights"] == json.loads(lights.read_text())
    before, _ = read_image(cap / raw["frames"][0]["file_path"])
    after, _ = read_image(out / raw["frames"][0]["file_path"])
    assert not np.allclose(before[..., :3], after[..., :3], atol=1e-3)
    # the override is exactly what a capture.json holding those lights renders
    again = tmp_path / "again"
    assert main(["render", str(out), "--material", str(cap / "truth"), "--out", str(again), "--quiet"]) == 0
    np.testing.assert_allclose(read_image(again / raw["frames"][0]["file_path"])[0], after, rtol=0, atol=1e-6)


def test_render_relights_with_an_environment_at_the_captures_intensity_and_rotation(tmp_path, monkeypatch):
    """--environment FILE replaces the capture's environment file only: the capture's intensity
    and rotation_deg apply to it. The render equals that of the capture whose capture.json names
    FILE with them, and differs from the render at intensity 1 and no rotation."""
    from pbrfit.io.images import write_image

    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap = tmp_path / "cap"
    assert main(["synth", "sphere-env", "--out", str(cap), "--size", "16", "--views", "2", "--format", "exr",
                 "--quiet"]) == 0
    # a sky that changes with azimuth (so that a rotation shows) and with height; the size of the
    # preset's env.exr (128 x 256), so that its tables' programs are those compiled already
    v, u = np.meshgrid(np.linspace(0, 1, 128), np.linspace(0, 2 * np.pi, 256, endpoint=False), indexing="ij")
    sky = np.stack([1.0 + np.cos(u), 1.0 + 0.5 * np.sin(2 * u), 0.5 + v], -1).astype(np.float32)
    write_image(cap / "sky.exr", sky, "float")
    data = json.loads((cap / "capture.json").read_text())
    frame = data["frames"][0]["file_path"]

    def render(environment, *extra):
        data["environment"] = environment
        (cap / "capture.json").write_text(json.dumps(data))
        out = tmp_path / f"out{len(list(tmp_path.glob('out*')))}"
        assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(out), "--quiet",
                     *extra]) == 0
        return read_image(out / frame)[0][..., :3]

    relit = render(dict(file="env.exr", intensity=2.0, rotation_deg=40.0), "--environment", str(cap / "sky.exr"))
    named = render(dict(file="sky.exr", intensity=2.0, rotation_deg=40.0))
    np.testing.assert_allclose(relit, named, rtol=1e-5, atol=1e-6)
    plain = render(dict(file="sky.exr", intensity=1.0, rotation_deg=0.0))
    assert np.abs(relit - plain).max() > 0.1


def test_render_and_synth_refuse_an_out_folder_they_did_not_write(tmp_path, capsys):
    out = tmp_path / "photos"
    out.mkdir()
    (out / "keep.jpg").write_text("not ours")
    # refused before anything is read: the capture and material need not exist
    assert main(["render", str(tmp_path / "cap"), "--material", str(tmp_path / "m"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(out) in err[0] and "no .pbrfit-output of kind 'capture'" in err[0]
    assert main(["synth", "peer-plane", "--out", str(out), "--quiet"]) == 2
    assert "no .pbrfit-output" in capsys.readouterr().err
    # a user's own capture folder holds capture.json but no marker: never replaced either
    (out / "capture.json").write_text("{}")
    assert main(["synth", "peer-plane", "--out", str(out), "--quiet"]) == 2
    assert "no .pbrfit-output" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["capture.json", "keep.jpg"]


@pytest.mark.parametrize("suffix,fmt,dtype", [(".hdr", "exr", "float"), (".jpg", "png8", "uint8")])
def test_render_to_a_file_type_without_alpha_writes_a_mask(tmp_path, monkeypatch, suffix, fmt, dtype):
    from pbrfit.io.images import write_image
    from pbrfit.scene.capture import load_capture

    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap, out = tmp_path / "cap", tmp_path / "out"
    assert main(["synth", "sphere-env", "--out", str(cap), "--size", "16", "--views", "2", "--format", fmt,
                 "--quiet"]) == 0
    data = json.loads((cap / "capture.json").read_text())
    for frame in data["frames"]:  # the same frames as Radiance HDR / JPEG files
        image, _ = read_image(cap / frame["file_path"])
        frame["file_path"] = str(Path(frame["file_path"]).with_suffix(suffix))
        write_image(cap / frame["file_path"], image[..., :3], dtype)
    (cap / "capture.json").write_text(json.dumps(data))
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(out), "--quiet"]) == 0
    rendered = load_capture(out)
    for frame, source in zip(_frames(out), load_capture(cap).frames):
        image, info = read_image(out / frame["file_path"])
        assert frame["file_path"].endswith(suffix) and image.shape[-1] == 3
        mask, _ = read_image(out / frame["mask_path"])
        assert set(np.unique(mask)) <= {0.0, 1.0} and mask.any()
        np.testing.assert_array_equal(mask[..., 0] > 0, source.mask)
    assert len(rendered.frames) == 2


def test_render_refuses_to_write_over_its_own_capture_and_takes_inline_lights(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap, out = tmp_path / "cap", tmp_path / "out"
    assert main(["synth", "peer-plane", "--out", str(cap), "--size", "16", "--views", "2", "--texture-size", "4",
                 "--quiet"]) == 0
    before = sorted(p.name for p in cap.rglob("*"))
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(cap), "--quiet"]) == 2
    assert "holds the capture being rendered" in capsys.readouterr().err
    assert sorted(p.name for p in cap.rglob("*")) == before
    light = '[{"type": "point", "position": [0, 0, 3], "color": [1, 1, 1], "intensity": 3}]'
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(out), "--lights", light,
                 "--quiet"]) == 0
    assert json.loads((out / "capture.json").read_text())["lights"] == json.loads(light)
    # nor over an earlier render that holds the capture (replacing it would delete the capture)
    inner = out / "inner"
    assert main(["synth", "peer-plane", "--out", str(inner), "--size", "8", "--views", "1", "--texture-size", "4",
                 "--quiet"]) == 0
    assert main(["render", str(inner), "--material", str(inner / "truth"), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err  # (refused first as holding files the render did not write)
    assert "holds files pbrfit did not write (inner/" in err and (inner / "capture.json").is_file()
    (out / ".pbrfit-output").write_text("capture\n")  # a marker that lists no files: the capture check refuses
    assert main(["render", str(inner), "--material", str(inner / "truth"), "--out", str(out), "--quiet"]) == 2
    assert "holds the capture being rendered" in capsys.readouterr().err and (inner / "capture.json").is_file()
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(tmp_path / "o2"), "--lights",
                 "[{bad"]) == 2
    assert "--lights: invalid JSON" in capsys.readouterr().err
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(tmp_path / "o2"), "--lights",
                 "[" * 100000 + "]" * 100000]) == 2
    assert "--lights: invalid JSON: nested too deeply" in capsys.readouterr().err
    lights = '[{"type": "point", "position": [0, 0, 3], "intensity": %s}]'
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(tmp_path / "o2"), "--lights",
                 lights % ("9" * 5000)]) == 2
    assert "--lights: invalid JSON: an integer of more than 4300 digits" in capsys.readouterr().err
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(tmp_path / "o2"), "--lights",
                 lights.replace('"type": "point"', '"type": "point", "type": "spot"') % 5]) == 2
    assert "--lights: invalid JSON: key 'type' twice in one object" in capsys.readouterr().err
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(tmp_path / "o2"), "--lights",
                 ""]) == 2  # not the capture's own lights, silently
    assert "--lights: empty" in capsys.readouterr().err
    # no light and a black environment: the same
    from pbrfit.io.images import write_image

    write_image(tmp_path / "black.exr", np.zeros((8, 16, 3), np.float32), "float")
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(tmp_path / "o3"), "--lights",
                 "[]", "--environment", str(tmp_path / "black.exr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--lights: no light: the environment " in err[0] and "black.exr is black" in err[0]
    # no light and no environment: every render would be black
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(tmp_path / "o3"), "--lights",
                 "[]"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--lights: no light: no environment, every light is off and the material emits" in err[0]
    assert not (tmp_path / "o3").exists()
    for k in ("0", "17"):
        assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(tmp_path / "o4"),
                     "--supersample", k]) == 2
        assert capsys.readouterr().err.strip() == f"pbrfit: error: --supersample: must be from 1 to 16, got {k}"
    assert not (tmp_path / "o4").exists()


def test_render_writes_paths_that_leave_the_capture_inside_its_output(tmp_path, monkeypatch):
    """The spec lets `file_path` and `mesh` leave the capture's folder or be absolute; written
    as they are, a render would land outside its output, over the capture's own images. And a
    NeRF-style transforms.json without `format` renders to a capture that loads again."""
    import shutil

    from pbrfit.scene.capture import load_capture

    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap = tmp_path / "cap"
    assert main(["synth", "peer-plane", "--out", str(cap), "--size", "16", "--views", "2", "--texture-size", "4",
                 "--quiet"]) == 0
    data = json.loads((cap / "capture.json").read_text())
    shared, meshes = tmp_path / "shared", tmp_path / "meshes"
    shared.mkdir(), meshes.mkdir()
    for frame in data["frames"]:
        src = cap / frame["file_path"]
        shutil.move(src, shared / src.name)
        frame["file_path"] = f"../shared/{src.name}"
    shutil.move(cap / data["mesh"], meshes / Path(data["mesh"]).name)
    data["mesh"] = str(meshes / Path(data["mesh"]).name)  # absolute
    data.pop("format")
    (cap / "capture.json").unlink()
    (cap / "transforms.json").write_text(json.dumps(data))
    before = {p.name: p.read_bytes() for p in shared.iterdir()}
    out = tmp_path / "out"
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(out), "--quiet"]) == 0
    assert {p.name: p.read_bytes() for p in shared.iterdir()} == before  # the inputs are untouched
    written = json.loads((out / "capture.json").read_text())
    assert written["format"] == "pbrfit-capture/1" and written["mesh"] == "mesh" + Path(data["mesh"]).suffix
    names = [f["file_path"] for f in written["frames"]]
    assert names == [f"frames/{i:03d}_{Path(f['file_path']).name}" for i, f in enumerate(data["frames"])]
    rendered = load_capture(out)
    assert len(rendered.frames) == 2 and all(f.mask.any() for f in rendered.frames)
    assert not (tmp_path / "shared" / "frames").exists() and sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["cache", "cap", "meshes", "out", "shared"])


def test_render_copies_the_files_a_gltf_mesh_names(tmp_path, monkeypatch):
    """A .gltf keeps its buffers in files beside it (or anywhere, by relative URI): the render
    output copies them with the mesh, rewriting a URI that would leave the output, so that the
    rendered folder loads, and fits, again."""
    import trimesh

    from pbrfit.scene.capture import load_capture

    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap = tmp_path / "cap"
    assert main(["synth", "peer-plane", "--out", str(cap), "--size", "16", "--views", "2", "--texture-size", "4",
                 "--quiet"]) == 0
    data = json.loads((cap / "capture.json").read_text())
    files = trimesh.load(cap / data["mesh"]).export(file_type="gltf")
    (name_gltf,) = [n for n in files if n.endswith(".gltf")]
    doc = json.loads(files[name_gltf])
    outside = tmp_path / "outside"
    outside.mkdir()
    for i, buffer in enumerate(doc["buffers"]):
        (outside / f"buffer {i}.bin").write_bytes(files[buffer["uri"]])
        buffer["uri"] = f"../outside/buffer%20{i}.bin"  # leaves the capture's folder, percent-encoded
    (cap / "mesh.gltf").write_text(json.dumps(doc))
    data["mesh"] = "mesh.gltf"
    (cap / "capture.json").write_text(json.dumps(data))
    before = load_capture(cap)
    out = tmp_path / "out"
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(out), "--quiet"]) == 0
    written = json.loads((out / "mesh.gltf").read_text())
    for i, buffer in enumerate(written["buffers"]):
        assert buffer["uri"] == f"mesh_files/buffers_{i}_buffer%20{i}.bin"
        assert (out / "mesh_files" / f"buffers_{i}_buffer {i}.bin").read_bytes() == (
            outside / f"buffer {i}.bin").read_bytes()
    rendered = load_capture(out)
    np.testing.assert_array_equal(np.asarray(rendered.mesh.vertices), np.asarray(before.mesh.vertices))
    # a URI that stays inside lands at the same place relative to the copy
    (cap / "bufs").mkdir()
    for i, buffer in enumerate(doc["buffers"]):
        (cap / "bufs" / f"b{i}.bin").write_bytes((outside / f"buffer {i}.bin").read_bytes())
        buffer["uri"] = f"bufs/b{i}.bin"
    (cap / "mesh.gltf").write_text(json.dumps(doc))
    out2 = tmp_path / "out2"
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(out2), "--quiet"]) == 0
    assert [b["uri"] for b in json.loads((out2 / "mesh.gltf").read_text())["buffers"]] == [
        b["uri"] for b in doc["buffers"]]
    assert (out2 / "bufs" / "b0.bin").is_file() and len(load_capture(out2).frames) == 2


def test_file_system_refusals_are_one_line_with_nothing_left(tmp_path, monkeypatch, capsys):
    # a full disk while the render writes, and a path component longer than the system takes:
    # exit status 2, one line naming the file, no traceback, no output folder
    import errno

    import pbrfit.render.output

    cap = tmp_path / "cap"
    assert main(["synth", "peer-plane", "--out", str(cap), "--size", "8", "--views", "1", "--texture-size", "4",
                 "--quiet"]) == 0

    def full(src, tmp, rel):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp / rel))

    with monkeypatch.context() as m:
        m.setattr(pbrfit.render.output, "_copy_into", full)
        out = tmp_path / "rendered"
        assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"pbrfit: error: {out}/mesh.glb: cannot write: No space left on device; nothing was written")
        assert err.count("\n") == 1, err
        assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    out = tmp_path / ("x" * 300)
    assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pbrfit: error: ") and "File name too long" in err and err.count("\n") == 1, err


def test_no_command_a_closed_pipe_and_warnings_are_one_line(capsys, monkeypatch):
    import io
    import sys
    import warnings

    import pbrfit.cli.main as cli

    assert main([]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"pbrfit: error: expected a command, one of {', '.join(cli._COMMANDS)} (see pbrfit --help)"]

    class Closed(io.StringIO):  # stdout whose reader left (`| head -1`)
        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            raise BrokenPipeError(32, "Broken pipe")

    def command(args):
        warnings.warn("a warning of\ntwo lines", RuntimeWarning)
        print("done")
        return 0

    monkeypatch.setitem(cli._COMMANDS, "demo", command)
    with monkeypatch.context() as m:
        m.setattr(sys, "stdout", Closed())
        assert main(["demo"]) == 141
    assert capsys.readouterr().err.splitlines() == ["pbrfit: warning: a warning of\\ntwo lines"]

    def child_pipe(args):  # another pipe broke, stdout is fine: a bug, raised
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setitem(cli._COMMANDS, "demo", child_pipe)
    with pytest.raises(BrokenPipeError):
        main(["demo"])


def test_control_characters_in_a_message_are_escaped(capsys, monkeypatch):
    """A file name with a newline or a terminal escape (capture.json may hold any string) is shown
    escaped: the error stays one line and cannot write to the terminal."""
    import warnings

    import pbrfit.cli.main as cli
    from pbrfit.errors import CaptureError

    def command(args):
        warnings.warn("images/\x1b[2Jx\n.png: odd")
        raise CaptureError("capture.json: frames[1].file_path: not found: images/0\n01.exr")

    monkeypatch.setitem(cli._COMMANDS, "demo", command)
    assert main(["demo"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        "pbrfit: warning: images/\\x1b[2Jx\\n.png: odd",
        "pbrfit: error: capture.json: frames[1].file_path: not found: images/0\\n01.exr"]


def test_render_refuses_the_environment_integrators_it_does_not_shade(tmp_path, monkeypatch, capsys):
    """``--model ibl=per_pixel`` (a fit's integrals) and ``ibl=monte_carlo`` (synth's reference) are
    refused in one line, exit status 2, nothing written."""
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap = tmp_path / "cap"
    assert main(["synth", "sphere-env", "--out", str(cap), "--size", "8", "--views", "1", "--texture-size", "4",
                 "--quiet"]) == 0
    for ibl in ("per_pixel", "monte_carlo"):
        out = tmp_path / f"o-{ibl}"
        assert main(["render", str(cap), "--material", str(cap / "truth"), "--out", str(out), "--model",
                     f"ibl={ibl}", "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"--model: ibl={ibl} is not one render shades" in err[0], err
        assert not out.exists()
