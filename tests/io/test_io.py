import os
import re
from pathlib import Path

import numpy as np
import pytest

from _capture_fixtures import QUAD_UV_GLTF, glb_accessor, glb_image, glb_mesh_transforms, read_glb, write_quad_glb
import pbrfit.io.atomic
from pbrfit.physics.color import linear_to_srgb, srgb_to_linear
from pbrfit.errors import CaptureError
from pbrfit.io.atomic import (OUTPUT_MARKER, CacheWarning, atomic_dir, atomic_path, check_not_inside, check_output_dir,
                           write_cache_file)
from pbrfit.io.gltf_export import write_gltf
from pbrfit.io.images import read_image, read_image_info, write_image
from pbrfit.io.material_files import read_map, read_material, write_material
from pbrfit.physics.material import Material


def _listing(folder):
    return sorted(p.name for p in folder.iterdir())


# --- atomic writes ------------------------------------------------------------------------------
def test_atomic_path_renames_on_success(tmp_path):
    final = tmp_path / "sub" / "a.txt"
    with atomic_path(final) as tmp:
        # the same name in a private folder beside it (what a signal removes)
        assert tmp.parent.parent == final.parent and tmp.name == final.name and tmp != final
        tmp.write_text("new")
        assert not final.exists()
    assert final.read_text() == "new"
    assert _listing(final.parent) == ["a.txt"]


def test_atomic_outputs_get_the_modes_the_umask_gives(tmp_path, monkeypatch):
    """Not tempfile's private 0600 / 0700: others can read a fit's maps where the umask lets them."""
    import os
    import stat

    from pbrfit.io import atomic as pio

    plain_file, plain_dir = tmp_path / "plain", tmp_path / "plaindir"
    plain_file.write_text("x")
    plain_dir.mkdir()
    mode = lambda p: stat.S_IMODE(os.stat(p).st_mode)
    assert (mode(plain_file), mode(plain_dir)) == (pio._FILE_MODE, pio._DIR_MODE)  # read from the umask
    monkeypatch.setattr(pio, "_FILE_MODE", 0o640)  # modes no umask default gives, nor tempfile
    monkeypatch.setattr(pio, "_DIR_MODE", 0o750)
    with atomic_path(tmp_path / "a.exr") as tmp:
        tmp.write_text("x")
    with atomic_dir(tmp_path / "out") as d:
        (d / "x").write_text("1")
    assert mode(tmp_path / "a.exr") == 0o640 and mode(tmp_path / "out") == 0o750


def test_atomic_path_failure_keeps_old_and_leaves_no_temp(tmp_path):
    final = tmp_path / "a.exr"
    final.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(final) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert final.read_text() == "old"
    assert _listing(tmp_path) == ["a.exr"]


def test_atomic_dir_success_failure_and_overwrite(tmp_path, monkeypatch):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with atomic_dir(out) as d:
            (d / "x").write_text("1")
            raise RuntimeError("boom")
    assert _listing(tmp_path) == []
    with atomic_dir(out) as d:
        (d / "x").write_text("1")
        assert not out.exists()
    assert _listing(out) == ["x"]
    with atomic_dir(out) as d:
        (d / "y").write_text("2")
    assert _listing(out) == ["y"]
    assert _listing(tmp_path) == ["out"]
    with pytest.raises(CaptureError, match="already exists"):
        with atomic_dir(out, overwrite=False):
            pass
    # with a kind, only an empty folder or an earlier output of that kind (its marker) is replaced
    with pytest.raises(CaptureError, match=r"no \.pbrfit-output of kind 'fit'"):
        with atomic_dir(out, kind="fit") as d:
            (d / "report.json").write_text("{}")
    assert _listing(out) == ["y"] and _listing(tmp_path) == ["out"]
    (out / "y").unlink()
    with atomic_dir(out, kind="fit") as d:  # empty: replaced, and marked
        (d / "report.json").write_text("{}")
    assert (out / OUTPUT_MARKER).read_text().splitlines() == ["fit", "report.json"]  # the kind, the files
    with atomic_dir(out, kind="fit") as d:  # an earlier output of the kind: replaced
        (d / "report.json").write_text("[]")
        (d / "views").mkdir()
        (d / "views" / "0.png").write_text("")
    assert (out / "report.json").read_text() == "[]"
    assert (out / OUTPUT_MARKER).read_text().splitlines() == ["fit", "report.json", "views/0.png"]
    # ... unless a file it did not write was saved into it since: that would go with it
    (out / "views" / "my notes.txt").write_text("keep me")
    with pytest.raises(CaptureError, match=r"holds files pbrfit did not write \(views/my notes.txt\)"):
        with atomic_dir(out, kind="fit") as d:
            (d / "report.json").write_text("{}")
    assert (out / "views" / "my notes.txt").read_text() == "keep me" and (out / "report.json").read_text() == "[]"
    (out / "views" / "my notes.txt").unlink()
    (out / OUTPUT_MARKER).write_text("fit\n")  # a marker that lists no files (older pbrfit): replaced as before
    (out / "other.txt").write_text("")
    with atomic_dir(out, kind="fit") as d:
        (d / "report.json").write_text("{}")
    assert not (out / "other.txt").exists()
    (out / OUTPUT_MARKER).write_bytes(b"\xff\xfefit\n")  # not text: not pbrfit's marker, refused in one line
    with pytest.raises(CaptureError, match="exists and is not a pbrfit fit output"):
        check_output_dir(out, "fit")
    (out / OUTPUT_MARKER).write_text("fit\n")
    # a place where no folder can be made: refused before any work, one line
    (tmp_path / "plain").write_text("")
    with pytest.raises(CaptureError, match="plain is not a folder"):
        check_output_dir(tmp_path / "plain" / "sub" / "out", "fit")
    with pytest.raises(CaptureError, match="plain is not a folder"):
        with atomic_dir(tmp_path / "plain" / "out", kind="fit"):
            pass
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    # root may write anywhere, whatever the mode: pbrfit.io.atomic's os.access answers for this
    # folder as it does for any other user, so that the refusal runs under root too
    real_access = os.access
    with monkeypatch.context() as m:
        m.setattr(pbrfit.io.atomic.os, "access",
                  lambda path, mode, **kw: False if Path(path) == locked else real_access(path, mode, **kw))
        with pytest.raises(CaptureError, match=re.escape(f"cannot write in {locked} (permission denied)")):
            check_output_dir(locked / "out", "fit")
        with pytest.raises(CaptureError, match="permission denied"):  # and a folder further down
            check_output_dir(locked / "a" / "b", "fit")
    with pytest.raises(CaptureError, match="cannot create the output folder"):
        with atomic_dir(tmp_path / "plain" / "x"):  # no kind: no check first, the mkdir's error
            pass
    with pytest.raises(CaptureError, match="kind 'capture'"):  # another kind: refused
        check_output_dir(out, "capture")
    (tmp_path / "f").write_text("")
    with pytest.raises(CaptureError, match="not a folder"):
        check_output_dir(tmp_path / "f", "fit")
    with pytest.raises(CaptureError, match="is the current folder or holds it"):
        check_output_dir(".", "fit")
    with pytest.raises(CaptureError, match="is the current folder or holds it"):
        check_output_dir("..", "fit")
    with pytest.raises(CaptureError, match="holds the capture"):
        check_not_inside(tmp_path / "out" / "cap", tmp_path / "out", "capture")
    check_not_inside(tmp_path / "outer", tmp_path / "out", "capture")  # a sibling whose name extends it


def test_signals_are_held_while_an_output_is_swapped_in():
    """A Ctrl-C or kill between moving the earlier output aside and renaming the new one in
    would lose both: the swap holds the signals, which arrive right after it."""
    import signal

    from pbrfit.io.atomic import _signals_held

    got = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: got.append(signum))
    try:
        with _signals_held():
            os.kill(os.getpid(), signal.SIGTERM)
            assert got == []
        assert got == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGTERM, previous)



#: A process whose writer thread is halfway through an output folder (an earlier one in place, a
#: cache file and a file of the output written) when the main thread abandons the writes, with
#: another writer's lock (`hold_on_abandon`) held for a while by a third thread.
_ABANDONED_PROCESS = """
import json, os, sys, threading, time
from pathlib import Path
from pbrfit.io.atomic import abandon_writes, atomic_dir, atomic_path, hold_on_abandon

root = Path(sys.argv[1])
with atomic_dir(root / "out") as d:
    (d / "old.txt").write_text("earlier output")
inside, go_on, renamed = threading.Event(), threading.Event(), threading.Event()
other_writer = threading.Lock()
hold_on_abandon("other writer", other_writer)

def write():
    with atomic_dir(root / "out") as d:
        (d / "new.txt").write_text("new output")
        with atomic_path(root / "cache.bin") as tmp:
            tmp.write_bytes(b"half")
            inside.set()
            go_on.wait()
    renamed.set()

def hold_other_writer():
    with other_writer:
        inside.wait()
        time.sleep(0.3)

threading.Thread(target=hold_other_writer, daemon=True).start()
threading.Thread(target=write, daemon=True).start()
inside.wait()
start = time.monotonic()
removed = abandon_writes(timeout=5)
waited = time.monotonic() - start
go_on.set()  # the writer reaches its renames, which wait for ever
time.sleep(0.3)
print(json.dumps(dict(removed=len(removed), waited=waited, renamed=renamed.is_set(), held=other_writer.locked(),
                      left=sorted(os.listdir(root)), out=sorted(os.listdir(root / "out")))))
sys.stdout.flush()
os._exit(0)
"""


def _in_a_process(script: str, folder) -> dict:
    """The JSON line a script prints, run in a Python process of its own with ``folder`` as its
    argument (it ends with ``os._exit``, as a process a signal ended)."""
    import json
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", script, str(folder)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_abandoned_writes_leave_no_temporary_and_rename_nothing(tmp_path):
    """`abandon_writes` (what a signal does before the process ends) removes the temporaries of
    a writer in another thread (the output folder's, a cache file's), waits for another writer's
    lock and keeps it, and no rename happens after it: the earlier output stays, whole."""
    got = _in_a_process(_ABANDONED_PROCESS, tmp_path)
    assert got["removed"] == 2 and got["left"] == ["out"] and got["out"] == ["old.txt"]
    assert not got["renamed"] and got["held"] and got["waited"] >= 0.2


def _abandoned_mid_write(writer: str, wait: float = 5.0) -> str:
    """A script for `_in_a_process`: ``writer`` defines ``write()``, run in a thread, which sets
    ``made`` at the moment a signal should come and then waits for ``go_on``; the main thread
    abandons the writes there (`abandon_writes`, what a signal does), lets the writer go on, waits
    at most ``wait`` seconds for it and prints how many temporaries were removed, whether the
    writer finished, and what is left in the folder."""
    return _MID_WRITE_HEAD + writer + _MID_WRITE_TAIL.replace("WAIT", repr(wait))


_MID_WRITE_HEAD = r"""
import json, os, sys, threading, warnings
from pathlib import Path
from pbrfit.io import atomic

root = Path(sys.argv[1])
made, go_on, done = threading.Event(), threading.Event(), threading.Event()
"""

_MID_WRITE_TAIL = r"""
threading.Thread(target=write, daemon=True).start()
made.wait()
removed = atomic.abandon_writes(timeout=5)  # the signal, in the main thread
go_on.set()  # the writer goes on, past the moment the signal removed its temporaries
done.wait(WAIT)
print(json.dumps(dict(removed=len(removed), done=done.is_set(), left=sorted(os.listdir(root)))))
sys.stdout.flush()
os._exit(0)
"""


def test_a_cache_write_a_signal_abandoned_before_its_open_leaves_nothing(tmp_path):
    """A signal that removes a cache file's temporary between its making and the writer's open
    (the G-buffer cache's first write): the open does not make it again, so nothing is left."""
    writer = r"""
made_temporary = atomic._new_temporary

def made_then_wait(make):  # the moment between the temporary's making and the writer's open
    path = made_temporary(make)
    made.set()
    go_on.wait()
    return path

atomic._new_temporary = made_then_wait

def write():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        atomic.write_cache_file(root / "gbuffer.npz", lambda f: f.write(b"data"))
    done.set()
"""
    assert _in_a_process(_abandoned_mid_write(writer), tmp_path) == dict(removed=1, done=True, left=[])


def test_an_output_folder_a_signal_abandoned_is_not_made_again_by_its_writer(tmp_path):
    """A signal that removes an output's temporary folder while the command's worker writes into
    it: the worker's next file does not make the folder again (it waits, and the process ends),
    so nothing is left."""
    writer = r"""
def write():  # a command's worker writing its output folder
    with atomic.atomic_dir(root / "out") as tmp:
        made.set()
        go_on.wait()  # then on to its next file, inside the folder the signal removed
        with atomic.atomic_path(tmp / "maps" / "base_color.exr") as path:
            path.write_bytes(b"data")
    done.set()
"""
    assert _in_a_process(_abandoned_mid_write(writer, wait=1.0), tmp_path) == dict(removed=1, done=False, left=[])


def test_a_file_written_by_path_after_a_signal_abandoned_it_leaves_nothing(tmp_path):
    """A signal that removes a file's temporary while its writer, which makes the file by path
    (OpenImageIO), has yet to write it: the temporary is the file's name in a private folder, so
    the write fails once the folder is gone instead of making the file again, and nothing is left."""
    writer = r"""
def write():  # a writer that makes its file by path, as OpenImageIO does
    try:
        with atomic.atomic_path(root / "base_color.exr") as path:
            made.set()
            go_on.wait()
            with open(path, "wb") as f:
                f.write(b"data")
    except OSError:
        pass
    done.set()
"""
    assert _in_a_process(_abandoned_mid_write(writer), tmp_path) == dict(removed=1, done=True, left=[])


# --- images -------------------------------------------------------------------------------------
def test_single_channel_2d_round_trip_guards_oiio_bug(tmp_path):
    # OpenImageIO garbles a 2-D array passed to write_image; write_image must pass (H, W, 1).
    a = np.arange(12, dtype=np.float32).reshape(3, 4) / 7.0
    write_image(tmp_path / "m.exr", a)
    back, info = read_image(tmp_path / "m.exr")
    assert back.shape == (3, 4, 1) and info.channels == 1
    np.testing.assert_array_equal(back[..., 0], a)


def test_the_same_pixels_write_the_same_bytes(tmp_path):
    """No time stamp in the file (OpenEXR's capDate, which OpenImageIO writes from the clock
    unless told otherwise): a fit run twice writes identical files."""
    a = np.random.default_rng(0).random((4, 5, 3)).astype(np.float32)
    write_image(tmp_path / "a.exr", a)
    assert b"capDate" not in (tmp_path / "a.exr").read_bytes()
    write_image(tmp_path / "b.exr", a)
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_exr_float_round_trip_exact(tmp_path, channels):
    a = np.random.default_rng(channels).normal(size=(5, 7, channels)).astype(np.float32) * 100
    write_image(tmp_path / "a.exr", a)
    back, info = read_image(tmp_path / "a.exr")
    np.testing.assert_array_equal(back, a)
    assert (info.width, info.height, info.format, info.is_ldr) == (7, 5, "float", False)
    assert info.alpha_channel == (3 if channels == 4 else None)
    assert info.file_format == "openexr"


@pytest.mark.parametrize("dtype, code_max", [("uint8", 255), ("uint16", 65535)])
def test_png_integer_round_trip(tmp_path, dtype, code_max):
    codes = np.random.default_rng(0).integers(0, code_max + 1, size=(4, 6, 3))
    write_image(tmp_path / "a.png", codes / code_max, dtype)
    back, info = read_image(tmp_path / "a.png")
    np.testing.assert_array_equal(np.round(back * code_max), codes)
    assert info.is_ldr and info.format == dtype and info.bits == (8 if dtype == "uint8" else 16)


def test_png_alpha_is_unassociated_both_ways(tmp_path):
    # OpenImageIO would multiply color by alpha on read (and divide on write) by default.
    px = np.array([[[200, 100, 50, 128]]], np.float64) / 255
    write_image(tmp_path / "a.png", px, "uint8")
    back, info = read_image(tmp_path / "a.png")
    np.testing.assert_array_equal(np.round(back * 255), [[[200, 100, 50, 128]]])
    assert info.alpha_channel == 3


@pytest.mark.parametrize("name, dtype, atol", [("a.hdr", "float", 0.02), ("a.tif", "uint8", 0.5 / 255),
                                                ("b.tif", "float", 0.0), ("a.jpg", "uint8", 0.1)])
def test_other_formats_read(tmp_path, name, dtype, atol):
    a = np.random.default_rng(1).uniform(0.1, 0.9, (8, 8, 3)).astype(np.float32)
    a[:] = a.mean((0, 1))  # flat, so JPEG compression stays close
    write_image(tmp_path / name, a, dtype)
    back, info = read_image(tmp_path / name)
    assert back.shape == (8, 8, 3) and back.dtype == np.float32
    if atol == 0.0:  # a float TIFF holds the floats
        np.testing.assert_array_equal(back, a)
    else:
        np.testing.assert_allclose(back, a, atol=atol, rtol=0.01)
    assert info.is_ldr == (dtype == "uint8")
    assert read_image_info(tmp_path / name) == info


def test_jpeg_is_written_at_full_quality_and_chroma_resolution(tmp_path):
    """`render` keeps a JPEG capture's file type: the JPEG holds the pixels as closely as JPEG
    goes (quality 100, no chroma subsampling). OpenImageIO's default 4:2:0 put a red-blue edge
    0.64 off."""
    a = np.zeros((32, 32, 3), np.float32)
    a[:, :16] = [1, 0, 0]
    a[:, 16:] = [0, 0, 1]
    a[8:24, 8:24] = [0, 1, 0]
    write_image(tmp_path / "edges.jpg", a, "uint8")
    back, _ = read_image(tmp_path / "edges.jpg")
    assert np.max(np.abs(back - a)) < 0.02


def test_read_image_errors_name_the_file(tmp_path):
    with pytest.raises(CaptureError, match=r"frames\[0\]: image file not found: .*nope.png"):
        read_image(tmp_path / "nope.png", "frames[0]")
    (tmp_path / "bad.png").write_bytes(b"not a png at all")
    with pytest.raises(CaptureError, match=r"cannot read image .*bad.png"):
        read_image(tmp_path / "bad.png")


def test_write_image_integer_clips_and_rounds(tmp_path):
    write_image(tmp_path / "a.png", np.array([[-1.0, 0.5, 2.0]]), "uint8")
    back, _ = read_image(tmp_path / "a.png")
    np.testing.assert_array_equal(np.round(back[..., 0] * 255), [[0, 128, 255]])


# --- material folders ---------------------------------------------------------------------------
def _material(rng, normal=False, occlusion=False, emissive=False, size=(4, 5)):
    h, w = size
    n = rng.normal(size=(h, w, 3)) + [0, 0, 3]
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return Material(
        base_color=rng.uniform(0, 1, (h, w, 3)).astype(np.float32),
        metallic=rng.uniform(0, 1, (h, w, 1)).astype(np.float32),
        roughness=rng.uniform(0, 1, (h, w, 1)).astype(np.float32),
        normal=n.astype(np.float32) if normal else None,
        occlusion=rng.uniform(0, 1, (h, w, 1)).astype(np.float32) if occlusion else None,
        emissive=rng.uniform(0, 3, (h, w, 3)).astype(np.float32) if emissive else None,
    )


def test_material_round_trip_and_layout(tmp_path):
    m = _material(np.random.default_rng(0), normal=True, occlusion=True, emissive=True)
    write_material(tmp_path / "fit", m)
    assert _listing(tmp_path / "fit") == sorted([
        "base_color.exr", "base_color.png", "metallic.exr", "roughness.exr",
        "metallic_roughness.png", "normal.png", "occlusion.exr", "emissive.exr"])  # fmt: skip
    back = read_material(tmp_path / "fit")
    for name in ("base_color", "metallic", "roughness", "occlusion", "emissive"):
        np.testing.assert_array_equal(getattr(back, name), getattr(m, name))
    np.testing.assert_allclose(back.normal, m.normal, atol=1.5 / 255 * 2)
    # glTF packing: G = roughness, B = metallic, linear 8-bit; R = occlusion
    orm, info = read_image(tmp_path / "fit" / "metallic_roughness.png")
    assert info.format == "uint8"
    np.testing.assert_allclose(orm[..., 1:2], m.roughness, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(orm[..., 2:3], m.metallic, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(orm[..., 0:1], m.occlusion, atol=0.5 / 255 + 1e-6)
    # base_color.png is sRGB-encoded
    png, _ = read_image(tmp_path / "fit" / "base_color.png")
    np.testing.assert_allclose(png, linear_to_srgb(np.asarray(m.base_color)), atol=0.5 / 255 + 1e-6)
    mono, info = read_image(tmp_path / "fit" / "roughness.exr")
    assert info.channels == 1 and info.format == "float"


def test_material_png_fallback(tmp_path):
    m = _material(np.random.default_rng(1))
    write_material(tmp_path, m)
    for name in ("base_color.exr", "metallic.exr", "roughness.exr"):
        os.remove(tmp_path / name)
    back = read_material(tmp_path)
    assert back.normal is None and back.occlusion is None
    png = np.round(np.asarray(linear_to_srgb(np.asarray(m.base_color))) * 255) / 255
    np.testing.assert_allclose(back.base_color, srgb_to_linear(png), atol=1e-6)
    np.testing.assert_allclose(back.roughness, m.roughness, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(back.metallic, m.metallic, atol=0.5 / 255 + 1e-6)


def test_material_uniform_1x1(tmp_path):
    m = Material.uniform([0.2, 0.4, 0.6], 0.0, 0.5)
    write_material(tmp_path, m)
    back = read_material(tmp_path)
    assert back.base_color.shape == (1, 1, 3)
    np.testing.assert_array_equal(back.roughness, [[[0.5]]])


def test_write_material_replaces_an_earlier_material(tmp_path):
    """Written over a folder that held a material with more maps, the folder reads back as the
    new material (the old normal, occlusion and emissive files go); values a material folder may
    not hold are refused before anything is written."""
    write_material(tmp_path, _material(np.random.default_rng(2), normal=True, occlusion=True, emissive=True))
    (tmp_path / "notes.txt").write_text("keep")
    m = Material.uniform([0.2, 0.4, 0.6], 0.0, 0.5)
    write_material(tmp_path, m)
    back = read_material(tmp_path)
    assert back.normal is None and back.occlusion is None and back.emissive is None
    assert (tmp_path / "notes.txt").read_text() == "keep"
    before = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
    for bad, match in ((Material.uniform([1.5, 0.3, 0.4], 0.0, 0.7), "base_color must lie in"),
                       (Material.uniform([0.5, 0.3, 0.4], float("nan"), 0.7), "metallic hold NaN"),
                       (Material.uniform([0.5, 0.3, 0.4], 0.0, -0.1), "roughness must lie in"),
                       (Material(np.full((4, 4, 3), 0.8, np.float32), np.ones((4, 4, 1), np.float32),
                                 np.full((2, 2, 1), 0.1, np.float32)), r"metallic \(4, 4\) and roughness \(2, 2\)")):
        with pytest.raises(CaptureError, match=match):
            write_material(tmp_path, bad)
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()} == before
    with pytest.raises(CaptureError, match="notes.txt: is not a folder"):
        write_material(tmp_path / "notes.txt", m)


def test_read_material_errors(tmp_path):
    with pytest.raises(CaptureError, match="material folder not found"):
        read_material(tmp_path / "missing")
    with pytest.raises(CaptureError, match="no base_color.exr or base_color.png"):
        read_material(tmp_path)
    write_image(tmp_path / "base_color.exr", np.zeros((2, 2, 3)))
    with pytest.raises(CaptureError, match="no metallic.exr or metallic_roughness.png"):
        read_material(tmp_path)


def test_read_map_refuses_non_finite_and_out_of_range_values(tmp_path):
    """A held map (--roughness-from DIR) or a rendered material with NaN or values outside [0, 1]
    is refused, as --roughness 2 is, rather than clamped or rendered as NaN."""
    rough = np.full((2, 3, 1), 0.5, np.float32)
    rough[1, 2] = np.nan
    write_image(tmp_path / "roughness.exr", rough)
    with pytest.raises(CaptureError, match="roughness.exr: 1 texels of roughness hold NaN"):
        read_map(tmp_path, "roughness")
    write_image(tmp_path / "roughness.exr", np.full((2, 3, 1), 2.0, np.float32))
    with pytest.raises(CaptureError, match=r"roughness must lie in \[0, 1\], found values from 2 to 2"):
        read_map(tmp_path, "roughness")
    write_image(tmp_path / "base_color.exr", np.full((2, 3, 3), -0.1, np.float32))
    with pytest.raises(CaptureError, match="base_color must lie in"):
        read_map(tmp_path, "base_color")


def test_read_map_takes_a_grey_rgb_map_and_refuses_one_whose_channels_differ(tmp_path):
    grey = np.full((2, 3, 3), 0.3, np.float32)
    write_image(tmp_path / "roughness.exr", grey)
    np.testing.assert_array_equal(read_map(tmp_path, "roughness"), grey[..., :1])
    grey[0, 0, 2] = 0.7
    write_image(tmp_path / "roughness.exr", grey)
    with pytest.raises(CaptureError, match="roughness.exr: roughness must be one channel; found 3 channels that "
                                           r"differ \(channels R, G, B\)"):
        read_map(tmp_path, "roughness")


def test_read_map_reads_one_map_alone(tmp_path):
    # --metallic-from DIR: a folder holding only metallic.exr is enough
    write_image(tmp_path / "metallic.exr", np.full((2, 3, 1), 0.25, np.float32))
    np.testing.assert_array_equal(read_map(tmp_path, "metallic"), np.full((2, 3, 1), 0.25, np.float32))
    with pytest.raises(CaptureError, match="no roughness.exr or metallic_roughness.png"):
        read_map(tmp_path, "roughness")
    orm = np.zeros((2, 3, 3), np.float32)
    orm[..., 1], orm[..., 2] = 0.6, 1.0  # G = roughness, B = metallic
    write_image(tmp_path / "metallic_roughness.png", orm, "uint8")
    np.testing.assert_allclose(read_map(tmp_path, "roughness"), round(0.6 * 255) / 255, rtol=1e-6)
    np.testing.assert_array_equal(read_map(tmp_path, "metallic"), 0.25)  # the EXR wins


def test_write_gltf_uniform_material_as_exact_factors_without_uv(tmp_path):
    import trimesh

    box = trimesh.creation.box()  # no texture coordinates
    out = write_gltf(tmp_path / "u.glb", box, Material.uniform([0.123456, 0.5, 0.9], 0.3, 0.7))
    tree, _ = read_glb(out)
    pbr = tree["materials"][0]["pbrMetallicRoughness"]
    np.testing.assert_allclose(pbr["baseColorFactor"], [0.123456, 0.5, 0.9, 1.0], rtol=1e-6)
    assert pbr["metallicFactor"] == pytest.approx(0.3) and pbr["roughnessFactor"] == pytest.approx(0.7)
    assert "baseColorTexture" not in pbr and "images" not in tree
    assert "TEXCOORD_0" not in tree["meshes"][0]["primitives"][0]["attributes"]
    assert tree["materials"][0]["doubleSided"] is True  # as pbrfit shades it
    assert len(trimesh.load(out).geometry) == 1


def _uniform_with(**extra):
    u = Material.uniform([0.2, 0.4, 0.6], 0.3, 0.7)
    return Material(base_color=u.base_color, metallic=u.metallic, roughness=u.roughness, **extra)


def test_write_gltf_keeps_occlusion_and_emissive_of_uniform_materials(tmp_path):
    """1 x 1 maps with an occlusion map (glTF has no occlusion factor) are written with textures;
    a 1 x 1 emissive map becomes emissiveFactor. Before, both were dropped or refused."""
    import trimesh

    from pbrfit.scene.mesh import load_mesh

    box = trimesh.creation.box()  # no texture coordinates
    tree, _ = read_glb(write_gltf(tmp_path / "e.glb", box, _uniform_with(emissive=np.full((1, 1, 3), [0.5, 2.0, 0.0]))))
    np.testing.assert_allclose(tree["materials"][0]["emissiveFactor"], [0.5, 1.0, 0.0])  # clipped, as the texture
    assert "images" not in tree

    # a 1 x 1 occlusion on a mesh without texture coordinates: 1 x 1 textures read at uv (0, 0)
    tree, blob = read_glb(write_gltf(tmp_path / "o1.glb", box, _uniform_with(occlusion=np.full((1, 1, 1), 0.4))))
    prim = tree["meshes"][0]["primitives"][0]
    np.testing.assert_array_equal(glb_accessor(tree, blob, prim["attributes"]["TEXCOORD_0"]), 0.0)
    mat = tree["materials"][prim["material"]]
    assert glb_image(tree, blob, mat["occlusionTexture"]["index"])[0, 0, 0] == round(0.4 * 255)

    # an occlusion map larger than the 1 x 1 others, on a mesh with texture coordinates: its own image
    occlusion = np.random.default_rng(4).uniform(0, 1, (3, 2, 1))
    quad = load_mesh(write_quad_glb(tmp_path / "quad.glb"))
    tree, blob = read_glb(write_gltf(tmp_path / "o3.glb", quad, _uniform_with(occlusion=occlusion)))
    mat = tree["materials"][0]
    image = glb_image(tree, blob, mat["occlusionTexture"]["index"])
    np.testing.assert_allclose(image[..., :1] / 255.0, occlusion, atol=0.5 / 255 + 1e-6)
    mr = glb_image(tree, blob, mat["pbrMetallicRoughness"]["metallicRoughnessTexture"]["index"])
    np.testing.assert_allclose(mr[0, 0] / 255.0, [1.0, 0.7, 0.3], atol=0.5 / 255 + 1e-6)
    with pytest.raises(ValueError, match="texture coordinate"):
        write_gltf(tmp_path / "x.glb", box, _uniform_with(occlusion=occlusion))


def test_write_gltf_occlusion_of_its_own_size(tmp_path):
    """An occlusion map whose size differs from metallic and roughness cannot share their
    packed image (R = 1 there); it gets its own."""
    from pbrfit.scene.mesh import load_mesh

    rng = np.random.default_rng(5)
    m = _material(rng, size=(4, 6))
    occlusion = rng.uniform(0, 1, (2, 2, 1)).astype(np.float32)
    m = Material(base_color=m.base_color, metallic=m.metallic, roughness=m.roughness, occlusion=occlusion)
    tree, blob = read_glb(write_gltf(tmp_path / "m.glb", load_mesh(write_quad_glb(tmp_path / "quad.glb")), m))
    mat = tree["materials"][0]
    image = glb_image(tree, blob, mat["occlusionTexture"]["index"])
    np.testing.assert_allclose(image[..., :1] / 255.0, occlusion, atol=0.5 / 255 + 1e-6)


# --- glTF export --------------------------------------------------------------------------------
def test_write_gltf_uv_and_texture_orientation(tmp_path):
    from pbrfit.scene.mesh import load_mesh

    mesh = load_mesh(write_quad_glb(tmp_path / "quad.glb"))
    rng = np.random.default_rng(2)
    m = _material(rng, normal=True, size=(4, 6))
    base = np.asarray(m.base_color).copy()
    base[0] = [1.0, 0.0, 0.0]  # row 0 (v = 0) red
    m = Material(base_color=base, metallic=m.metallic, roughness=m.roughness, normal=m.normal)
    out = write_gltf(tmp_path / "out" / "material.glb", mesh, m)
    assert _listing(out.parent) == ["material.glb"]

    tree, blob = read_glb(out)
    prim = tree["meshes"][0]["primitives"][0]
    np.testing.assert_allclose(glb_accessor(tree, blob, prim["attributes"]["TEXCOORD_0"]), QUAD_UV_GLTF)
    np.testing.assert_allclose(glb_accessor(tree, blob, prim["attributes"]["NORMAL"]), mesh.vertex_normals, atol=1e-7)
    mat = tree["materials"][prim["material"]]
    pbr = mat["pbrMetallicRoughness"]
    assert pbr["metallicFactor"] == 1.0 and pbr["roughnessFactor"] == 1.0
    color = glb_image(tree, blob, pbr["baseColorTexture"]["index"])
    assert color.shape == (4, 6, 3)
    np.testing.assert_array_equal(color[0], np.broadcast_to([255, 0, 0], (6, 3)))  # row 0 is v = 0
    np.testing.assert_allclose(color / 255.0, linear_to_srgb(base), atol=0.5 / 255 + 1e-6)
    mr = glb_image(tree, blob, pbr["metallicRoughnessTexture"]["index"])
    np.testing.assert_allclose(mr[..., 1:2] / 255.0, m.roughness, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(mr[..., 2:3] / 255.0, m.metallic, atol=0.5 / 255 + 1e-6)
    assert "normalTexture" in mat and mat["doubleSided"] is True

    # and it loads back through trimesh (via load_mesh) with the same uv
    again = load_mesh(out)
    np.testing.assert_allclose(again.visual.uv, QUAD_UV_GLTF)
    np.testing.assert_allclose(again.vertices, mesh.vertices)


def test_write_gltf_turns_a_z_up_world_upright(tmp_path):
    """glTF is +Y up: a +z world's mesh goes under a root node whose rotation is the axis change
    the environment makes for a +z world (`to_environment_frame`), its vertex data untouched, so
    the quad (the z = 0 floor, facing +z) faces +Y in a viewer; a +y world gets no transform."""
    import jax.numpy as jnp
    import trimesh

    from pbrfit.lighting.environment import to_environment_frame
    from pbrfit.scene.mesh import load_mesh

    mesh = load_mesh(write_quad_glb(tmp_path / "quad.glb"))
    m = _material(np.random.default_rng(6), size=(4, 4))
    dirs = np.random.default_rng(7).normal(size=(16, 3))
    for up, floor_normal in (("+y", [0, 0, 1]), ("+z", [0, 1, 0])):
        out = write_gltf(tmp_path / f"{up[1]}.glb", mesh, m, up)
        tree, blob = read_glb(out)
        prim = tree["meshes"][0]["primitives"][0]
        np.testing.assert_array_equal(glb_accessor(tree, blob, prim["attributes"]["POSITION"]),
                                      np.asarray(mesh.vertices, np.float32))
        [(_, world)] = glb_mesh_transforms(tree)
        np.testing.assert_allclose(dirs @ world[:3, :3].T, to_environment_frame(jnp.asarray(dirs), up), atol=1e-6)
        normals = glb_accessor(tree, blob, prim["attributes"]["NORMAL"]) @ world[:3, :3].T
        np.testing.assert_allclose(normals, np.broadcast_to(floor_normal, normals.shape), atol=1e-6)
        # trimesh, a reader of its own, applies the node transform too: the floor's faces face up
        np.testing.assert_allclose(trimesh.load(out, force="mesh").face_normals, [floor_normal] * 2, atol=1e-6)
    assert len(tree["nodes"]) == 2 and tree["scenes"][0]["nodes"] == [1]  # +z: one root node added
    tree, _ = read_glb(tmp_path / "y.glb")
    assert [set(node) - {"name"} for node in tree["nodes"]] == [{"mesh"}]  # +y: no transform at all
    with pytest.raises(ValueError, match="world_up"):
        write_gltf(tmp_path / "x.glb", mesh, m, "-z")


def test_write_gltf_names_buffer_view_targets_and_a_repeat_sampler(tmp_path):
    """Vertex data in ARRAY_BUFFER views, indices in an ELEMENT_ARRAY_BUFFER view, images in
    views without a target; every texture samples REPEAT, LINEAR magnified and trilinear
    minified; a uniform material has no texture and no sampler."""
    import trimesh

    from pbrfit.scene.mesh import load_mesh

    mesh = load_mesh(write_quad_glb(tmp_path / "quad.glb"))
    tree, _ = read_glb(write_gltf(tmp_path / "m.glb", mesh, _material(np.random.default_rng(8), normal=True)))
    prim = tree["meshes"][0]["primitives"][0]
    target = lambda accessor: tree["bufferViews"][tree["accessors"][accessor]["bufferView"]].get("target")
    assert {name: target(a) for name, a in prim["attributes"].items()} == {
        "POSITION": 34962, "NORMAL": 34962, "TEXCOORD_0": 34962}
    assert target(prim["indices"]) == 34963
    assert all("target" not in tree["bufferViews"][image["bufferView"]] for image in tree["images"])
    assert tree["samplers"] == [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 10497}]
    assert len(tree["textures"]) == 3 and all(t["sampler"] == 0 for t in tree["textures"])
    tree, _ = read_glb(write_gltf(tmp_path / "u.glb", trimesh.creation.box(), Material.uniform([0.5] * 3, 0.0, 0.5)))
    assert "samplers" not in tree and "textures" not in tree
    assert {tree["bufferViews"][v]["target"] for v in range(len(tree["bufferViews"]))} == {34962, 34963}


def _png_chunks(path):
    import struct

    data, chunks, at = Path(path).read_bytes(), [], 8
    while at < len(data):
        length, kind = struct.unpack(">I4s", data[at:at + 8])
        chunks.append(kind.decode())
        at += 12 + length
    return chunks


def test_png_colour_chunks_say_what_the_pixels_hold(tmp_path):
    """base_color.png is sRGB-encoded (sRGB chunk); metallic_roughness.png and normal.png hold
    linear data (gAMA 1.0, no sRGB chunk), which a reader that honours the chunks must not decode."""
    m = _material(np.random.default_rng(3), normal=True, size=(2, 3))
    write_material(tmp_path / "m", m)
    assert "sRGB" in _png_chunks(tmp_path / "m" / "base_color.png")
    for name in ("metallic_roughness.png", "normal.png"):
        chunks = _png_chunks(tmp_path / "m" / name)
        assert "gAMA" in chunks and "sRGB" not in chunks and "cHRM" not in chunks, (name, chunks)
    for space in ("srgb", "linear"):
        write_image(tmp_path / f"{space}.png", np.full((2, 2, 3), 0.5), "uint16", color_space=space)
        assert ("sRGB" in _png_chunks(tmp_path / f"{space}.png")) == (space == "srgb")
        np.testing.assert_allclose(read_image(tmp_path / f"{space}.png")[0], round(0.5 * 65535) / 65535)
    with pytest.raises(ValueError, match="color_space"):
        write_image(tmp_path / "x.png", np.zeros((2, 2, 3)), "uint8", color_space="rec2020")


def test_only_exr_and_associated_tiff_alpha_count_as_premultiplied(tmp_path):
    rgba = np.random.default_rng(0).random((4, 4, 4)).astype(np.float32)
    for name, dtype, associated in (("a.exr", "float", True), ("a.png", "uint8", False), ("a.bmp", "uint8", False),
                                    ("a.tif", "uint16", False)):
        write_image(tmp_path / name, rgba, dtype)
        info = read_image(tmp_path / name)[1]
        assert info.alpha_channel == 3 and info.associated_alpha is associated, name
    # a TIFF written the way most tools write one, without the unassociated-alpha tag: premultiplied
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(tmp_path / "b.tif"))
    assert out.open(str(tmp_path / "b.tif"), oiio.ImageSpec(4, 4, 4, "uint16")) and out.write_image(rgba)
    out.close()
    info = read_image(tmp_path / "b.tif")[1]
    assert info.alpha_channel == 3 and info.associated_alpha is True


def test_convergence_plot_survives_non_finite_losses(tmp_path):
    from pbrfit.io.outputs import _convergence_plot

    history = [dict(step=0, loss=float("inf")), dict(step=1, loss=float("nan")), dict(step=2, loss=0.5),
               dict(step=3, loss=0.01)]
    _convergence_plot(tmp_path / "c.png", history)
    _convergence_plot(tmp_path / "d.png", history[:2])  # nothing finite: an empty frame
    drawn, empty = read_image(tmp_path / "c.png")[0], read_image(tmp_path / "d.png")[0]
    assert drawn.shape == empty.shape == (320, 520, 3)
    assert drawn.min() < 0.5 < drawn.max() and not np.array_equal(drawn, empty)  # a curve on c only


def _write_oiio(path, pixels, names=None, fmt="float"):
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], fmt)
    if names is not None:
        spec.channelnames = names
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(pixels)
    out.close()
    return path


def test_damaged_or_non_colour_images_are_refused(tmp_path):
    from pbrfit.io.images import color_channels

    rng = np.random.default_rng(0)
    jpg = _write_oiio(tmp_path / "f.jpg", (rng.random((32, 32, 3)) * 255).astype(np.uint8), fmt="uint8")
    assert read_image(jpg)[0].shape == (32, 32, 3)
    data = jpg.read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) * 6 // 10])  # decodes, its lost rows grey
    with pytest.raises(CaptureError, match=r"frame: image .*cut.jpg is damaged: .*Premature end of JPEG"):
        read_image(tmp_path / "cut.jpg", "frame")
    for names, match in ((["Z", "ID"], "no colour channels .* only Z, ID"), (["N.X", "N.Y", "N.Z"], "only N.X, N.Y, N.Z"),
                         (["X", "Y", "Z"], "CIE X, Y, Z")):
        path = _write_oiio(tmp_path / f"{len(names)}{names[0]}.exr", np.ones((4, 4, len(names)), np.float32), names)
        with pytest.raises(CaptureError, match=match):
            color_channels(read_image(path)[1], "frame")
    for name in ("R", "L"):  # one channel, of any name, is a grey image
        grey = _write_oiio(tmp_path / f"{name}.exr", np.ones((4, 4, 1), np.float32), [name])
        assert color_channels(read_image(grey)[1], "frame") == [0]


def test_output_folder_through_a_link(tmp_path):
    """A link is followed to the folder it names, which the output replaces (the link stays); a
    link to nothing is refused before any work."""
    target = tmp_path / "target"
    target.mkdir()
    (tmp_path / "link").symlink_to(target)
    with atomic_dir(tmp_path / "link", kind="fit") as d:
        (d / "report.json").write_text("{}")
    assert (tmp_path / "link").is_symlink() and _listing(target) == [OUTPUT_MARKER, "report.json"]
    with pytest.raises(CaptureError, match=r"link: holds the material folder"):  # an input the link leads to
        check_not_inside(target, tmp_path / "link", "material folder")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    with pytest.raises(CaptureError, match=r"dangling: is a link to .*nowhere, which does not exist"):
        check_output_dir(tmp_path / "dangling", "fit")


def test_a_cache_that_cannot_be_written_is_a_warning(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.warns(CacheWarning, match=r"cache folder .*file/sub: cannot write \(Not a directory\)"):
        write_cache_file(tmp_path / "file" / "sub" / "g.npz", lambda f: f.write(b"1"))
    write_cache_file(tmp_path / "ok" / "g.npz", lambda f: f.write(b"1"))
    assert (tmp_path / "ok" / "g.npz").read_bytes() == b"1" and _listing(tmp_path / "ok") == ["g.npz"]


def test_atomic_dir_names_refusals_by_the_output_and_keeps_bugs(tmp_path):
    # a full disk whose write() names no file: the output folder is named; a missing folder
    # inside the temporary one is a bug, not the system refusing, and stays an OSError
    import errno

    out = tmp_path / "out"
    with pytest.raises(CaptureError, match=r"out: cannot write: No space left on device; nothing was written"):
        with atomic_dir(out, kind="fit"):
            raise OSError(errno.ENOSPC, "No space left on device")
    with pytest.raises(CaptureError, match=r"out/views/0.png: cannot write: Permission denied"):
        with atomic_dir(out, kind="fit") as d:
            raise PermissionError(errno.EACCES, "Permission denied", str(d / "views" / "0.png"))
    with pytest.raises(FileNotFoundError):
        with atomic_dir(out, kind="fit") as d:
            (d / "missing" / "report.json").write_text("{}")
    with pytest.raises(CaptureError, match=r"^cannot write image \S*/out/images/2.exr: disk full$"):
        with atomic_dir(out, kind="fit") as d:
            raise CaptureError(f"cannot write image {d / 'images' / '2.exr'}: disk full")
    assert not out.exists() and list(tmp_path.iterdir()) == []
