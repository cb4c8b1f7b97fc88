"""The GPU session script runs end to end on the CPU (`--smoke`: Triton's interpreter, toy sizes),
so that it never reaches a GPU untried: every section ends with exit 0 and writes its numbers."""

import csv
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from moex.kernels.cpu.simd import width

ROOT = Path(__file__).resolve().parent.parent


def test_gpu_session_script_smoke_runs_every_section(tmp_path):
    env = {**os.environ, "PYTHON": sys.executable, "TRITON_INTERPRET": "1"}
    done = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu_session.sh"), "--smoke",
                           str(tmp_path)], capture_output=True, text=True, timeout=900, env=env,
                          cwd=tmp_path)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    with open(tmp_path / "sections.csv") as f:
        sections = list(csv.DictReader(f))
    assert [s["section"] for s in sections] == ["0", "1", "2", "3", "4", "5"]
    assert all(s["exit_code"] == "0" and float(s["seconds"]) > 0 for s in sections)
    log = (tmp_path / "gpu_session.md").read_text()
    # a marginal time (long run minus short run) of the smoke's toy sizes can come out below 0
    # on a busy machine (the cpu baseline's 0.3 ms per epoch): a number all the same
    number = r"-?\d+\.\d+"
    assert re.search(r"backend gpu: cpu, Capabilities\(.*interpreted=True", log)
    assert re.search(r"\d+ passed", log)  # section 1 ran its test
    for phase in ("phase 1, fixed rate", "phase 1, adaptive rate", "phase 2, adaptive rate"):
        # float64 and float32 on gpu, the cpu baseline, the sweep's one setting and its one
        # number of adaptive-rate candidates per call
        assert len(re.findall(rf"\| {phase} \| 2 \| \w+ \| \d \| 15 \| {number} \| {number} \|",
                              log)) == 5, phase
    noisy = r"\| phase 2, adaptive rate, input noise 0.001 \| 2 \| gpu \| 1 \| 15 \| "
    assert len(re.findall(rf"{noisy}{number} \| {number} \|", log)) == 1  # on the device
    assert "adaptive-rate candidates per call 2:" in log
    assert len(re.findall(rf"\| 2 x 2 \| cpu \| \w+ \| \d \| {number} \| \d+ \|", log)) == 2
    assert "registers" in log and "(the paper's criterion) in" in log
    metrics = (tmp_path / "table2_metrics.csv").read_text().splitlines()
    assert metrics[0].startswith("run,") and len(metrics) == 3  # header + 2 networks
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "gpu_session.md", "sections.csv", "table2_jobs.csv", "table2_metrics.csv"]


def test_the_device_session_calls_fit_a_visit_and_leave_out_the_cpu_only_tests():
    """On a GPU the default call (sections 0, 2, 4, 5) and the second (--only 1,3) each stay
    within 8 minutes by their sections' limits (a device command may run 10); section 1's
    selection runs neither the interpreter smoke above (minutes, and meant for the CPU) nor the
    AOT compiles (tests/test_gpu_aot.py)."""
    script = (ROOT / "benchmarks" / "gpu_session.sh").read_text()
    limits = {int(n): int(s) for n, s in re.findall(r'section (\d) "[^"]*" \\?\s*\$\(lim (\d+)\)',
                                                    script)}
    assert sorted(limits) == [0, 1, 2, 3, 4, 5]
    assert 'echo 0,2,4,5' in script
    assert sum(limits[n] for n in (0, 2, 4, 5)) <= 480 and limits[1] + limits[3] <= 480
    selection = re.search(r'tests=\(-m "gpu or not slow" -k "([^"]+)"\)', script).group(1)
    listed = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p",
                             "no:cacheprovider", "-o", "addopts=", "-m", "gpu or not slow", "-k",
                             selection, str(ROOT / "tests")], capture_output=True, text=True,
                            timeout=300, cwd=ROOT)
    ids = [line for line in listed.stdout.splitlines() if "::" in line]
    assert len(ids) > 30 and "tests/test_kernels.py::test_cuda_backends_match_cpu[gpu]" in ids
    assert not [i for i in ids if "smoke" in i or "test_gpu_aot" in i or "device_session" in i]


def test_the_comparison_with_the_c_tools_refuses_a_folder_that_is_no_checkout(tmp_path):
    """benchmarks/bench_vs_mregn.py builds the authors' tools from a checkout the user names
    (never committed here, so CI has none): a wrong folder ends with the build script's one-line
    reason and exit 2, before anything is timed."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    done = subprocess.run([sys.executable, str(root / "benchmarks" / "bench_vs_mregn.py"),
                           str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    assert "is not an mregn checkout" in done.stderr


def test_the_phase1_breakdown_times_every_stage(tmp_path):
    """benchmarks/bench_phase1_parts.py: a row per stage of phase 1 (and with --phase 2 of phase
    2), each a finite time."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    done = subprocess.run([sys.executable, str(root / "benchmarks" / "bench_phase1_parts.py"),
                           "--runs", "1", "--repeats", "1", "--steps", "2"], capture_output=True,
                          text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for stage in ("forward", "mixture", "backward", "sums per run", "whole value_and_grad",
                  "training loop"):
        assert re.search(rf"\| 1 \| {stage}[^|]* \| -?\d+\.\d+ \|", done.stdout), stage
    done = subprocess.run([sys.executable, str(root / "benchmarks" / "bench_phase1_parts.py"),
                           "--phase", "2", "--runs", "1", "--repeats", "1"], capture_output=True,
                          text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for stage in ("forward", "softmax objective", "backward", "sums per run",
                  "whole value_and_grad"):  # phase 2's stages, each a positive time
        assert re.search(rf"\| 1 \| {stage}[^|]* \| \d+\.\d+ \|", done.stdout), stage



def test_the_stage_benchmark_times_each_stage_on_each_thread_count(tmp_path):
    """benchmarks/bench_stages.py: per phase a row per stage the step calls (the shared main call
    among them), the rest, the step and the speed-up the code allows, one column per thread
    count."""
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_stages.py"), "--runs",
                           "2", "--threads", "1", "--steps", "2", "--base", "1", "--series", "2",
                           "--length", "60"], capture_output=True, text=True, timeout=600,
                          cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    number = r"-?\d+\.\d+"
    for phase, kernel in (("phase 1, fixed rate", "_expert_items"),
                          ("phase 1, adaptive rate", "_expert_items"),
                          ("phase 2, adaptive rate", "gating_items")):
        part = done.stdout.split(f"## {phase}")[1].split("## ")[0]
        assert re.search(rf"\| shared by the threads: {kernel} \| {number} \({number}\) \|",
                         part), phase
        assert re.search(rf"\| \*\*a step\*\* \| \*\*{number}\*\* \|", part), phase
        assert "the rest (the training loop's Python)" in part
        # Amdahl's bound for the thread count the stages were timed on is that step itself
        assert re.search(r"\| speed-up at best \(the threads' calls of 1 thread\(s\) divided, the "
                         r"rest as it is\) \| 1\.00x \|", part), phase


def test_the_host_share_benchmark_prints_a_share_per_phase(tmp_path):
    """benchmarks/bench_host.py: per phase an epoch time, the host's part of it and the share."""
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_host.py"), "--runs",
                           "1", "--steps", "2", "--base", "1", "--repeats", "1"],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    number = r"-?\d+\.\d+"
    for phase in ("phase 1, fixed rate", "phase 1, adaptive rate", "phase 2, adaptive rate"):
        assert re.search(rf"\| {phase} \| 1 \| {number} \| {number} \| {number} % \|",
                         done.stdout), phase


def test_the_adaptive_rate_benchmark_prints_its_rows(tmp_path):
    """benchmarks/bench_adaptive.py: phase 1 at a fixed rate, then both adaptive phases with the
    trial's pass (forward and objective) reused and run again, each a time and a ratio."""
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_adaptive.py"),
                           "--runs", "1", "--rounds", "1", "--steps", "2", "--base", "1"],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    number = r"-?\d+\.\d+"
    assert re.search(rf"\| 1 \| phase 1, fixed rate \| {number} \|", done.stdout)
    for phase in ("phase 1", "phase 2"):
        assert re.search(rf"\| 1 \| {phase}, adaptive rate \| {number} \| {number} \| {number} "
                         rf"\({number}-{number}\) \|", done.stdout), phase


def test_the_epoch_benchmark_pairs_two_precisions_round_by_round(tmp_path):
    """benchmarks/bench_epochs.py with two --dtype: a row per phase with both precisions' times
    and their ratio as a median (min-max) of the rounds."""
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_epochs.py"),
                           "--runs", "1", "--threads", "1", "--dtype", "float64", "float32",
                           "--series", "2", "--length", "30", "--steps", "2", "--base", "1",
                           "--repeats", "2"], capture_output=True, text=True, timeout=600,
                          cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    number = r"-?\d+\.\d+"
    assert "| float64 / float32 |" in done.stdout
    for phase in ("phase 1, fixed rate", "phase 1, adaptive rate", "phase 2, adaptive rate"):
        assert re.search(rf"\| lissajous2 \| {phase} \| 1 \| 1 \| 15 \| {number} \| {number} \| "
                         rf"{number} \({number}-{number}\) \|", done.stdout), phase


def test_the_epoch_benchmark_pairs_two_thread_counts_round_by_round(tmp_path):
    """With --paired and --threads 1 2: a row per phase with the wall time on each, the speed-up
    (median (min-max) of the rounds, and the best rounds' ratio), the CPU time ratio, and the
    control of two trainings of half the runs at once (their speed-up, and the threads' over
    theirs); --paired with one thread count, with a first count other than 1, or with fewer runs
    than threads is refused in one line, exit 2."""
    script = [sys.executable, str(ROOT / "benchmarks" / "bench_epochs.py"), "--series", "2",
              "--length", "30", "--steps", "2", "--base", "1", "--repeats", "2", "--paired"]
    done = subprocess.run(script + ["--runs", "2", "--threads", "1", "2"], capture_output=True,
                          text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    number = r"-?\d+\.\d+"
    assert ("| speed-up | best round over best round | CPU time, 2 / 1 | 2 trainings at once: "
            "speed-up | 2 threads over them |") in done.stdout
    spread, times = rf"{number} \({number}-{number}\)", rf"{number}x \({number}-{number}\)"
    for phase in ("phase 1, fixed rate", "phase 1, adaptive rate", "phase 2, adaptive rate"):
        found = re.search(rf"\| lissajous2 \| {phase} \| 2 \| 15 \| {number} \| {number} \| "
                          rf"{times} \| ({number})x \| {spread} \| {times} \| {spread} \|",
                          done.stdout)
        assert found and float(found[1]) > 0, phase
    for threads, runs, why in ((["2"], "2", "--paired takes two --threads, the first 1"),
                               (["2", "1"], "2", "--paired takes two --threads, the first 1"),
                               (["1", "2"], "1", "--paired --runs 1: at least one run per thread")):
        refused = subprocess.run(script + ["--runs", runs, "--threads", *threads],
                                 capture_output=True, text=True, timeout=60, cwd=tmp_path)
        assert refused.returncode == 2 and why in refused.stderr, threads
        assert "Traceback" not in refused.stderr


def test_the_gpu_profile_names_where_each_phase_spends_its_epoch():
    """benchmarks/gpu_profile.py on the CPU (its CI path): a line per phase with the epoch's wall
    time and the host's operators, and a table of them; the same for the closed loop's chunks."""
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "gpu_profile.py"),
                           "--device", "cpu", "--backend", "cpu", "--runs", "1", "--epochs", "2",
                           "--samples", "2", "--chunks", "1", "--top", "3"],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    for phase in ("phase 1, fixed rate", "phase 1, adaptive rate", "phase 2, adaptive rate"):
        assert re.search(rf"{phase}, 1 networks: \d+\.\d+ ms wall per epoch", done.stdout), phase
    assert done.stdout.count("| on the host (self CPU time) | ms per epoch |") == 3
    assert re.search(r"closed loop, one tangent, 1 networks: \d+\.\d+ ms wall per chunk of 500 "
                     r"steps", done.stdout)
    assert "| on the host (self CPU time) | ms per chunk of 500 steps |" in done.stdout


def test_the_sizes_benchmark_reports_time_and_memory_per_number_of_networks():
    """benchmarks/bench_sizes.py at toy sizes: a row per number of networks with two times, the
    measured peak and moex's estimate (a time can come out below 0 at 2 steps: a number still)."""
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_sizes.py"), "--runs",
                           "1", "--steps", "2", "--length", "300", "--features", "3",
                           "--experts", "2", "--threads", "1"], capture_output=True, text=True,
                          timeout=600, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    number = r"-?\d+\.\d+"
    assert re.search(rf"\| 1 \| {number} \| {number} \| \d+\.\d\d \| \d+\.\d\d \|", done.stdout)


def test_the_peak_probe_prints_a_clock_and_a_peak():
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_peak.py"), "--steps",
                           "100000"], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    found = re.search(r"(\d+\.\d+) Gflop/s -> clock (\d+\.\d+) GHz .* = (\d+\.\d+) Gflop/s",
                      done.stdout)
    rate, clock, peak = map(float, found.groups())
    assert rate == pytest.approx(4 * clock, rel=0.01)  # 2 pipes x 2 flops per cycle
    assert peak == pytest.approx(16 * clock, rel=0.01)
    for dtype in ("float64", "float32"):  # the kernels' blocks: a vector FMA is 2 flops a lane
        found = re.search(rf"vector FMA chains, {dtype} \((\d+) lanes\): (\d+\.\d) Gflop/s "
                          r"per core \((\d+\.\d+) G vector FMAs", done.stdout)
        lanes, rate, fmas = int(found[1]), float(found[2]), float(found[3])
        assert lanes == width(np.dtype(dtype)) and rate > 0
        # (the two figures are printed to 0.1 and 0.01)
        assert rate == pytest.approx(2 * lanes * fmas, rel=0.02, abs=0.01 * lanes + 0.05)
    # two threads at once: between time-sliced on one core (1x, less the switching) and two cores
    ceiling = float(re.search(r"two threads' vector FMA rate over one thread's: (\d+\.\d+)x",
                              done.stdout)[1])
    assert 0.5 < ceiling < 2.2


def test_the_forward_variants_agree_in_the_interpreter():
    """benchmarks/gpu_forward_variants.py without a GPU: the forward kernel by columns and its
    earlier design by rows give the same outputs (to rounding), and a rerun the same bits."""
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "gpu_forward_variants.py")],
                          capture_output=True, text=True, timeout=300,
                          env={**os.environ, "TRITON_INTERPRET": "1"})
    assert done.returncode == 0, done.stderr[-2000:]
    row = done.stdout.strip().splitlines()[-1].split("|")
    assert row[1].strip() == "4 (interpreter)"
    assert float(row[5]) < 1e-12 and float(row[6]) < 1e-12 and row[7].strip() == "yes"
