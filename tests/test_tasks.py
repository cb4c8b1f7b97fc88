import logging

import numpy as np
import pytest
import torch

from moex.errors import ConfigError
from moex.tasks import lissajous, make_task, reber, task_config
from moex.tasks.switching import generate_switching


def _switch_stats(labels_at_boundaries):
    """Empirical transition matrix from a sequence of primitive indices at decision points."""
    K = labels_at_boundaries.max() + 1
    counts = np.zeros((K, K))
    np.add.at(counts, (labels_at_boundaries[:-1], labels_at_boundaries[1:]), 1)
    return counts / counts.sum(1, keepdims=True)


@pytest.mark.parametrize("name", ["lissajous2", "lissajous9", "reber", "markov_primitives"])
def test_same_seed_same_data_and_shapes(name):
    own = dict(primitives=[{"amplitude": [0.5, 0.5]}, {"amplitude": [0.3, 0.2],
                                                       "frequency": [2, 1]}],
               transition=[[0.5, 0.5], [0.5, 0.5]]) if name == "markov_primitives" else {}
    cfg = task_config(name, num_series=3, length=200, num_test_series=2, **own)
    a, b, c = make_task(cfg, 1), make_task(cfg, 1), make_task(cfg, 2)
    assert np.array_equal(a.series, b.series) and np.array_equal(a.labels, b.labels)
    assert not np.array_equal(a.labels, c.labels) or not np.array_equal(a.series, c.series)
    assert a.series.shape[:2] == (3, 200) and a.labels.shape == (3, 200)
    assert a.test.series.shape[:2] == (2, 200)
    assert np.all(np.abs(a.series) <= 1.0)


@pytest.mark.parametrize("p", [0.5, 0.25, 0.125])
def test_lissajous2_transition_and_residence(p, period=25, length=200_000):
    rng = np.random.default_rng(0)
    series, labels = generate_switching(lissajous.two_circles(),
                                        lissajous.two_circles_transition(p), length, period,
                                        rng=rng)
    at_decisions = labels[::period]  # one primitive per period; switches only at the origin
    assert (labels.reshape(-1, period) == at_decisions[:, None]).all()
    empirical = _switch_stats(at_decisions)
    n = len(at_decisions)
    assert abs(empirical[0, 1] - p) < 4 * np.sqrt(p * (1 - p) / (n / 2))
    assert abs(empirical[1, 0] - p) < 4 * np.sqrt(p * (1 - p) / (n / 2))
    # residence time (repetitions of a curve) is geometric with mean 1/p
    runs = np.diff(np.flatnonzero(np.diff(at_decisions) != 0))
    assert abs(runs.mean() - 1 / p) < 0.05 / p
    # continuity: the orbit moves about 2π·0.4/P per step and never jumps
    steps = np.linalg.norm(np.diff(series, axis=0), axis=1)
    assert steps.max() < 1.05 * 2 * np.pi * 0.4 / period


@pytest.mark.parametrize("rule", ["paper", "mregn"])
def test_lissajous9_transitions_and_continuity(rule, period=32, length=400_000):
    prims = lissajous.nine_curves()
    transition = lissajous.nine_curves_transition(rule)
    assert np.allclose(transition.sum(1), 1)
    series, labels = generate_switching(prims, transition, length, period,
                                        rng=np.random.default_rng(1),
                                        initial=0)
    # decisions happen when a primitive ends; recover the visited sequence
    visits, n = [], 0
    while n < length:
        visits.append(labels[n])
        n += int(prims[labels[n]].length * period)
    visits = np.array(visits[:-1])
    counts = np.zeros((12, 12))
    np.add.at(counts, (visits[:-1], visits[1:]), 1)
    empirical = counts / counts.sum(1, keepdims=True)
    assert np.abs(empirical - transition).max() < 0.03
    steps = np.linalg.norm(np.diff(series, axis=0), axis=1)
    assert steps.max() < 0.12  # no jumps at period 32 (the largest step is 0.111)


def test_reber_strings_obey_grammar_and_choice_probability():
    rng = np.random.default_rng(2)
    symbols = reber.generate_reber(50_000, 100, 0.5, rng)
    assert reber.accepts(symbols)
    assert not reber.violations(symbols).any()
    # after T from state 0 the automaton is in state 1; state 1 emits S or X with 1/2 each
    T, S = reber.SYMBOLS.index("T"), reber.SYMBOLS.index("S")
    B = reber.SYMBOLS.index("B")
    after_b = symbols[1:][symbols[:-1] == B]
    assert abs((after_b == T).mean() - 0.5) < 0.02
    broken = symbols.copy()
    broken[10] = S if symbols[10] != S else B
    assert not reber.accepts(broken) or reber.violations(broken).any()
    # the threshold rule's "no gate above 0.5" symbol (index 7) is a violation, then a restart
    none = symbols.copy()
    none[20] = len(reber.SYMBOLS)
    assert not reber.accepts(none)
    assert np.flatnonzero(reber.violations(none)).tolist() == [20]


def test_reber_one_hot_targets():
    data = make_task(task_config("reber", num_series=4, length=500), 0)
    assert data.series.shape == (4, 500, 0)
    assert data.gate_targets.shape == (4, 500, 7)
    assert np.array_equal(data.gate_targets.argmax(-1), data.labels)


@pytest.mark.parametrize("bad, match", [
    (dict(name="lissajous2", switch_prob=1.5), "task.switch_prob=1.5 is outside"),
    (dict(name="lissajous2", num_series=0), "task.num_series=0"),
    (dict(name="reber", switch_prob=0.5), "task.switch_prob is not a key of task reber"),
    (dict(name="nope"), "task.name='nope' is unknown"),
    (dict(name="markov_primitives", primitives=[{"amplitude": [1, 1]}],
          transition=[[0.5]]), "task.transition\\[0\\] sums to 0.5"),
])
def test_bad_task_config(bad, match):
    with pytest.raises(ConfigError, match=match):
        make_task(task_config(**bad), 0)


def test_csv_task(tmp_path):
    rng = np.random.default_rng(0)
    for i in range(3):
        np.savetxt(tmp_path / f"s{i}.csv", rng.uniform(-1, 1, (50, 2)), delimiter=",")
    data = make_task(task_config("csv", path=str(tmp_path), length=0), 0)
    assert data.series.shape == (3, 50, 2)
    (tmp_path / "s1.csv").write_text("0.1,0.2\nnan,0.3\n" * 30)
    with pytest.raises(ConfigError, match="NaN or inf"):
        make_task(task_config("csv", path=str(tmp_path), length=0), 0)
    (tmp_path / "s1.csv").write_text("0.1,0.2\n0.3\n" * 30)
    with pytest.raises(ConfigError, match="rows of different lengths"):
        make_task(task_config("csv", path=str(tmp_path), length=0), 0)


def test_an_unknown_task_lists_the_closest_first():
    with pytest.raises(ConfigError, match="task.name='lisajous2' is unknown; choose one of "
                                          "lissajous2, lissajous9, "):
        task_config("lisajous2")


def test_empty_npy_arrays_and_folders_named_like_files_are_clean_errors(tmp_path):
    np.save(tmp_path / "empty.npy", np.zeros((120, 0)))
    with pytest.raises(ConfigError, match="empty array of shape \\(120, 0\\)"):
        make_task(task_config("csv", path=str(tmp_path / "empty.npy"), length=0), 0)
    data = tmp_path / "data"
    (data / "sub.csv").mkdir(parents=True)  # a folder named like a file is not read
    np.savetxt(data / "s.csv", np.zeros((20, 2)), delimiter=",")
    assert make_task(task_config("csv", path=str(data), length=0), 0).series.shape == (
        1, 20, 2)


def test_data_seed_sets_the_data_apart_from_the_networks():
    from moex.tasks import make_task, task_config

    base = task_config("lissajous2", num_series=2, length=200)
    own = make_task(base, 3).series
    fixed = task_config("lissajous2", num_series=2, length=200, data_seed=3)
    np.testing.assert_array_equal(make_task(fixed, 0).series, own)  # seed no longer matters
    np.testing.assert_array_equal(make_task(fixed, 7).series, own)
    assert not np.array_equal(make_task(base, 0).series, own)


def test_a_csv_reads_back_exactly_and_a_word_in_it_is_refused(tmp_path):
    """Every written digit is kept (the nearest double, whatever pandas parses with: pandas 3.0
    lost the last bit of some); a cell that is not a number names its row."""
    from moex.tasks import files

    values = np.random.default_rng(1).uniform(-0.5, 0.5, (50, 2))
    np.savetxt(tmp_path / "a.csv", values, delimiter=",", fmt="%.17g", header="x,y",
               comments="")
    series, _ = files.load_series(str(tmp_path / "a.csv"), 0, 3)
    np.testing.assert_array_equal(series[0], values)
    (tmp_path / "b.csv").write_text("x,y\n0.1,0.2\n0.3,abc\n0.5,0.6\n")
    with pytest.raises(ConfigError, match=r"b.csv data row 2 is not numeric \(0.3, abc\)"):
        files.load_series(str(tmp_path / "b.csv"), 0, 3)


def test_the_noise_floor_is_half_the_quietest_windows_one_step_change():
    """White noise of SD s changes by s√2 per step: the floor is about s/√2; with a quiet and a
    loud regime it follows the quiet one; a constant series gets the smallest floor."""
    from moex.tasks.scaling import FLOOR, noise_floor

    rng = np.random.default_rng(0)
    white = rng.normal(0, 0.1, (4, 2000, 3))
    assert noise_floor(white) == pytest.approx(0.1 / np.sqrt(2), rel=0.1)
    quiet = np.arange(2000) // 200 % 2 == 0  # alternating regimes of 200 steps
    mixed = rng.normal(0, 1, (2, 2000, 2)) * np.where(quiet, 0.01, 0.2)[None, :, None]
    assert noise_floor(mixed) == pytest.approx(0.01 / np.sqrt(2), rel=0.2)
    assert noise_floor(np.zeros((1, 300, 2))) == FLOOR


TOY_MODULE = """
from dataclasses import dataclass

import numpy as np

from moex.errors import check_positive
from moex.tasks.base import Task, TaskConfig, user_data


@dataclass
class ToyConfig(TaskConfig):
    name: str = "toy3d"
    period: float = 20.0

    def __post_init__(self):
        super().__post_init__()
        check_positive("task.period", self.period)


def make(cfg, rng, min_length):
    t = 2 * np.pi * np.arange(cfg.length) / cfg.period
    phases = rng.uniform(0, 2 * np.pi, size=cfg.num_series)
    return user_data(0.8 * np.stack([np.stack([np.sin(t + p), np.cos(t + p), np.sin(2 * t)], -1)
                                     for p in phases]))


TASKS = (Task(ToyConfig, make, lambda cfg: 3),)
"""

TOY_YAML = """# @package _global_
task: {name: toy3d, num_series: 2, length: 40, num_test_series: 0, period: 16}
"""


def test_a_task_is_one_module_and_one_yaml_a_toy_3d_task_trains_with_no_other_edit(
        monkeypatch, tmp_path):
    """A task is a module (its config class, generator and `Task` entry) and a YAML: a 3-feature
    toy task written here, in a temporary module and a temporary config
    folder, is type-checked, trained and evaluated by `moex train` on the command line; its
    own key (`task.period`) is overridable and another task's key is refused."""
    import importlib

    from moex import cli, tasks

    (tmp_path / "toy_task_module.py").write_text(TOY_MODULE)
    (tmp_path / "conf" / "task").mkdir(parents=True)
    (tmp_path / "conf" / "task" / "toy3d.yaml").write_text(TOY_YAML)
    monkeypatch.syspath_prepend(str(tmp_path))
    toy = importlib.import_module("toy_task_module")
    for task in toy.TASKS:  # what the registry's line in moex/tasks/__init__.py does
        monkeypatch.setitem(tasks.TASKS, task.name, task)
    monkeypatch.chdir(tmp_path)
    search = f"hydra.searchpath=[file://{tmp_path / 'conf'}]"
    tiny = ["model.experts.context_size=4", "model.gating.context_size=5",
            "train.experts.steps=6", "train.gating.steps=4", "eval.num_samples=2",
            "eval.lyapunov_steps=50", "eval.transient=10", "eval.plot_steps=20"]
    with pytest.raises(SystemExit) as refused:
        cli.main(["train", "task=toy3d", search, "task.switch_prob=0.3", *tiny])
    assert refused.value.code == 2
    handlers = list(logging.getLogger().handlers)
    try:
        cli.main(["train", "task=toy3d", search, "task.period=12", *tiny,
                  f"hydra.run.dir={tmp_path / 'run'}"])
    finally:
        logging.getLogger().handlers[:] = handlers  # Hydra set up the run's log
    saved = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    assert saved["config"]["task"] == {"name": "toy3d", "num_series": 2, "length": 40,
                                       "num_test_series": 0, "data_seed": -1, "period": 12.0}
    assert saved["series"].shape == (2, 40, 3) and saved["experts"]["w_out"].shape[-2] == 3
    assert (tmp_path / "run" / "metrics.csv").exists()
    assert not (tmp_path / "outputs").exists()  # the refused command wrote nothing
