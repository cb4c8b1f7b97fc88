"""Every Triton kernel compiled for an NVIDIA H200 (sm_90a) on the CPU, at the sizes users run
(`benchmarks/gpu_aot.py`, in a process of its own: the suite may have set up Triton's
interpreter): no training kernel spills and none exceeds its budget, except the cases `KNOWN`
names, which a redesign must clear (the test then fails until they leave `KNOWN`: the list is
exact both ways). The evaluation's kernels (closed loop, symbol reader) are compiled at Table 2's
sizes only (each of their compiles takes 5-20 s here)."""

import csv
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("triton")
pytestmark = pytest.mark.aot  # not in the default run: .ci/run runs `pytest -m aot` after it
ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "benchmarks" / "gpu_aot.py"
_spec = importlib.util.spec_from_file_location("gpu_aot", SCRIPT)  # its sizes and kernel names
aot = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(aot)
# (size, kernel, what is over): over budget today. None since the forward and backward kernels
# form their products with the weights by columns (the float32 phase-1 backward spilled 8 B)
KNOWN: set[tuple[str, str, str]] = set()


@pytest.mark.parametrize("size", list(aot.SIZES))
def test_every_kernel_compiles_for_an_h200_within_its_budget(size, tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    table = tmp_path / "aot.csv"
    done = subprocess.run([sys.executable, str(SCRIPT), "--sizes",
                           size, "--csv", str(table), *([] if size == "table2" else
                                                        ["--training"])],
                          capture_output=True, text=True, env=env, timeout=600)
    with open(table) as f:
        rows = list(csv.DictReader(f))
    kernels = {row["kernel"] for row in rows}
    # every training kernel (a symbolic task has no phase 1), the evaluation's at Table 2
    phase1 = set() if size.startswith("table1") else {"mixture_objective"}
    assert kernels >= set(aot.TRAINING) - {"mixture_objective"} | phase1
    assert size != "table2" or {"closed_loop_kernel", "nearest_kernel"} <= kernels
    # the closed loop: one compile per configuration (potentials kept; tangent counted or not in
    # the transient), not per chunk length (the trained states' 999 steps are 500 + 499)
    assert size != "table2" or sum(row["kernel"] == "closed_loop_kernel" for row in rows) == 3
    assert all(int(row["registers"]) > 0 and int(row["instructions"]) > 0 for row in rows)
    over = {(size, row["kernel"], problem) for row in rows if row["over budget"] != "-"
            for problem in row["over budget"].split("; ")}
    assert over == {k for k in KNOWN if k[0] == size}
    assert done.returncode == (1 if over else 0), done.stderr[-2000:]
