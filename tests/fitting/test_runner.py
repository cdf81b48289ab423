"""The persistent compilation cache pbrfit keeps (`pbrfit.fitting.runner.enable_compilation_cache`)."""

import os

from jax._src.lru_cache import LRUCache

from pbrfit.fitting.runner import COMPILATION_CACHE_BYTES, stamp_cache_entries


def test_entries_of_an_unsized_cache_get_an_access_time(tmp_path):
    """A folder an earlier pbrfit filled without eviction: its entries have no access time, and a
    sized cache then failed to write any new entry beside them (FileNotFoundError on the first
    entry's "-atime"). Stamped, old entries keep their times and new writes go through."""
    old = tmp_path / "jit_f-1-cache"
    old.write_bytes(b"old executable")
    os.utime(old, ns=(1_000_000_000, 2_000_000_000))
    kept = tmp_path / "jit_g-2-cache"
    kept.write_bytes(b"stamped executable")
    (tmp_path / "jit_g-2-atime").write_bytes((5).to_bytes(8, "little"))
    stamp_cache_entries(tmp_path)
    assert (tmp_path / "jit_f-1-atime").read_bytes() == (2_000_000_000).to_bytes(8, "little")
    assert (tmp_path / "jit_g-2-atime").read_bytes() == (5).to_bytes(8, "little")
    cache = LRUCache(str(tmp_path), max_size=COMPILATION_CACHE_BYTES)
    cache.put("jit_h-3", b"new executable")
    assert cache.get("jit_h-3") == b"new executable" and cache.get("jit_f-1") == b"old executable"
    stamp_cache_entries(tmp_path / "absent")  # a folder not made yet: nothing to do


def test_pending_tables_give_their_shapes_at_once_and_the_tables_when_built():
    """`PendingTables`: the placeholder has the tables' structure, shapes and dtypes (zeros), and
    `result` the tables `build` makes; an error in `build` is raised by `start`."""
    import jax.numpy as jnp
    import numpy as np
    import pytest

    from pbrfit.fitting.runner import PendingTables

    build = lambda: dict(a=jnp.arange(6.0).reshape(2, 3), b=(jnp.ones(4, jnp.int32),))  # noqa: E731
    pending = PendingTables.start(build)
    assert pending.placeholder["a"].shape == (2, 3) and pending.placeholder["b"][0].dtype == np.int32
    assert not np.any(pending.placeholder["a"])
    np.testing.assert_array_equal(pending.result()["a"], build()["a"])
    assert pending.seconds >= 0.0

    def broken():
        raise ValueError("no environment here")

    with pytest.raises(ValueError, match="no environment here"):
        PendingTables.start(broken)


def test_a_fit_builds_the_split_sum_tables_while_it_compiles(tmp_path, monkeypatch):
    """`fit` of a capture under an environment builds the split sum's tables in a thread
    (`PendingTables`), and fitting with them pending gives the maps that the tables themselves
    give, to the bit."""
    import numpy as np

    import pbrfit
    from data_synth.presets import make_scene
    from data_synth.writer import synthesize
    from pbrfit.fitting import api
    from pbrfit.fitting.api import fit_observations
    from pbrfit.fitting.observations import observations_from_capture
    from pbrfit.fitting.runner import PendingTables
    from pbrfit.render.views import capture_ibl, model_for_capture

    synthesize(make_scene("sphere-floor", size=20, views=3, texture_size=8, noise=0.0), tmp_path / "cap")
    capture = pbrfit.load_capture(tmp_path / "cap")
    started = []
    start = PendingTables.start
    monkeypatch.setattr(api.PendingTables, "start", classmethod(lambda cls, build: started.append(1) or start(build)))
    lean = dict(resolution=8, max_steps=6, search=False, repair=False, uniform_check=False)
    fitted = pbrfit.fit(capture, ibl="split_sum", occlusion="off", pixel_samples=1, **lean)
    assert fitted.report["ibl"]["seconds"] > 0.0 and started == [1]
    monkeypatch.undo()
    model = model_for_capture(capture)
    obs = observations_from_capture(capture)
    tables = capture_ibl(capture, model=model)
    now = fit_observations(obs, model=model, ibl=tables, **lean)
    pending = PendingTables.start(lambda: capture_ibl(capture, model=model))
    later = fit_observations(obs, model=model, ibl=pending, **lean)
    for name in ("base_color", "metallic", "roughness"):
        np.testing.assert_array_equal(np.asarray(getattr(later.material, name)),
                                      np.asarray(getattr(now.material, name)))
    assert later.report["steps"] == now.report["steps"]
