import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from moex.tasks.scaling import noise_floor

MOEX = [sys.executable, "-c", "from moex.launch import main; main()"]  # the `moex` command
TINY = ["task.num_series=2", "task.length=40", "task.num_test_series=1",
        "model.experts.context_size=4", "model.gating.context_size=5",
        "train.experts.steps=6", "train.gating.steps=4", "train.experts.log_every=2",
        "train.gating.log_every=2", "num_runs=2", "eval.num_samples=2",
        "eval.lyapunov_steps=200", "eval.transient=20", "eval.plot_steps=100"]


def _moex(args, cwd):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(MOEX + args, cwd=cwd, capture_output=True, text=True, env=env,
                          timeout=300)


def test_train_from_another_directory_leaves_the_documented_files(tmp_path, moex_here):
    run_dir = tmp_path / "run"
    work = tmp_path / "elsewhere"
    work.mkdir()
    result = _moex(["train", "task=lissajous2", *TINY, f"hydra.run.dir={run_dir}"], cwd=work)
    assert result.returncode == 0, result.stderr
    for name in ("checkpoint.pt", "history.csv", "train.log", ".hydra/config.yaml",
                 "metrics.csv", "samples.npz", "figures/learning_curves.png",
                 "figures/trajectory.png", "figures/gates.png", "figures/residence_times.png",
                 "figures/runs.png", "figures/phase_portrait.png", "report.md"):
        assert (run_dir / name).is_file(), name
    page = (run_dir / "report.md").read_text()  # the run's page: metrics and every figure
    assert "| run | E | E^g |" in page and "![learning curves](figures/learning_curves.png)" in page
    assert all(f"(figures/{p.name})" in page for p in (run_dir / "figures").iterdir())
    assert list(work.iterdir()) == []  # nothing written to the working directory
    progress = [line for line in (run_dir / "train.log").read_text().splitlines()
                if "experts: step" in line]
    # steps 2-5 with rate and time left (the first step, which compiles, is not timed); the
    # last line is the trained parameters' value, the one history.csv ends with
    assert len(progress) == 5 and all(re.search(r"[\d.]+ steps/s, \d+:\d\d:\d\d left", line)
                                       for line in progress[:4]), progress
    assert "experts: step 6/6 (final), E mean" in progress[4]
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert checkpoint["gating"]["w_out"].shape == (2, 2, 5)
    history = pd.read_csv(run_dir / "history.csv")
    assert {"run", "phase", "step", "E", "E_g", "log_likelihood", "lr_scale"} <= set(history)
    assert set(history["phase"]) == {"experts", "gating"}
    assert set(history["run"]) == {0, 1}
    # a row every log_every steps and one for the trained parameters: no extra row at step 5
    assert sorted(set(history.loc[history["phase"] == "experts", "step"])) == [0, 2, 4, 6]
    metrics = pd.read_csv(run_dir / "metrics.csv")
    assert metrics["run"].tolist() == [0, 1]
    for column in ("E", "E_g", "E_closed", "block_kl_train", "block_kl_test", "max_lyapunov",
                   "switch_prob"):
        assert metrics[column].notna().all(), column
    for column in ("num_samples", "lyapunov_steps", "block_length", "censored_stays"):
        assert metrics[column].dtype == "int64", column  # counts are written as integers
    from moex.metrics.table import is_known

    assert [c for c in metrics if not is_known(c)] == []  # every metric is in the one table
    # the chaos label with its error in the table, the log and the page (never "± nan")
    assert set(metrics["chaos"]) <= {"chaotic", "undetermined", "not chaotic"}
    log = (run_dir / "train.log").read_text()
    assert "(the paper's criterion) in" in log and "± nan" not in log
    # the evaluation says what it does before it starts (no silent pause after training)
    assert log.index("evaluating 2 runs:") < log.index("of 2 runs:")
    assert all(f"({label})" in page for label in metrics["chaos"])
    # 200 steps hold at most 8 laps, too few to test periods up to 100: no sample is judged
    assert (metrics["periodicity_samples"] == 0).all()
    assert metrics["nonperiodic_fraction"].isna().all()

    # the final E and E^g of the history are the ones the metric table measures
    last = history.sort_values(["step", "run"]).groupby(["phase", "run"]).tail(1)
    last = last.sort_values("run")
    np.testing.assert_allclose(last.loc[last["phase"] == "gating", "E_g"], metrics["E_g"],
                               rtol=1e-9)
    np.testing.assert_allclose(last.loc[last["phase"] == "experts", "E"], metrics["E"],
                               rtol=1e-9)
    trained = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}

    # evaluate again with other settings, then generate noisy samples, from the checkpoint: each
    # into a folder of its own, the run's own files untouched
    result = _moex(["evaluate", f"run_dir={run_dir}", "eval.num_samples=3",
                    "eval.lyapunov_steps=100", "eval.noise_var=0.001"], cwd=work)
    assert result.returncode == 0, result.stderr
    (evaluated,) = (run_dir / "evaluate").iterdir()
    again = pd.read_csv(evaluated / "metrics.csv")
    assert (again["num_samples"] == 3).all() and (again["noise_var"] == 0.001).all()
    assert {"samples.npz", "eval_config.yaml", "evaluate.log", "figures"} <= {
        p.name for p in evaluated.iterdir()}
    result = _moex(["generate", f"run_dir={run_dir}", "steps=50", "num_samples=2",
                    "noise_var=0.001", f"out_dir={tmp_path}/generated"], cwd=work)
    assert result.returncode == 0, result.stderr
    samples = np.load(tmp_path / "generated" / "samples.npz")
    assert samples["outputs"].shape == (2, 2, 50, 2) and samples["gates"].shape == (2, 2, 50, 2)
    assert samples["symbols"].shape == (2, 2, 50)
    # from the trained state of series 1, without noise every sample is the same
    result = _moex(["generate", f"run_dir={run_dir}", "steps=30", "num_samples=2",
                    "from_series=1", f"out_dir={tmp_path}/from1"], cwd=work)
    assert result.returncode == 0, result.stderr
    outputs = np.load(tmp_path / "from1" / "samples.npz")["outputs"]
    assert np.array_equal(outputs[:, 0], outputs[:, 1])
    result = moex_here(["generate", f"run_dir={run_dir}", "from_series=5"], cwd=work)
    assert result.returncode == 2 and "from_series=5 is outside [-1, 1]" in result.stderr
    result = moex_here(["generate", f"run_dir={run_dir}", f"out_dir={run_dir}"], cwd=work)
    assert result.returncode == 2 and "is the run folder itself" in result.stderr
    assert {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()
            and "evaluate" not in p.parts} == trained
    assert list(work.iterdir()) == []


def test_a_failed_evaluation_leaves_nothing_behind(tmp_path, moex_here):
    run_dir = tmp_path / "run"
    result = _moex(["train", "task=lissajous2", *TINY, "eval.enabled=false",
                    f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    del checkpoint["gating"]["w_rec"]  # a broken network
    torch.save(checkpoint, run_dir / "checkpoint.pt")
    before = sorted(p.name for p in run_dir.iterdir())
    for verb in ("evaluate", "generate"):
        result = moex_here([verb, f"run_dir={run_dir}"], cwd=tmp_path)
        assert result.returncode == 2, result.stderr
        assert result.stderr.strip() == (f"moex: error: {run_dir}/checkpoint.pt: its gating "
                                         f"network lacks w_rec; it is not a usable moex "
                                         f"checkpoint (train again into another folder, or "
                                         f"restore the file)")
        assert sorted(p.name for p in run_dir.iterdir()) == before


def test_resume_true_continues_the_latest_run_of_the_task(tmp_path, moex_here):
    args = ["train", "task=lissajous2", *TINY, "eval.enabled=false"]
    assert _moex(args, cwd=tmp_path).returncode == 0
    (run_dir,) = (tmp_path / "outputs" / "lissajous2").iterdir()
    before = (run_dir / "checkpoint.pt").stat().st_mtime_ns
    result = _moex(args + ["resume=true"], cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert str(run_dir) in result.stdout
    assert list((tmp_path / "outputs" / "lissajous2").iterdir()) == [run_dir]
    assert (run_dir / "checkpoint.pt").stat().st_mtime_ns == before  # finished: not redone
    result = moex_here(["train", "task=reber", "resume=true"], cwd=tmp_path)
    assert result.returncode == 2 and "outputs/reber/ holds no run" in result.stderr


def test_reber_trains_the_gating_network_only(tmp_path):
    run_dir = tmp_path / "run"
    result = _moex(["train", "task=reber", "task.length=30", "task.num_series=2",
                    "train.gating.steps=3", "model.gating.context_size=4", "eval.num_samples=2",
                    "eval.lyapunov_steps=50", "eval.transient=5", "train.experts.steps=200",
                    f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "train.experts.steps=200 ignored: task reber has no signal for experts" in \
        result.stdout + result.stderr
    history = pd.read_csv(run_dir / "history.csv")
    assert set(history["phase"]) == {"gating"}
    page = (run_dir / "report.md").read_text()  # the page says what was trained
    assert "3 gating-phase steps (no experts: phase 1 does not run)" in page
    assert "200 + 3" not in page
    metrics = pd.read_csv(run_dir / "metrics.csv")
    assert metrics["block_length"].tolist() == [3] and metrics["block_kl_test"].notna().all()
    assert not {"E", "E_closed"} & set(metrics)  # no experts, no signal: left out, not NaN
    assert not (run_dir / "figures" / "residence_times.png").exists()


@pytest.mark.parametrize("override, message", [
    ("task=nope", "task=nope is unknown; choose one of"),
    ("noise_var=0.001", "unknown key noise_var; did you mean eval.noise_var?"),
    ("model.nope=1", "unknown key model.nope; allowed keys: model.num_experts"),
    ("model.gating.contxt_size=3", "allowed keys: model.gating.context_size, "),
    ("task.length=[1,2", "task.length: cannot parse the override"),
    ("model.num_experts=0", "model.num_experts=0 must be >= 1"),
    ("model.experts.epsilon=1.5", "model.experts.epsilon=1.5 is outside (0.0, 1.0]"),
    ("model.gating.epsilon=0", "model.gating.epsilon=0.0 is outside (0.0, 1.0]"),
    ("model.delay=0", "model.delay=0 must be >= 1"),
    ("model.sigma_min=0", "model.sigma_min=0.0 must be positive"),
    ("task.switch_prob=1.2", "task.switch_prob=1.2 is outside [0.0, 1.0]"),
    ("task.switch_prob=0.5,1.2", "task.switch_prob=1.2 is outside [0.0, 1.0]"),
    ("model.gating.context_size=-3", "model.gating.context_size=-3 must be >= 1"),
    ("model.num_experts=abc", "model.num_experts"),
    ("num_runs=0", "num_runs=0 must be >= 1"),
    ("hydra/launcher=slurn", "hydra/launcher=slurn is unknown; choose one of slurm, "),
    ("plot.run=-2", "plot.run"),
    ("eval.kl_floor=0", "eval.kl_floor=0.0 must be positive"),
    ("eval.kl_form=c", "eval.kl_form='c'; choose paper or mregn"),
] + ([] if torch.cuda.is_available() else [
    ("device=cuda", "device=cuda but this machine has no CUDA device"),
]))
def test_bad_input_is_one_line_exit_2_and_writes_nothing(override, message, tmp_path, moex_here):
    multirun = ["-m"] if "," in override else []
    result = moex_here(["train", *multirun, override, f"hydra.run.dir={tmp_path}/run",
                    f"hydra.sweep.dir={tmp_path}/sweep"], cwd=tmp_path)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("moex: error: "), result.stderr
    assert message in lines[0]
    assert "Traceback" not in result.stderr + result.stdout
    assert sorted(p.name for p in Path(tmp_path).iterdir()) == []


def test_a_sweep_without_m_is_refused_not_run_on_its_first_value(tmp_path, moex_here):
    result = moex_here(["train", "num_runs=1,2", f"hydra.run.dir={tmp_path}/run"], tmp_path)
    assert result.returncode == 2 and result.stderr.strip() == (
        "moex: error: num_runs=1,2: several values are a sweep, which needs -m (moex train -m "
        "num_runs=1,2); a list is written num_runs=[a,b]")
    assert list(tmp_path.iterdir()) == []


def test_bad_transition_matrix_and_csv(tmp_path, moex_here):
    (tmp_path / "bad.csv").write_text("0.1,0.2\n0.3,nan\n" * 5)
    (tmp_path / "ragged.csv").write_text("0.1,0.2\n0.3\n" * 5)
    (tmp_path / "short.csv").write_text("0.1,0.2\n0.3,0.1\n")
    (tmp_path / "binary.csv").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "header.csv").write_text("t,x,y\n" + "0,0.1,0.2\n" * 10)
    for args, message in [
        (["task=csv", f"task.path={tmp_path}/ragged.csv"], "rows of different lengths"),
        (["task=csv", f"task.path={tmp_path}/binary.csv"], "is not a text file"),
        (["task=csv", f"task.path={tmp_path}/header.csv", "task.columns=[x,z]"],
         "task.columns: ['z'] not in"),
        (["task=csv", f"task.path={tmp_path}/short.csv"],
         "series have 2 steps, need at least 3 (model.delay + 2)"),
        (["task=csv", f"task.path={tmp_path}/short.csv", "model.delay=3"],
         "need at least 5 (model.delay + 2)"),
        (["task=markov_primitives", "task.transition=[[0.5,0.4],[0.5,0.5]]"],
         "task.transition[0] sums to 0.9, not 1"),
        (["task=csv", f"task.path={tmp_path}/bad.csv"], "has NaN or inf values (first at step 1)"),
        (["task=csv"], "task.path"),
    ]:
        result = moex_here(["train", *args, f"hydra.run.dir={tmp_path}/run"], cwd=tmp_path)
        assert result.returncode == 2 and message in result.stderr, result.stderr
        assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("verb", ["evaluate", "generate"])
def test_run_dir_without_checkpoint(verb, tmp_path, moex_here):
    result = moex_here([verb, f"run_dir={tmp_path}/none"], cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == f"moex: error: run_dir={tmp_path}/none holds no checkpoint.pt"
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "checkpoint.pt").write_bytes(b"not a checkpoint")
    result = moex_here([verb, f"run_dir={tmp_path}"], cwd=tmp_path)
    assert result.returncode == 2 and "cannot be read" in result.stderr
    assert "it is not a usable moex checkpoint" in result.stderr
    torch.save({"format_version": 99}, tmp_path / "checkpoint.pt")
    result = moex_here([verb, f"run_dir={tmp_path}"], cwd=tmp_path)
    assert result.returncode == 2
    assert "its format is 99; this moex reads formats 1 and 2" in result.stderr


def test_missing_launcher_plugin_is_named(tmp_path):
    pytest.importorskip("hydra_plugins")
    try:
        import hydra_plugins.hydra_submitit_launcher  # noqa: F401
        pytest.skip("the submitit launcher is installed here")
    except ImportError:
        pass
    result = _moex(["train", "-m", "hydra/launcher=slurm", f"hydra.sweep.dir={tmp_path}/s"],
                   cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == ("moex: error: hydra/launcher: the submitit launcher plugin "
                                     "is not installed; pip install -e '.[slurm]'")


def test_unknown_verb_and_version():
    result = _moex(["fly"], cwd=".")
    assert result.returncode == 2 and "unknown verb 'fly'" in result.stderr
    result = _moex(["--version"], cwd=".")
    assert result.returncode == 0 and result.stdout.strip() == "moex 0.1.0"


def test_csv_run_evaluates_from_another_directory(tmp_path):
    (tmp_path / "a" / "data").mkdir(parents=True)
    (tmp_path / "b").mkdir()
    rng = np.random.default_rng(0)
    for i in range(2):
        np.savetxt(tmp_path / "a" / "data" / f"s{i}.csv", rng.uniform(-0.5, 0.5, (30, 2)),
                   delimiter=",")
    run_dir = tmp_path / "run"
    args = ["task=csv", "task.path=data", "train.experts.steps=3", "train.gating.steps=2",
            "eval.num_samples=2", "eval.lyapunov_steps=20", "eval.transient=2"]
    result = _moex(["train", *args, "task.num_series=5", f"hydra.run.dir={run_dir}"],
                   cwd=tmp_path / "a")
    assert result.returncode == 0, result.stderr
    said = result.stdout + result.stderr  # the sizes read, and the size the files overrule
    assert "task csv: 2 series x 30 steps of 2 features" in said
    assert "task.num_series=5 ignored: task csv trains on every series its files hold (2)" in said
    result = _moex(["evaluate", f"run_dir={run_dir}", f"out_dir={tmp_path}/ev"],
                   cwd=tmp_path / "b")
    assert result.returncode == 0, result.stderr
    metrics = pd.read_csv(tmp_path / "ev" / "metrics.csv")
    assert metrics["E"].notna().all()
    assert "block_kl_test" not in metrics  # no held-out series: left out, not NaN


def test_csv_with_a_header_and_columns_by_name(tmp_path):
    rng = np.random.default_rng(1)
    frame = pd.DataFrame(rng.uniform(-0.5, 0.5, (40, 3)), columns=["time", "x", "y"])
    frame.to_csv(tmp_path / "mine.csv", index=False)
    run_dir = tmp_path / "run"
    result = _moex(["train", "task=csv", f"task.path={tmp_path}/mine.csv", "task.columns=[y,x]",
                    "train.experts.steps=3", "train.gating.steps=2", "eval=quick",
                    f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    saved = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    np.testing.assert_array_equal(saved["series"][0].numpy(), frame[["y", "x"]].to_numpy())
    # a csv task's σ̄ comes from the data (model.sigma_min=auto), said in the log, kept as a
    # number, and the same command continues the folder
    floor = noise_floor(frame[["y", "x"]].to_numpy()[None])
    assert saved["config"]["model"]["sigma_min"] == pytest.approx(floor)
    assert f"model.sigma_min=auto: σ̄ = {floor:.4g}" in result.stdout + result.stderr
    assert f"σ̄ = {floor:.3g}" in (run_dir / "report.md").read_text()
    again = _moex(["train", "task=csv", f"task.path={tmp_path}/mine.csv", "task.columns=[y,x]",
                   "train.experts.steps=3", "train.gating.steps=2", "eval=quick",
                   f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    assert again.returncode == 0, again.stderr


def test_a_task_of_your_own_from_a_config_dir(tmp_path):
    (tmp_path / "conf" / "task").mkdir(parents=True)
    (tmp_path / "conf" / "task" / "three.yaml").write_text("""# @package _global_
task:
  name: markov_primitives
  num_series: 2
  length: 60
  period: 20
  primitives:
    - {name: a, amplitude: [0.3, 0.3], phase: [0.0, 1.5708], offset: [-0.5, 0.0]}
    - {name: b, amplitude: [0.3, 0.3], phase: [0.0, 1.5708], offset: [0.0, 0.0]}
    - {name: c, amplitude: [0.3, 0.3], phase: [0.0, 1.5708], offset: [0.5, 0.0]}
  transition: [[0.5, 0.25, 0.25], [0.25, 0.5, 0.25], [0.25, 0.25, 0.5]]
model: {num_experts: 3}
""")
    tiny = [a for a in TINY if not a.startswith("task.")] + ["eval=quick"]
    for flags in (["--config-dir", str(tmp_path / "conf")],
                  [f"hydra.searchpath=[file://{tmp_path / 'conf'}]"]):
        run_dir = tmp_path / f"run{len(flags)}"
        result = _moex(["train", *flags, "task=three", *tiny, f"hydra.run.dir={run_dir}"],
                       cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["gating"][
            "w_out"].shape[1] == 3
    result = _moex(["train", "--config-dir", str(tmp_path / "conf"), "task=three",
                    "model.num_experts=2", f"hydra.run.dir={tmp_path}/no"], cwd=tmp_path)
    assert result.returncode == 2
    assert "model.num_experts=2 is fewer than the 3 primitives" in result.stderr
    assert not (tmp_path / "no").exists()


def test_shell_completion_installs_and_completes_the_keys_of_each_verb(tmp_path):
    """Verbs first, then the verb's groups, options and keys (one level at a time), folders
    after `report`; each Tab answered by the `moex` entry point without Hydra or PyTorch."""
    script = _moex(["-sc", "install=bash"], tmp_path)
    assert script.returncode == 0 and "complete -o nospace" in script.stdout, script.stderr
    (tmp_path / "outputs" / "run1").mkdir(parents=True)
    for line, expected, absent in (("moex ", {"train", "evaluate", "report"}, {"train."}),
                                   ("moex tr", {"train"}, {"train.", "train="}),
                                   ("moex train ", {"task=", "eval.", "seed="}, {"train"}),
                                   ("moex train task.na", {"task.name="}, set()),
                                   ("moex train task=r", {"task=reber"}, set()),
                                   ("moex evaluate eval.nois", {"eval.noise_var="}, set()),
                                   ("moex report out", {"outputs/"}, set()),
                                   ("moex report outputs/r", {"outputs/run1/"}, set())):
        env = {**os.environ, "COMP_LINE": line, "COMP_POINT": str(len(line))}
        done = subprocess.run([sys.executable, "-X", "importtime", "-c",
                               "from moex.launch import main; main()", "-sc", "query=bash"],
                              cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
        said = set(done.stdout.split())
        assert done.returncode == 0 and expected <= said and not absent & said, (line, said)
        imported = {row.split("|")[-1].strip() for row in done.stderr.splitlines()}
        assert not {"torch", "hydra", "numba", "pandas"} & imported, line
    fish = subprocess.run([sys.executable, "-c", "from moex.launch import main; main()", "-sc",
                           "query=fish"], cwd=tmp_path, capture_output=True, text=True,
                          env={**os.environ, "COMP_LINE": "moex ev"}, timeout=60)
    assert fish.stdout.split() == ["evaluate"]  # fish asks with COMP_LINE alone
    bad = _moex(["-sc"], tmp_path)
    assert bad.returncode == 2 and "install=bash" in bad.stderr and "Traceback" not in bad.stderr


def test_the_completion_keys_are_those_the_configs_give():
    """moex/completion_keys.json (what a Tab reads) is current: `python -m moex.completion`
    writes it again whenever a config key or group changes."""
    import json

    from moex import completion

    assert json.loads(completion.KEYS.read_text()) == json.loads(
        json.dumps(completion.table())), "run: python -m moex.completion"


@pytest.mark.slow
@pytest.mark.parametrize("task", ["lissajous2", "lissajous9", "reber"])
def test_every_task_trains_and_evaluates_on_the_gpu_backend(task, tmp_path):
    """backend=gpu end to end (Triton's interpreter without CUDA: 40-110 s a task): both phases,
    the evaluation's closed loop with its tangent, symbols and every output file."""
    from moex.kernels import available

    gpu, why = available("gpu")
    if gpu is None:
        pytest.skip(f"backend gpu cannot run here: {why}")
    device = gpu.device
    done = _moex(["train", f"task={task}", "task.num_series=2", "task.length=40",
                  "task.num_test_series=1", "train.experts.steps=2", "train.gating.steps=2",
                  "num_runs=2", "backend=gpu", f"device={device}", "eval.num_samples=2",
                  "eval.lyapunov_steps=40", "eval.transient=10", "eval.plot_steps=40",
                  f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    metrics = pd.read_csv(tmp_path / "run" / "metrics.csv")
    assert len(metrics) == 2 and metrics["max_lyapunov"].notna().all()
    assert not metrics["failed"].any()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks a machine without CUDA")
def test_backend_gpu_without_cuda_is_refused_and_writes_nothing(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    done = subprocess.run(MOEX + ["train", "backend=gpu", f"hydra.run.dir={tmp_path / 'run'}"],
                          cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "moex: error: backend=gpu needs device=cuda and a CUDA device (device=cpu); use "
        "backend=cpu (or auto) on this machine"]
    assert list(tmp_path.iterdir()) == []


def test_misspelt_choices_and_keys_get_the_closest_first(tmp_path, moex_here):
    task = moex_here(["train", "task=lisajous2"], tmp_path)
    assert task.returncode == 2
    assert "task=lisajous2 is unknown; choose one of lissajous2, lissajous9, " in task.stderr
    key = moex_here(["train", "train.expert.steps=3"], tmp_path)
    assert key.returncode == 2
    assert "unknown key train.expert.steps; did you mean train.experts.steps" in key.stderr
    assert list(tmp_path.iterdir()) == []


def test_version_answers_without_importing_the_stack(tmp_path):
    done = _moex(["--version"], tmp_path)
    assert done.returncode == 0 and done.stdout.startswith("moex ")
    probe = subprocess.run([sys.executable, "-c", "import sys; sys.argv = ['moex', '--version']; "
                            "from moex.launch import main; main(); "
                            "print('torch' in sys.modules, 'hydra' in sys.modules)"],
                           capture_output=True, text=True, timeout=60)
    assert probe.stdout.split()[-2:] == ["False", "False"], probe.stdout + probe.stderr


def test_cfg_with_multirun_is_one_line_not_a_traceback(tmp_path, moex_here):
    done = moex_here(["train", "-m", "num_runs=1,2", "--cfg", "job"], tmp_path)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert "drop -m" in done.stderr and list(tmp_path.iterdir()) == []


def test_a_single_run_composes_its_config_once_and_builds_its_data_once(tmp_path, monkeypatch):
    """`moex train` composes the command line once (the validation's config is the one the run
    uses, with .hydra/ as `hydra.main` writes it) and builds its data set once."""
    import logging

    from hydra._internal.config_loader_impl import ConfigLoaderImpl

    from moex import cli, data

    counts = {"composed": 0, "built": 0}
    compose, make = ConfigLoaderImpl.load_configuration, data.make_task

    def composing(self, *args, **kwargs):
        counts["composed"] += 1
        return compose(self, *args, **kwargs)

    def building(*args, **kwargs):
        counts["built"] += 1
        return make(*args, **kwargs)

    monkeypatch.setattr(ConfigLoaderImpl, "load_configuration", composing)
    monkeypatch.setattr(data, "make_task", building)
    monkeypatch.chdir(tmp_path)
    run_dir = tmp_path / "run"
    handlers = list(logging.getLogger().handlers)
    try:  # a seed of its own: no data set of another test in this process's cache
        cli.main(["train", "task=lissajous2", *TINY, "seed=8123", "eval.enabled=false",
                  f"hydra.run.dir={run_dir}"])
    finally:
        logging.getLogger().handlers[:] = handlers  # Hydra set up the run's log
    assert counts == {"composed": 1, "built": 1}
    hydra_cfg = (run_dir / ".hydra" / "hydra.yaml").read_text()
    assert "    - hydra.mode=RUN\n" in hydra_cfg and "name: train\n" in hydra_cfg
    assert (run_dir / ".hydra" / "overrides.yaml").read_text().startswith("- task=lissajous2\n")
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["phase"] == "done"


def test_resume_picks_the_newest_unfinished_run_and_a_rerun_names_it(tmp_path, monkeypatch,
                                                                    capsys):
    """resume=true continues the newest unfinished folder of the task (not a newer finished
    one); the same command without it starts afresh but names the unfinished folder first."""
    import json

    from moex import cli

    monkeypatch.chdir(tmp_path)
    for name, status in (("2026-12-01_10-00-00", "interrupted"), ("2026-12-02_10-00-00", "done"),
                         ("2026-12-03_10-00-00", "done")):
        run = tmp_path / "outputs" / "lissajous2" / name
        (run / ".hydra").mkdir(parents=True)
        (run / "checkpoint.pt").write_bytes(b"")
        (run / "status.json").write_text(json.dumps({"status": status}))
        (run / ".hydra" / "overrides.yaml").write_text("- task=lissajous2\n- seed=3\n")
    assert cli._latest_run("lissajous2").name == "2026-12-01_10-00-00"
    cli._tell_interrupted("lissajous2", ["seed=3", "task=lissajous2"])
    said = capsys.readouterr().err
    assert "outputs/lissajous2/2026-12-01_10-00-00 holds an unfinished run" in said
    assert "resume=true" in said
    cli._tell_interrupted("lissajous2", ["seed=4", "task=lissajous2"])  # another command
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("code, status, stderr", [(None, 0, ""), (3, 3, ""),
                                                  ("moex: error: x", 1, "moex: error: x\n")])
def test_the_command_ends_as_sys_exit_would_without_the_teardown(code, status, stderr, tmp_path):
    """`moex.launch.leave`: the exit status and message of sys.exit(code), the exit handlers run
    (logging's flush among them) and the buffered output written; then os._exit."""
    log = tmp_path / "x.log"
    script = ("import atexit, logging, sys; from moex.launch import leave; "
              f"logging.basicConfig(filename={str(log)!r}); logging.warning('kept'); "
              "atexit.register(print, 'handler ran'); print('buffered', end=' '); "
              f"leave({code!r}); print('not reached')")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)
    assert (done.returncode, done.stdout, done.stderr) == (status, "buffered handler ran\n",
                                                           stderr)
    assert log.read_text() == "WARNING:root:kept\n"
