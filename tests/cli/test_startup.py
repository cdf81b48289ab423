"""The parser loads none of the fit's stack: ``--help`` of every command and the usage errors the
parser catches import neither JAX nor optimistix, equinox, OpenImageIO or trimesh (each runs in
a fresh interpreter, since this one has them loaded)."""

import json
import subprocess
import sys

import pytest

from pbrfit.cli.main import _COMMANDS, main
from pbrfit.fitting.defaults import CG_RTOL, MAX_STEPS, SOLVERS
from pbrfit.lighting.settings import PixelIBLSettings

#: What a command's module loads and the parser must not.
HEAVY = ("jax", "jaxlib", "optimistix", "equinox", "OpenImageIO", "trimesh")

# runs each argv through main, its output kept; prints each status and stderr, then what it loaded
_CHILD = """
import contextlib, io, json, sys
from pbrfit.cli.main import main
runs = []
for argv in json.loads(sys.argv[1]):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    runs.append(dict(status=status, out=out.getvalue(), err=err.getvalue()))
heavy = sorted(m for m in sys.modules if m.split(".")[0] in json.loads(sys.argv[2]))
print(json.dumps(dict(runs=runs, heavy=heavy)))
"""


def _run_child(argvs):
    proc = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(argvs), json.dumps(HEAVY)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)


def test_help_of_every_command_loads_no_jax():
    argvs = [["--help"]] + [[name, "--help"] for name in _COMMANDS]
    result = _run_child(argvs)
    assert result["heavy"] == []
    for argv, run in zip(argvs, result["runs"]):
        assert run["status"] == 0 and run["err"] == "", (argv, run)
        assert run["out"].startswith("usage: pbrfit"), (argv, run)


@pytest.mark.parametrize("argv", [
    ["fit", "cap", "--out", "o", "--bogus"],        # unknown flag
    ["fit", "cap", "--out", "o", "--solver", "x"],  # bad choice
    ["fit", "cap"],                                 # missing argument
    ["render", "cap", "--out", "o", "--supersample", "two"],  # not a number
    ["synth", "no-such-preset", "--out", "o"],
    ["no-such-command"],
    [],                                             # no command: after parsing, before any command
])
def test_usage_errors_are_one_line_and_load_no_jax(argv):
    result = _run_child([argv])
    run = result["runs"][0]
    assert result["heavy"] == []
    assert run["status"] == 2 and run["out"] == "", run
    lines = run["err"].splitlines()
    assert len(lines) == 1 and lines[0].startswith("pbrfit: error: "), run


# the console script's way: main() on the process's own command line, in the main thread
_SCRIPT = """
import atexit, json, sys
atexit.register(lambda: print("teardown", flush=True))
sys.argv = ["pbrfit"] + json.loads(sys.argv[1])
from pbrfit.cli.main import main
sys.exit(main())
"""


@pytest.mark.parametrize("argv, status", [
    (["fit", "--help"], 0),                                  # answered by the parser
    (["fit", "no-such-capture", "--out", "o"], 2),           # the command's own error, in its worker
])
def test_the_command_ends_the_process_once_its_output_is_flushed(argv, status, tmp_path):
    """The process ends with the command's status and every line it wrote, without the
    interpreter's teardown (the atexit hook here never runs)."""
    proc = subprocess.run([sys.executable, "-c", _SCRIPT, json.dumps(argv)], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path)
    assert proc.returncode == status, proc.stderr[-3000:]
    assert "teardown" not in proc.stdout
    if status == 0:
        assert proc.stdout.startswith("usage: pbrfit fit") and proc.stderr == "", proc
    else:
        lines = proc.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("pbrfit: error: ") and "no-such-capture" in lines[0], proc
        assert not (tmp_path / "o").exists()


def test_the_parser_shows_the_rooms_defaults_and_choices(capsys):
    # the numbers come from the rooms' JAX-free modules, the ones the fit itself uses
    assert main(["fit", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert f"default {MAX_STEPS})" in text and f"default {CG_RTOL:g};" in text
    assert f"(default {PixelIBLSettings.samples})" in text and f"(default {PixelIBLSettings.levels})" in text
    assert "--solver {" + ",".join(SOLVERS) + "}" in text
