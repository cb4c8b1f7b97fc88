"""The first run's helper process (`moex.kernels.cpu.warm`): the run waits for the kernels the
helper compiles, only while the helper runs and only until the kernel is in the cache."""

import subprocess
import sys
import time
from types import SimpleNamespace

import pytest

from moex.kernels.cpu import warm


def _kernel(name, index_path):
    """A stand-in for a numba dispatcher: its name and where its cache index would be."""
    return SimpleNamespace(__name__=name, _cache=SimpleNamespace(
        _cache_file=SimpleNamespace(_index_path=str(index_path))))


@pytest.fixture
def helper(monkeypatch):
    """A helper process that runs for 0.6 s."""
    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(0.6)"])
    monkeypatch.setattr(warm, "_helper", process)
    yield process
    process.kill()
    process.wait()


def test_the_run_waits_for_a_kernel_the_helper_compiles_until_the_helper_ends(helper, tmp_path):
    start = time.perf_counter()
    assert warm.wait_for(_kernel("_closed_blocks", tmp_path / "missing.nbi"))
    assert time.perf_counter() - start > 0.3
    assert helper.poll() is not None


def test_the_run_stops_waiting_when_the_kernel_is_in_the_cache(helper, tmp_path):
    index = tmp_path / "kernel.nbi"
    index.write_text("")
    start = time.perf_counter()
    assert not warm.wait_for(_kernel("_gating_items", index))
    assert time.perf_counter() - start < 0.3
    assert helper.poll() is None


def test_the_run_never_waits_for_a_kernel_the_helper_does_not_compile(helper, tmp_path):
    assert not warm.wait_for(_kernel("_expert_items", tmp_path / "missing.nbi"))
    assert helper.poll() is None


def test_without_a_helper_nothing_waits(monkeypatch, tmp_path):
    monkeypatch.setattr(warm, "_helper", None)
    assert not warm.wait_for(_kernel("_closed_blocks", tmp_path / "missing.nbi"))
