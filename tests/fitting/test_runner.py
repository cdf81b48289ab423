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
