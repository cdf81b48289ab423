"""A fit's checkpoint: the journal of its solver runs, from which an interrupted fit goes on.

A fit is deterministic, so a fit resumed from its checkpoint runs its pipeline again from the
start, and each solver run (`pbrfit.fitting.runner.Runner`) that the journal holds, the same
run (`call_id`: its number in the fit, its start x0, its problem and its step budget), returns
the x and counts the journal kept instead of solving; the first run the journal does not hold
solves for real, from the journal's partial run where that is the one (the structured solver's
state after its last whole part, `pbrfit.fitting.solvers.structured.LMCarry`). What runs between
the solves (the grid start, the search, the stages' host-side work) runs again; the maps come
out as those of a fit never interrupted, to the bit.

The checkpoint is a folder beside the output folder (`checkpoint_folder`, never inside it) that
holds ``checkpoint.json`` (the fingerprint of the fit: its inputs and options, and the journal's
entries), one ``call-NNNN.npy`` per run journaled and ``partial.npz``; each file is written under
a temporary name and renamed into place (`pbrfit.io.atomic.atomic_path`), the data before the
entry that names it, so a kill at any moment leaves a checkpoint that is whole up to its last
entry. The command removes it once the output is written.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np

from ..errors import CaptureError
from ..io.atomic import atomic_open

__all__ = ["Checkpoint", "checkpoint_folder", "call_id", "folder_digests", "CHECKPOINT_SECONDS", "CHECKPOINT_SUFFIX"]

#: A checkpoint's folder is the output folder's path with this added (`checkpoint_folder`).
CHECKPOINT_SUFFIX = ".pbrfit-checkpoint"
#: The most seconds of solving a kill loses: the structured solver runs in parts of about this
#: long (`pbrfit.fitting.runner.Runner`), and the state after a part is saved where the last save is
#: at least this old. Every solver run's end is saved.
CHECKPOINT_SECONDS = 2.0
#: The journal's index in the folder.
_INDEX = "checkpoint.json"
#: The version of the folder's layout.
_LAYOUT = 1


def checkpoint_folder(out: str | os.PathLike) -> Path:
    """Where the fit writing ``out`` keeps its checkpoint: beside it, ``OUT.pbrfit-checkpoint``."""
    out = Path(os.path.abspath(out))
    return out.with_name(out.name + CHECKPOINT_SUFFIX)


def call_id(number: int, x0, problem, steps: int) -> str:
    """A solver run's identity in a fit: its number, its start's bytes, its problem (shapes, free
    channels, prior weight, the model's environment light) and its step budget, hashed."""
    h = hashlib.sha256(f"{number}:{int(steps)}".encode())
    for part in (x0, problem.free, problem.smooth, problem.pair_weight):
        a = np.ascontiguousarray(np.asarray(part))
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    h.update(repr((problem.obs.samples, tuple(problem.index.shape), tuple(problem.pairs.shape),
                   problem.model.ibl)).encode())
    return h.hexdigest()[:32]


def folder_digests(folder: str | os.PathLike, skip: tuple = ()) -> dict:
    """{relative path: SHA-256 of its bytes} of every file under ``folder`` (a file: that one),
    names starting with "." and the paths under ``skip`` left out."""
    root = Path(folder)
    if root.is_file():
        return {root.name: _digest(root)}
    skipped = [Path(os.path.abspath(s)) for s in skip]
    out = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if any(part.startswith(".") for part in rel.parts) or not path.is_file():
            continue
        if any(s == path or s in path.parents for s in skipped):
            continue
        out[rel.as_posix()] = _digest(path)
    return out


def _digest(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _differs(old: Mapping, new: Mapping) -> Optional[str]:
    """The first difference between two fingerprints, in words (None: the same)."""
    for name in ("pbrfit", "options", "files"):
        a, b = old.get(name), new.get(name)
        if a == b:
            continue
        if not isinstance(a, Mapping) or not isinstance(b, Mapping):
            return f"{name} {a} there, {b} now"
        for key in sorted(set(a) | set(b)):
            if a.get(key) != b.get(key):
                if name == "files":
                    what = "is new" if key not in a else ("is gone" if key not in b else "has changed")
                    return f"{key} {what}"
                return f"{key} {a.get(key, '(not given)')} there, {b.get(key, '(not given)')} now"
    return None


class Checkpoint:
    """A fit's checkpoint in ``folder`` (`checkpoint_folder`), for the fit whose inputs and options
    ``fingerprint`` describes ({"pbrfit": version, "options": {name: value}, "files": {path:
    digest}}, JSON). ``resume``: go on from the checkpoint there (none there: start afresh; one of
    another fit, a different fingerprint: `CaptureError` naming the folder and the first
    difference); else one there is replaced. ``seconds``: the most solving a kill may lose
    (`CHECKPOINT_SECONDS`). Nothing is written until the first solver run ends."""

    def __init__(self, folder: str | os.PathLike, fingerprint: Mapping[str, Any], resume: bool = False,
                 seconds: float = CHECKPOINT_SECONDS):
        self.folder, self.seconds = Path(folder), float(seconds)
        self.fingerprint = json.loads(json.dumps(fingerprint))
        self.entries, self.partial = [], None
        self.replayed = self.steps_replayed = 0
        self.resumed_from = None
        self.replaying = False
        self._issued = 0  # solver runs numbered so far in this fit, over every pass and model it fits
        self._saved = time.monotonic()
        index = self.folder / _INDEX
        if self.folder.exists() and not index.is_file() and (not self.folder.is_dir() or any(self.folder.iterdir())):
            raise CaptureError(f"{self.folder}: exists and is not a pbrfit checkpoint; refusing to replace it, "
                               "move it or choose another output folder")
        if resume and index.is_file():
            try:
                saved = json.loads(index.read_text())
                layout, entries, partial = saved["layout"], saved["entries"], saved.get("partial")
                old = saved["fingerprint"]
            except (OSError, ValueError, KeyError, TypeError):
                raise CaptureError(f"{index}: not a readable checkpoint; run without --resume to start again") from None
            differs = _differs(old, self.fingerprint) if layout == _LAYOUT else f"layout {layout} there, {_LAYOUT} now"
            if differs is not None:
                raise CaptureError(f"{self.folder}: a checkpoint of another fit ({differs}); run without --resume "
                                   "to start again, or remove it")
            self.entries, self.partial = list(entries), partial
            self.replaying = bool(self.entries or self.partial)
        elif self.folder.exists():
            shutil.rmtree(self.folder)
        self._journal = list(self.entries)  # what the folder's index lists (a replayed entry is kept)

    # -- replay -----------------------------------------------------------------------------------

    def replay(self, number: int, ident: str, where: Mapping) -> Optional[tuple]:
        """The journaled outcome of run ``number`` (x, info, the progress it reported as (k, E)
        pairs), or None where the journal does not hold it: then the replay ends here (what the
        journal holds after it is dropped), and `resumed` says so, with ``where`` (the progress
        callback's) for the place."""
        if not self.replaying:
            return None
        if number < len(self.entries) and self.entries[number]["id"] == ident:
            entry = self.entries[number]
            x = np.load(self.folder / entry["file"])
            self.replayed += 1
            self.steps_replayed += int(entry["info"].get("steps", 0))
            return x, dict(entry["info"]), [tuple(p) for p in entry["reported"]]
        self._end_replay(number, where)
        return None

    def partial_run(self, number: int, ident: str) -> Optional[tuple]:
        """(x, the structured solver's carry as a dict of arrays) of run ``number`` where the
        journal's partial run is that one (then its steps count as replayed), else None."""
        if self.partial is None or self.partial["number"] != number or self.partial["id"] != ident:
            return None
        with np.load(self.folder / "partial.npz") as data:
            arrays = {name: data[name] for name in data.files}
        self.partial = None
        if int(arrays.pop("number")) != number:  # (a later save, of another run, than the index names)
            return None
        steps = int(arrays["k"]) - 1  # (the file's own: a later save than the index's, after such a kill)
        self.steps_replayed += steps
        self.resumed_from["step"] = steps
        return arrays.pop("x"), arrays

    def _end_replay(self, number: int, where: Mapping) -> None:
        self.replaying = False
        self.resumed_from = dict(where, solver_run=number, step=0)
        del self._journal[number:]
        self.entries = []
        if self.partial is not None and self.partial["number"] != number:
            self.partial = None

    def resumed(self) -> Optional[dict]:
        """The report's "resumed": the solver runs and steps taken from the checkpoint, and where the
        fit went on (the level, footprint, stage part it was at, the run's number and its step), or
        None for a fit that started afresh."""
        if not self.replayed and self.resumed_from is None:
            return None
        return dict(solver_runs_replayed=self.replayed, steps_replayed=self.steps_replayed, at=self.resumed_from)

    def next_run(self) -> int:
        """The next solver run's number in the fit: one count over every `pbrfit.fitting.runner.Runner`
        the fit makes (a fit may run several passes, the footprint's and the light model's
        choices each fitting again), so that every run is journaled under its own number."""
        number, self._issued = self._issued, self._issued + 1
        return number

    # -- saving ------------------------------------------------------------------------------------

    def record(self, number: int, ident: str, x, info: Mapping, reported) -> None:
        """Journal run ``number``'s outcome (x, its info, the (k, E) it reported)."""
        if number < len(self._journal):  # replayed: already there
            return
        name = f"call-{number:04d}.npy"
        self.folder.mkdir(parents=True, exist_ok=True)
        with atomic_open(self.folder / name) as f:
            np.save(f, np.asarray(x))
        self._journal.append(dict(id=ident, file=name, info=dict(info),
                                  reported=[[int(k), float(e)] for k, e in reported]))
        self._write_index(None)

    def save_partial(self, number: int, ident: str, x, steps: int, carry: Mapping) -> None:
        """Keep run ``number``'s state after ``steps`` steps (x, the solver's carry), where the
        last save is `seconds` old."""
        if time.monotonic() - self._saved < self.seconds:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        with atomic_open(self.folder / "partial.npz") as f:
            np.savez(f, x=np.asarray(x), number=np.asarray(number), **{k: np.asarray(v) for k, v in carry.items()})
        self._write_index(dict(number=number, id=ident, steps=int(steps)))

    def _write_index(self, partial: Optional[dict]) -> None:
        text = json.dumps(dict(layout=_LAYOUT, fingerprint=self.fingerprint, entries=self._journal,
                               partial=partial))
        with atomic_open(self.folder / _INDEX) as f:
            f.write(text.encode())
        self._saved = time.monotonic()

    def remove(self) -> None:
        """Remove the checkpoint (the fit's output is written)."""
        shutil.rmtree(self.folder, ignore_errors=True)
