"""The first run's helper process (`moex.precompile`, started by `moex.launch`): the run
waits for the kernels the helper compiles, only while the helper runs and only until the kernel is
in the cache for the run's precision; the command starts a helper only for a cpu training, and the
run adopts it or stops it."""

import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from numba import typeof, types

import moex
from moex import compile_helper, launch
from moex.kernels import cpu
from moex.kernels.cpu import lanes, warm


def _kernel(name, index_path):
    """A stand-in for a numba dispatcher: its name and where its cache index would be."""
    return SimpleNamespace(__name__=name, _cache=SimpleNamespace(
        _cache_file=SimpleNamespace(_index_path=str(index_path))))


@pytest.fixture
def helper(monkeypatch):
    """A helper process that runs for 0.6 s."""
    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(0.6)"])
    monkeypatch.setattr(warm, "_helper", process)
    monkeypatch.setattr(warm, "_dtype", None)
    yield process
    process.kill()
    process.wait()


def test_the_run_waits_for_a_kernel_the_helper_compiles_until_the_helper_ends(helper, tmp_path):
    start = time.perf_counter()
    assert warm.wait_for(_kernel("closed_blocks", tmp_path / "missing.nbi"))
    assert time.perf_counter() - start > 0.3
    assert helper.poll() is not None


def test_the_run_stops_waiting_when_the_kernel_is_in_the_cache(helper, tmp_path):
    index = tmp_path / "kernel.nbi"
    index.write_text("")
    start = time.perf_counter()
    assert not warm.wait_for(_kernel("gating_items", index))
    assert time.perf_counter() - start < 0.3
    assert helper.poll() is None


def test_the_run_never_waits_for_a_kernel_the_helper_does_not_compile(helper, tmp_path):
    assert not warm.wait_for(_kernel("_expert_items", tmp_path / "missing.nbi"))
    assert helper.poll() is None


def test_a_failed_helper_is_said_once_in_the_log(monkeypatch, tmp_path, caplog):
    process = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    process.wait()
    monkeypatch.setattr(warm, "_helper", process)
    monkeypatch.setattr(warm, "_failure_told", False)
    with caplog.at_level("WARNING", logger="moex.kernels.cpu"):
        warm.wait_for(_kernel("closed_blocks", tmp_path / "missing.nbi"))
        warm.wait_for(_kernel("gating_items", tmp_path / "missing.nbi"))
    failures = [r for r in caplog.records if "compile helper" in r.getMessage()]
    assert len(failures) == 1 and "exit code 3" in failures[0].getMessage()


def test_the_helper_calls_every_kernel_it_compiles():
    """`moex.precompile.compile_later_phases` runs the closed loop, phase 2 and the symbols as
    the helper does (its stderr goes nowhere: a call that no longer matches a kernel's signature
    had left every first run compiling them itself)."""
    from moex.kernels.cpu import LATER
    from moex.kernels.cpu.symbols import _nearest
    from moex.precompile import compile_later_phases

    compile_later_phases("float64")
    for kernel in (*LATER, _nearest):
        assert kernel.signatures, kernel


def test_without_a_helper_nothing_waits(monkeypatch, tmp_path):
    monkeypatch.setattr(warm, "_helper", None)
    assert not warm.wait_for(_kernel("closed_blocks", tmp_path / "missing.nbi"))


def _sleeper(told=None):
    """A stand-in helper: it writes what it reads on stdin to the file `told`, then sleeps."""
    script = f"import sys, time; open({str(told)!r}, 'w').write(sys.stdin.readline())" \
        if told else "import time"
    return subprocess.Popen([sys.executable, "-c", script + "; time.sleep(30)"],
                            stdin=subprocess.PIPE, text=True)


def test_a_signature_of_the_runs_precision_counts_as_cached(monkeypatch):
    """Signatures as numba's cache index keeps them (tuples of numba types) and the run's sizes as
    `warm_up` gives them: a string match on two spellings of the types (`str` of the run's, the
    index's `repr`) had found no kernel ever cached, and every later run started a helper and
    waited for it."""
    def kernel(*signatures, name="closed_blocks"):
        keys = {(signature, "magic"): 0 for signature in signatures}
        return SimpleNamespace(__name__=name, _cache=SimpleNamespace(_cache_file=SimpleNamespace(
            _load_index=lambda: keys)))

    f64 = (types.int64, types.Tuple((types.float64[:, :, :, ::1],)))
    f32 = (types.int64, types.Tuple((types.float32[:, :, :, ::1],)))
    assert warm._indexed(kernel(f64), "float64") and not warm._indexed(kernel(f64), "float32")
    assert warm._indexed(kernel(f32), "float32") and not warm._indexed(kernel(f32), "float64")
    assert warm._indexed(kernel(f64, f32), "float32")
    assert not warm._indexed(kernel(), "float64")
    # phase 2's kernel counts only when compiled for the run's sizes (`lanes.sizes`' type)
    monkeypatch.setenv("MOEX_CPU_SIZES", "compiled")  # (the tests' default: runtime)
    ours, theirs = (typeof(lanes.sizes(h, 4, 2)) for h in (15, 7))
    sized = (*f64, ours)
    assert warm._indexed(kernel(sized, name="gating_items"), "float64", _told(15))
    assert not warm._indexed(kernel(sized, name="gating_items"), "float64", _told(7))
    assert not warm._indexed(kernel((*f64, theirs), name="gating_items"), "float64", _told(15))
    assert warm._indexed(kernel(f64), "float64", _told(7))  # the closed loop: any sizes


def _told(units: int) -> types.Type:
    """The sizes `warm.start` is given for a gating RNN of `units` units, 4 inputs, 2 outputs."""
    told = {}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(warm, "start", lambda *args: told.setdefault("sizes", args[3]))
        cpu.warm_up("float64", (units, 4, 2))
    return told["sizes"]


@pytest.mark.parametrize("argv, precision", [
    (["train"], "float64"),
    (["train", "task=reber", "precision=float32", "num_runs=3"], "float32"),
    (["train", "-m", "task.switch_prob=0.5,0.25", "backend=cpu"], "float64"),
    (["train", "+backend=compiled"], "float64"),
    (["train", "precision=float32,float64"], None),  # a sweep over precisions
    (["train", "backend=reference"], None),
    (["train", "backend=gpu", "device=cuda"], None),
    (["train", "device=cuda"], None),
    (["train", "-m", "hydra/launcher=joblib"], None),  # jobs in other processes
    (["train", "--cfg", "job"], None),
    (["evaluate", "run_dir=outputs/x"], None),
    ([], None),
])
def test_the_command_starts_a_helper_only_for_a_cpu_training_in_its_process(argv, precision):
    assert launch.helper_precision(argv) == precision


def test_the_run_adopts_the_commands_helper_of_its_precision_and_tells_it_the_sizes(
        monkeypatch, tmp_path):
    """The run writes its gating RNN's units, inputs and outputs to the helper's stdin, for
    which it compiles phase 2 (`moex.precompile`)."""
    process = _sleeper(tmp_path / "told")
    monkeypatch.setattr(compile_helper, "helper", ("float64", process))
    monkeypatch.setattr(warm, "_helper", None)
    try:
        assert warm.start("float64", (), (15, 4, 2), None) is process
        assert warm._helper is process and compile_helper.helper is None
        deadline = time.monotonic() + 20
        while (not (tmp_path / "told").exists() or not (tmp_path / "told").read_text()) \
                and time.monotonic() < deadline:
            time.sleep(0.05)
        assert (tmp_path / "told").read_text() == "15 4 2\n"
        assert process.poll() is None
    finally:
        process.kill()
        process.wait()


def test_a_helper_of_another_precision_is_stopped(monkeypatch):
    process = _sleeper()
    monkeypatch.setattr(compile_helper, "helper", ("float32", process))
    monkeypatch.setattr(warm, "_helper", None)
    monkeypatch.setattr(warm, "cached", lambda dtype, kernels, sizes: True)  # no helper of its own
    assert warm.start("float64", (), (3, 4, 2), None) is None
    assert process.poll() is not None and compile_helper.helper is None


def test_a_helper_the_run_never_adopted_is_stopped_at_exit(monkeypatch):
    process = _sleeper()
    monkeypatch.setattr(compile_helper, "helper", ("float64", process))
    compile_helper.stop()  # registered with atexit when the command starts a helper
    assert process.poll() is not None and compile_helper.helper is None


def test_the_command_starts_no_helper_once_a_run_found_the_kernels_cached(monkeypatch, tmp_path):
    """A run that finds the helper's kernels cached leaves a stamp (`warm.start`); with it the
    command starts no helper (it would import PyTorch and numba only to find them cached)."""
    monkeypatch.setattr(compile_helper, "stamp", lambda precision: tmp_path / f"{precision}.stamp")
    monkeypatch.setattr(compile_helper, "helper", None)
    monkeypatch.setattr(warm, "_helper", None)
    monkeypatch.setattr(warm, "cached", lambda dtype, kernels, sizes: True)
    assert warm.start("float64", (), (3, 4, 2), None) is None
    assert (tmp_path / "float64.stamp").exists() and not (tmp_path / "float32.stamp").exists()
    compile_helper.start("float64")
    assert compile_helper.helper is None  # stamped: no process
    compile_helper.start("float32")  # another precision: not stamped, a helper starts
    try:
        assert compile_helper.helper is not None and compile_helper.helper[0] == "float32"
    finally:
        compile_helper.stop()


def test_the_stamp_is_named_after_the_kernels_sources_versions_and_precision(monkeypatch,
                                                                              tmp_path):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    name = compile_helper.stamp("float64")
    assert name.parent == tmp_path and name != compile_helper.stamp("float32")
    monkeypatch.setattr(compile_helper.metadata, "version", lambda package: "0.0.0")
    assert compile_helper.stamp("float64") != name  # another numba: another stamp
    compile_helper.mark_cached("float64")
    assert compile_helper.stamp("float64").exists() and not name.exists()


def test_a_kernel_once_used_is_used_with_nothing_around_it(monkeypatch):
    """`lanes.first_use`: a kernel's first use in the process goes through a context of its own
    (it may wait for the helper and log), which marks the kernel ready; every later use gets the
    one do-nothing context (the training loop's every step)."""
    monkeypatch.setattr(lanes, "_ready", set())

    def kernel():  # (hashable, as numba's dispatchers are)
        pass
    first = lanes.first_use(kernel, "test kernel")
    assert first is not lanes._READY
    with first:
        assert kernel not in lanes._ready
    assert lanes.first_use(kernel, "test kernel") is lanes._READY


def test_the_helper_imports_the_runs_own_moex_wherever_the_command_runs(tmp_path):
    """`compile_helper.python`: a working directory holding another moex (a checkout beside an
    installed copy) is not what the helper imports; `python -m` would have put it first."""
    (tmp_path / "moex").mkdir()
    (tmp_path / "moex" / "__init__.py").write_text("")
    argv, env = compile_helper.python("-c", "import moex; print(moex.__file__)")
    found = subprocess.run(argv, env=env, cwd=tmp_path, capture_output=True, text=True,
                           check=True).stdout.strip()
    assert Path(found).resolve() == Path(moex.__file__).resolve()
    plain = subprocess.run([sys.executable, "-c", "import moex; print(moex.__file__)"],
                           cwd=tmp_path, capture_output=True, text=True, check=True).stdout
    assert Path(plain.strip()).resolve().parent == (tmp_path / "moex").resolve()  # (the trap)
