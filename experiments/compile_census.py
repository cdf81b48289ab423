"""Which XLA compiles a test run (or any run) makes, and for how long: a census.

As a pytest plugin it records every compile request JAX makes in each test process (xdist
workers included), one JSON line each: the test running, the program's name, the seconds the
request took, its persistent-cache key and whether the cache had it. As a script it summarises
those lines.

```
PBRFIT_COMPILE_CENSUS=/tmp/census PYTHONPATH=experiments python -m pytest -n 2 -p compile_census
python experiments/compile_census.py /tmp/census            # by program, by test file, by test
python experiments/compile_census.py /tmp/census --program jit_solve
```

It wraps `jax._src.compiler.compile_or_get_cached` (and reads the key and the cache's answer
from two of its helpers), JAX internals of the version the project pins: a study's tool, not
part of pbrfit. Subprocesses a test starts are not counted. Results: experiments/speed.md.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import threading
import time
from pathlib import Path

_FOLDER = os.environ.get("PBRFIT_COMPILE_CENSUS")
_current = {"test": None}
_local = threading.local()
_out = None


def _write(record: dict) -> None:
    global _out
    if _out is None:
        Path(_FOLDER).mkdir(parents=True, exist_ok=True)
        name = f"{os.environ.get('PYTEST_XDIST_WORKER', 'main')}-{os.getpid()}.jsonl"
        _out = open(Path(_FOLDER) / name, "a")
    _out.write(json.dumps(record) + "\n")
    _out.flush()


def _install() -> None:
    import jax._src.compiler as compiler

    resolve, read, compile_or_get = (compiler._resolve_compilation_strategy, compiler._cache_read,
                                     compiler.compile_or_get_cached)

    def resolve_keyed(*args, **kwargs):
        key, options = resolve(*args, **kwargs)
        _local.key = key
        return key, options

    def read_noted(*args, **kwargs):
        executable, seconds = read(*args, **kwargs)
        _local.hit = executable is not None
        return executable, seconds

    def timed(backend, computation, *args, **kwargs):
        _local.key = _local.hit = None
        t0 = time.perf_counter()
        try:
            return compile_or_get(backend, computation, *args, **kwargs)
        finally:
            name = str(computation.operation.attributes["sym_name"]).strip('"')
            _write(dict(test=_current["test"], program=name, seconds=round(time.perf_counter() - t0, 4),
                        key=_local.key, hit=_local.hit, thread=threading.current_thread().name))

    compiler._resolve_compilation_strategy = resolve_keyed
    compiler._cache_read = read_noted
    compiler.compile_or_get_cached = timed


if _FOLDER:
    _install()


def pytest_runtest_setup(item):
    _current["test"] = item.nodeid


def _rows(folder: Path) -> list[dict]:
    rows = []
    for path in sorted(folder.glob("*.jsonl")):
        rows += [json.loads(line) | {"process": path.stem} for line in path.read_text().splitlines() if line]
    return rows


def _table(title: str, groups: dict, top: int) -> None:
    print(f"\n{title}: seconds, compiles")
    for name, (seconds, count) in sorted(groups.items(), key=lambda kv: -kv[1][0])[:top]:
        print(f"  {seconds:8.1f} {count:6d}  {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--program", help="break one program's compiles down by test")
    parser.add_argument("--top", type=int, default=25)
    args = parser.parse_args()
    rows = _rows(args.folder)
    misses = [r for r in rows if not r["hit"]]
    print(f"{len(rows)} compile requests, {sum(r['seconds'] for r in rows):.0f} s; "
          f"{len(rows) - len(misses)} read from the persistent cache; "
          f"{len(misses)} compiled, {sum(r['seconds'] for r in misses):.0f} s")
    by_key = collections.defaultdict(list)
    for r in misses:
        if r["key"] is not None:  # None: the persistent cache was off, no key to compare
            by_key[r["key"]].append(r["seconds"])
    again = [s for seconds in by_key.values() for s in seconds[1:]]
    print(f"compiled more than once (by key): {len(again)} compiles, {sum(again):.0f} s")

    def grouped(select, rows):
        groups = collections.defaultdict(lambda: [0.0, 0])
        for r in rows:
            g = groups[select(r)]
            g[0] += r["seconds"]
            g[1] += 1
        return groups

    if args.program:
        chosen = [r for r in misses if r["program"] == args.program]
        _table(f"{args.program}, by test", grouped(lambda r: str(r["test"]), chosen), args.top)
        return
    _table("by program", grouped(lambda r: r["program"], misses), args.top)
    _table("by test file", grouped(lambda r: str(r["test"]).split("::")[0], misses), args.top)
    _table("by test", grouped(lambda r: str(r["test"]), misses), args.top)


if __name__ == "__main__":
    main()
