"""Reruns are bit-identical whatever numba's kernel cache holds.

The compiled kernels once gave different last bits when compiled in the process and when loaded
from the disk cache (fused multiply-adds chosen differently in the two compilation contexts);
the chaotic closed loop amplified them into different metrics. This test trains the same small
problem in a fresh process that compiles every kernel (empty cache) and in one that loads them
all from that cache, and compares every tensor of the checkpoint bit for bit, the history and
the metric table. It compiles every kernel once (about two minutes on two cores).
"""

import os
import subprocess

import pandas as pd
import torch

from tests.test_cli import MOEX, TINY

# long enough for last-bit differences to reach the parameters (they did within 5 steps)
LONGER = ["task.length=100", "train.experts.steps=30", "train.gating.steps=30",
          "train.experts.adaptive_lr=true"]


def _train(run_dir, cache_dir, cwd):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir), "PYTHONUNBUFFERED": "1"}
    result = subprocess.run(MOEX + ["train", "task=lissajous2", *TINY, *LONGER,
                                    f"hydra.run.dir={run_dir}"],
                            cwd=cwd, capture_output=True, text=True, env=env, timeout=900)
    assert result.returncode == 0, result.stderr
    return result


def _tensors(tree, prefix=""):
    """Every tensor in a checkpoint, by its path of keys."""
    if isinstance(tree, torch.Tensor):
        return {prefix: tree}
    if isinstance(tree, dict):
        return {k: v for key, value in tree.items() for k, v in
                _tensors(value, f"{prefix}/{key}").items()}
    return {}


def test_compiled_and_cached_kernels_give_identical_runs(tmp_path):
    cache = tmp_path / "numba-cache"
    fresh, cached = tmp_path / "fresh", tmp_path / "cached"
    _train(fresh, cache, tmp_path)  # empty cache: every kernel compiled in the process
    assert any(cache.rglob("*.nbi")), "the first run left no kernel cache"
    _train(cached, cache, tmp_path)  # every kernel loaded from the cache
    a = _tensors(torch.load(fresh / "checkpoint.pt", weights_only=True))
    b = _tensors(torch.load(cached / "checkpoint.pt", weights_only=True))
    assert a.keys() == b.keys() and len(a) > 10
    for key in a:
        assert torch.equal(a[key], b[key]), f"{key} differs between compiled and cached kernels"
    for name in ("history.csv", "metrics.csv"):
        pd.testing.assert_frame_equal(pd.read_csv(fresh / name), pd.read_csv(cached / name),
                                      check_exact=True)


_PROBE = """
import numpy as np
from moex.kernels.cpu import rnn, simd
LB = simd.width(np.float64)
z = np.zeros((1, 1, LB))
args = (z, z, z, z, z[0], z[0], z[0] + 1.0, z[0], True, z[0], z, z,  # T = H = inputs = 1
        np.zeros((0, 1, LB)), np.zeros((0, LB)), np.zeros((0, LB)), ((), (), ()))
rnn.forward_pass(*args)
stats = rnn.forward_pass.stats
print(rnn.__file__, sum(stats.cache_hits.values()), sum(stats.cache_misses.values()))
"""


def test_a_kernel_cached_before_an_edit_of_a_file_it_inlines_from_is_compiled_afresh(tmp_path):
    """numba keys a cached function on its own file only; the cpu package keys its kernels on all
    of its sources (`moex.kernels.cpu.cache`). On a copy of the package: `rnn.forward_pass` compiled
    into an empty cache is loaded by the next process; after an edit of simd.py alone (which
    `forward_pass` inlines, rnn.py unchanged) the next process compiles it afresh instead of loading
    the stale entry. A function outside the package keeps numba's own key."""
    import shutil
    import sys
    from pathlib import Path

    from numba import njit

    from moex.compile_helper import kernel_sources
    from moex.kernels.cpu import rnn

    shutil.copytree(Path(rnn.__file__).parents[3] / "moex", tmp_path / "moex",
                    ignore=shutil.ignore_patterns("__pycache__"))
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}

    def probe():
        done = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                              env=env, cwd=tmp_path, timeout=600)
        assert done.returncode == 0, done.stderr
        where, hits, misses = done.stdout.split()
        assert Path(where).is_relative_to(tmp_path)  # the copy
        return int(hits), int(misses)

    assert probe() == (0, 1)  # an empty cache: compiled
    assert probe() == (1, 0)  # loaded
    with open(tmp_path / "moex" / "kernels" / "cpu" / "simd.py", "a") as simd:
        simd.write("# an edit\n")
    assert probe() == (0, 1)  # compiled afresh, not the stale entry
    assert type(rnn.forward_pass._cache._impl.locator).__name__.startswith("Package")
    assert rnn.forward_pass._cache._impl.locator.get_source_stamp() == kernel_sources()

    @njit(cache=True)
    def outside(x):  # pragma: no cover
        return x + 1

    assert not type(outside._cache._impl.locator).__name__.startswith("Package")
