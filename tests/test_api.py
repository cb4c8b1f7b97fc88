"""The README's Python API example runs as written and returns what it says."""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

import moex

README = Path(__file__).resolve().parent.parent / "README.md"


def _readme_python_example() -> str:
    text = README.read_text()
    section = text.split("## Python API", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_readme_api_example_runs_and_returns_named_results(capsys):
    namespace: dict = {}
    exec(compile(_readme_python_example(), "README.md", "exec"), namespace)
    metrics, samples, series = namespace["metrics"], namespace["samples"], namespace["series"]
    assert isinstance(metrics, pd.DataFrame) and len(metrics) == 2
    assert {"E", "E_g", "E_closed", "max_lyapunov", "switch_prob"} <= set(metrics)
    assert np.isfinite(metrics[["E", "E_g", "max_lyapunov"]].to_numpy()).all()
    assert metrics["E"].max() < 0.01  # the experts fit the two circles
    assert samples["outputs"].shape == (2, 1, 500, series.shape[-1])
    assert samples["gates"].shape[:3] == (2, 1, 500)
    np.testing.assert_allclose(samples["gates"].sum(-1), 1.0, atol=1e-9)
    assert "max_lyapunov" in capsys.readouterr().out


def test_fitted_save_gives_a_folder_the_cli_evaluates_and_load_reads_back(tmp_path):
    """`Fitted.save` writes a run folder: `moex.load` returns the same parameters and history,
    `moex evaluate run_dir=...` evaluates it, and saving over it is refused."""
    t = np.linspace(0, 8 * np.pi, 200)
    series = 0.6 * np.stack([np.sin(t), np.cos(t)], -1)
    fitted = moex.fit(series, expert_steps=20, gating_steps=10, num_runs=2)
    folder = fitted.save(tmp_path / "run")
    loaded = moex.load(folder)
    for part in ("experts", "gating"):
        for name, value in getattr(fitted, part).items():
            assert torch.equal(getattr(loaded, part)[name], value), (part, name)
    assert torch.equal(loaded.beta, fitted.beta)
    pd.testing.assert_frame_equal(loaded.history, fitted.history, check_dtype=False)
    np.testing.assert_array_equal(loaded.dataset.series, fitted.dataset.series)
    pd.testing.assert_frame_equal(loaded.evaluate(quick=True), fitted.evaluate(quick=True))
    with pytest.raises(moex.ConfigError, match="already holds a run"):
        fitted.save(folder)
    # what trained it travels with it: versions, machine, backend, each phase's time
    assert fitted.provenance["verb"] == "fit" and fitted.provenance["backend"] == "cpu"
    assert {"phase 1", "phase 2"} <= set(fitted.provenance["seconds"])
    assert loaded.provenance == fitted.provenance  # written by save, read by load
    shown = repr(fitted)  # one line, not the tensors
    assert "\n" not in shown and len(shown) < 300 and "2 runs of task csv" in shown
    done = subprocess.run([sys.executable, "-c", "from moex.cli import main; main()", "evaluate",
                           f"run_dir={folder}", "eval=quick", f"out_dir={tmp_path / 'eval'}"],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert len(pd.read_csv(tmp_path / "eval" / "metrics.csv")) == 2


def test_load_reads_a_cli_run(tmp_path):
    """A run folder of `moex train` loads into the `Fitted` that `fit` returns."""
    run = tmp_path / "run"
    done = subprocess.run([sys.executable, "-c", "from moex.cli import main; main()", "train",
                           "task=lissajous2", "task.num_series=2", "task.length=60",
                           "train.experts.steps=10", "train.gating.steps=5", "num_runs=2",
                           "eval.enabled=false", f"hydra.run.dir={run}"],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    fitted = moex.load(run)
    assert fitted.config.num_runs == 2 and fitted.config.task.name == "lissajous2"
    assert fitted.experts["w_rec"].shape[0] == 2 and fitted.beta.shape[:2] == (2, 2)
    assert set(fitted.history["phase"]) == {"experts", "gating"}
    assert fitted.generate(steps=30)["outputs"].shape == (2, 1, 30, 2)
