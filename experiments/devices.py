"""Devices: the peer fit on one device and sharded over four, back to back in one environment.

On the CPU the number of devices is fixed when JAX starts, so both fits run as
``pbrfit fit CAP --out OUT --resolution 64 --devices N --quiet --cache FRESH`` in a new process
with ``XLA_FLAGS=--xla_force_host_platform_device_count=4`` (four host devices, the same for
both): N = 1, then N = 4, each with an empty cache (cold), launch-to-exit wall time. The capture
is ``pbrfit synth peer-plane`` (6 views of 128², 4 point lights, noiseless). Reported: both wall
times and their ratio, the largest per-texel difference of each fitted map between the two, the
steps and the RMSE against ``truth/``.

    python experiments/devices.py [--out experiments/results/devices.json]

Four host devices share the same cores as one, so on a CPU the ratio measures the cost of the
sharded program (padding, collectives), not a speed-up; the maps' agreement is the point.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DEVICES = 4
MAPS = ("base_color", "metallic", "roughness")


def _pbrfit(*args: str, env: dict) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "pbrfit.cli.main", *args], env=env, check=True)
    return time.perf_counter() - t0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "devices.json"))
    args = parser.parse_args()
    from pbrfit.io.images import read_image

    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=f"--xla_force_host_platform_device_count={DEVICES}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        _pbrfit("synth", "peer-plane", "--out", str(tmp / "cap"), "--quiet", env=env)
        runs = {}
        for n in (1, DEVICES):
            out = tmp / f"fit{n}"
            wall = _pbrfit("fit", str(tmp / "cap"), "--out", str(out), "--resolution", "64", "--devices", str(n),
                           "--quiet", "--cache", str(tmp / f"cache{n}"), env=env)
            report = json.loads((out / "report.json").read_text())
            runs[n] = dict(wall_s=wall, steps=report["steps"], devices=len(report["devices"]),
                           truth_rmse=report["truth_rmse"])
            print(f"devices {n}: {wall:.1f} s, {report['steps']} steps, truth RMSE {report['truth_rmse']}")
        diff = {name: float(np.max(np.abs(read_image(tmp / "fit1" / f"{name}.exr")[0]
                                          - read_image(tmp / f"fit{DEVICES}" / f"{name}.exr")[0])))
                for name in MAPS}
    result = dict(scene="peer-plane", resolution=64, runs={str(k): v for k, v in runs.items()},
                  wall_ratio=runs[DEVICES]["wall_s"] / runs[1]["wall_s"], max_map_difference=diff)
    print(f"ratio {result['wall_ratio']:.2f}; largest map differences {diff}")
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
