"""The README's Python API example runs as written and returns what it says."""

import re
from pathlib import Path

import numpy as np
import pandas as pd

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
