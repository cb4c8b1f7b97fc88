"""Bad input and faults: each ends in one `moex: error:` line (exit 2) or a clean stop (exit
128 + signal), with no traceback, nothing half-written, and a finished run folder untouched."""

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from moex import checkpoint
from moex.config import EvaluateConfig
from moex.verbs.trained import load_run
from tests.test_cli import MOEX, TINY, _moex


def _files(folder: Path) -> dict:
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _one_error_line(result, *fragments) -> str:
    assert result.returncode == 2, result.stderr + result.stdout
    assert "Traceback" not in result.stderr + result.stdout
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("moex: error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A finished tiny two-Lissajous run, evaluated quickly."""
    run_dir = tmp_path_factory.mktemp("trained") / "run"
    result = _moex(["train", "task=lissajous2", *TINY, f"hydra.run.dir={run_dir}"],
                   cwd=run_dir.parent)
    assert result.returncode == 0, result.stderr
    return run_dir


def test_user_files_nan_in_a_stack_complex_values_and_a_byte_order_mark(tmp_path, moex_here):
    stack = np.random.default_rng(0).uniform(-0.5, 0.5, (3, 30, 2))
    stack[2, 7, 1] = np.nan
    np.save(tmp_path / "nan.npy", stack)
    np.save(tmp_path / "complex.npy", stack[:2].astype(complex))
    for name, fragments in [("nan.npy", ["nan.npy (series 2) has NaN or inf values",
                                         "first at step 7"]),
                            ("complex.npy", ["complex128 values", "real numbers"])]:
        result = moex_here(["train", "task=csv", f"task.path={tmp_path}/{name}",
                        f"hydra.run.dir={tmp_path}/run"], cwd=tmp_path)
        _one_error_line(result, *fragments)
        assert not (tmp_path / "run").exists()
    # a UTF-8 byte-order mark is not data: every row of the file is trained on
    rows = "\n".join(f"{0.01 * i:.2f},{-0.01 * i:.2f}" for i in range(20))
    (tmp_path / "bom.csv").write_bytes("\ufeff".encode() + rows.encode())
    result = _moex(["train", "task=csv", f"task.path={tmp_path}/bom.csv",
                    "train.experts.steps=2", "train.gating.steps=2", "eval.enabled=false",
                    f"hydra.run.dir={tmp_path}/bom"], cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    series = torch.load(tmp_path / "bom" / "checkpoint.pt", weights_only=True)["series"]
    assert series.shape == (1, 20, 2) and series[0, 0, 0] == 0.0


def test_data_beyond_the_tanh_range_is_refused_or_scaled_and_mapped_back(tmp_path, moex_here):
    rng = np.random.default_rng(2)
    frame = pd.DataFrame({"time": np.arange(40.0) * 0.6, "x": rng.uniform(-0.5, 0.5, 40)})
    frame.to_csv(tmp_path / "wide.csv", index=False)
    args = ["train", "task=csv", f"task.path={tmp_path}/wide.csv", "train.experts.steps=2",
            "train.gating.steps=2", "eval=quick"]
    result = moex_here([*args, f"hydra.run.dir={tmp_path}/none"], cwd=tmp_path)
    _one_error_line(result, "feature 0 spans [0, 23.4], outside [-1, 1]", "task.scale=auto")
    assert not (tmp_path / "none").exists()
    run_dir = tmp_path / "scaled"
    result = _moex([*args, "task.scale=auto", f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    saved = checkpoint.load(run_dir)
    series = saved.series.numpy()
    assert series.min() == pytest.approx(-0.8) and series.max() == pytest.approx(0.8)
    scale = saved.scale_arrays()
    np.testing.assert_allclose(series[0] * scale["factor"] + scale["offset"],
                               frame.to_numpy(), rtol=1e-12, atol=1e-12)
    # generated outputs come back in the data's units: tanh outputs (|y| < 1) times the factor
    result = _moex(["generate", f"run_dir={run_dir}", "steps=20", f"out_dir={tmp_path}/gen"],
                   cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    outputs = np.load(tmp_path / "gen" / "samples.npz")["outputs"]
    within = (np.abs(outputs - scale["offset"]) <= scale["factor"] + 1e-12).all()
    assert within and np.abs(outputs[..., 0]).max() > 1  # data units, not the model's


def test_a_damaged_checkpoint_in_a_finished_folder_is_refused_untouched(trained, tmp_path,
                                                                        moex_here):
    run_dir = tmp_path / "copy"
    run_dir.mkdir()
    for path, data in _files(trained).items():
        target = run_dir / path.relative_to(trained)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
    whole = (run_dir / "checkpoint.pt").read_bytes()
    (run_dir / "checkpoint.pt").write_bytes(whole[: len(whole) // 2])  # truncated
    before = _files(run_dir)
    for args in (["train", "task=lissajous2", *TINY, f"hydra.run.dir={run_dir}"],
                 ["evaluate", f"run_dir={run_dir}"], ["generate", f"run_dir={run_dir}"]):
        _one_error_line(moex_here(args, cwd=tmp_path), "checkpoint.pt: it cannot be read")
        assert _files(run_dir) == before
    # a finished folder trained with other settings: refused before Hydra writes its config
    result = moex_here(["train", "task=lissajous2", *TINY, "seed=5", f"hydra.run.dir={trained}"],
                   cwd=tmp_path)
    _one_error_line(result, "was trained with seed=0, not 5")
    result = moex_here(["train", "task=lissajous2", *TINY, "train.gating.steps=5",
                        f"hydra.run.dir={trained}"], cwd=tmp_path)  # the differing key named
    _one_error_line(result, "was trained with train.gating.steps=4, not 5")


def test_report_names_a_damaged_file(trained, tmp_path, moex_here):
    sweep = tmp_path / "sweep"
    for job, damage in enumerate([("metrics.csv", b"\x00\x01garbage,\n\x02"),
                                  ("status.json", b"{not json"),
                                  (".hydra/config.yaml", b"task: [unclosed")]):
        job_dir = sweep / str(job)
        for path, data in _files(trained).items():
            target = job_dir / path.relative_to(trained)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        (job_dir / damage[0]).write_bytes(damage[1])
        result = moex_here(["report", str(sweep)], cwd=tmp_path)
        _one_error_line(result, f"{job_dir / damage[0]}", "fix or remove it")
        (job_dir / damage[0]).write_bytes((trained / damage[0]).read_bytes())


@pytest.mark.parametrize("override, fragment", [
    ("hydra.job.chdir=maybe", "hydra.job.chdir"),
    ("hydra.nope=1", "hydra.nope"),
    ("plot.run=5", "plot.run=5 is outside [-1, 0] (num_runs=1)"),
    ("task.length=1000000000", "GiB of memory"),
    ("num_runs=100000", "GiB of memory"),
])
def test_more_bad_input_before_any_work(override, fragment, tmp_path, moex_here):
    start = time.perf_counter()
    result = moex_here(["train", override, "num_runs=1", f"hydra.run.dir={tmp_path}/run"]
                   if override != "num_runs=100000" else
                   ["train", override, f"hydra.run.dir={tmp_path}/run"], cwd=tmp_path)
    _one_error_line(result, fragment)
    assert time.perf_counter() - start < 60  # refused up front, not after minutes
    assert list(tmp_path.iterdir()) == []


def test_folders_that_are_files_or_too_big_a_generation(trained, tmp_path, moex_here):
    # a folder that cannot be created (read-only file systems answer alike; root may write
    # anywhere else, so /proc stands in for them)
    result = moex_here(["train", "task=lissajous2", "hydra.run.dir=/proc/moex-test/run"],
                   cwd=tmp_path)
    _one_error_line(result, "hydra.run.dir=/proc/moex-test/run cannot be written")
    (tmp_path / "file").write_text("x")
    result = moex_here(["train", "task=lissajous2", f"hydra.run.dir={tmp_path}/file"], cwd=tmp_path)
    _one_error_line(result, f"hydra.run.dir={tmp_path}/file is a file, not a folder")
    result = moex_here(["evaluate", f"run_dir={trained}", f"out_dir={tmp_path}/file"], cwd=tmp_path)
    _one_error_line(result, f"out_dir={tmp_path}/file is a file, not a folder")
    result = moex_here(["generate", f"run_dir={trained}", "steps=10000000000"], cwd=tmp_path)
    _one_error_line(result, "generating 2 runs x 4 samples x 10000000000 steps", "GiB")
    assert not (trained / "generate").exists()


def test_a_second_process_on_the_same_folder_is_refused(tmp_path):
    run_dir = tmp_path / "run"
    slow = [*TINY, "train.experts.steps=200000", "eval.enabled=false"]
    first = subprocess.Popen(MOEX + ["train", "task=lissajous2", *slow,
                                     f"hydra.run.dir={run_dir}"], cwd=tmp_path,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 120
        # Hydra writes config.yaml, hydra.yaml, then overrides.yaml: the last one there means
        # config.yaml is whole (waiting for config.yaml alone once read it half-written)
        while not (run_dir / ".hydra" / "overrides.yaml").exists() and time.time() < deadline:
            time.sleep(0.2)
        config = (run_dir / ".hydra" / "config.yaml").read_text()
        assert config
        result = _moex(["train", "task=lissajous2", *slow, f"hydra.run.dir={run_dir}"],
                       cwd=tmp_path)
        _one_error_line(result, "is being written by another moex process",
                        f"pid {first.pid}")
        assert (run_dir / ".hydra" / "config.yaml").read_text() == config
    finally:
        first.send_signal(signal.SIGINT)
        first.wait(timeout=120)
    assert first.returncode == 130


def test_sigint_during_evaluation_stops_within_seconds_and_writes_nothing(trained, tmp_path):
    out_dir = tmp_path / "ev"
    process = subprocess.Popen(MOEX + ["evaluate", f"run_dir={trained}", f"out_dir={out_dir}",
                                       "eval.num_samples=20", "eval.lyapunov_steps=10000000"],
                               cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    deadline = time.time() + 120
    while time.time() < deadline and not (out_dir / "evaluate.log").exists():
        time.sleep(0.2)
    time.sleep(8)  # inside the closed loop, which needs about a minute
    process.send_signal(signal.SIGINT)
    start = time.perf_counter()
    _, stderr = process.communicate(timeout=60)
    assert time.perf_counter() - start < 10
    assert process.returncode == 130, stderr
    assert "interrupted" in stderr and "Traceback" not in stderr
    assert not (out_dir / "metrics.csv").exists() and not (out_dir / "samples.npz").exists()


def test_eval_paper_re_evaluates_a_quick_run_at_the_papers_sizes(trained):
    assert load_run(EvaluateConfig(run_dir=str(trained))).cfg.eval.num_samples == 2
    paper = load_run(EvaluateConfig(run_dir=str(trained), paper_sizes=True)).cfg.eval
    assert (paper.num_samples, paper.lyapunov_steps, paper.transient) == (50, 100000, 1000)
    tool = EvaluateConfig(run_dir=str(trained), paper_sizes=True)
    tool.eval.num_samples = 7  # an explicit key wins over eval=paper
    assert load_run(tool).cfg.eval.num_samples == 7


def test_eval_paper_on_the_command_line_sets_the_papers_sizes(trained):
    from moex.cli import validate
    tool, _ = validate("evaluate", [f"run_dir={trained}", "eval=paper"])
    assert tool.paper_sizes
    tool, _ = validate("evaluate", [f"run_dir={trained}", "eval=quick"])
    assert not tool.paper_sizes and tool.eval.num_samples == 4


def test_sigint_during_trains_evaluation_keeps_the_trained_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    args = ["train", "task=lissajous2", *TINY, f"hydra.run.dir={run_dir}"]
    process = subprocess.Popen(MOEX + args + ["eval.num_samples=20",
                                              "eval.lyapunov_steps=10000000"],
                               cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    deadline = time.time() + 300
    log = run_dir / "train.log"
    while time.time() < deadline and not (log.exists()
                                          and "gating: step 4/4 (final)" in log.read_text()):
        time.sleep(0.2)
    time.sleep(5)  # inside the evaluation's closed loop
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    assert checkpoint.load(run_dir).phase == "done" and not (run_dir / "metrics.csv").exists()
    assert '"interrupted"' in (run_dir / "status.json").read_text()
    result = _moex(args, cwd=tmp_path)  # the same training, evaluated this time
    assert result.returncode == 0, result.stderr
    assert (run_dir / "metrics.csv").exists()


@pytest.mark.parametrize("knob", ["MOEX_GPU_TRIALS=0", "MOEX_GPU_WARPS=four"])
def test_a_bad_gpu_knob_is_refused_in_one_line_and_writes_nothing(tmp_path, knob):
    name, value = knob.split("=")
    env = {**os.environ, name: value, "TRITON_INTERPRET": "1"}
    result = subprocess.run(MOEX + ["train", "backend=gpu", f"hydra.run.dir={tmp_path / 'run'}"],
                            cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    _one_error_line(result, f"{knob} must be a whole number >= 1")
    assert not (tmp_path / "run").exists()


def test_a_bad_cpu_size_choice_is_refused_in_one_line_and_writes_nothing(tmp_path):
    env = {**os.environ, "MOEX_CPU_SIZES": "fixed"}
    result = subprocess.run(MOEX + ["train", f"hydra.run.dir={tmp_path / 'run'}"],
                            cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    _one_error_line(result, "MOEX_CPU_SIZES=fixed; choose compiled or runtime")
    assert not (tmp_path / "run").exists()


def test_sigint_during_a_packed_sweep_exits_130_and_every_job_says_interrupted(tmp_path):
    """Ctrl-C while a packed batch trains: exit 130 without a traceback, every job's
    status.json says interrupted, and the message names the -m command's sweep folder."""
    sweep = tmp_path / "sweep"
    args = ["train", "-m", "task=lissajous2", *TINY, "task.switch_prob=0.5,0.25",
            "hydra/launcher=packed", f"hydra.sweep.dir={sweep}"]
    process = subprocess.Popen(MOEX + args + ["train.experts.steps=2000000"], cwd=tmp_path,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
    seen = []
    for line in process.stdout:  # the batch is announced: its training starts
        seen.append(line)
        if "packed: 2 jobs" in line:
            break
    time.sleep(5)  # inside phase 1 (the data and a cached kernel take about a second)
    process.send_signal(signal.SIGINT)
    output = "".join(seen) + process.communicate(timeout=120)[0]
    assert process.returncode == 130, output
    assert "Traceback" not in output and "AttributeError" not in output
    assert f"re-run the same -m command with hydra.sweep.dir={sweep}" in output
    for job in ("0", "1"):
        assert json.loads((sweep / job / "status.json").read_text())["status"] == "interrupted"
