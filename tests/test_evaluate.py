"""The metric table (moex.evaluation), tracking during training, and the production Lyapunov path
(moex.closed_loop on a backend) against a known exponent."""

import dataclasses
import math

import numpy as np
import pandas as pd
import pytest
import torch

from moex import objectives
from moex.closed_loop import closed_loop_lyapunov, generate, trained_state
from moex.config import Config
from moex.config.evaluation import EvalConfig
from moex.config.model import ModelConfig
from moex.config.train import ExpertPhaseConfig, GatingPhaseConfig, TrainConfig
from moex.data import load_task
from moex.evaluation import _decided, _train_block_kl, evaluate
from moex.jobs import initial_parameters
from moex.kernels import get_backend
from moex.metrics.lyapunov import chaos_label, standard_error
from moex.metrics.switching import segment_symbols, switch_probability
from moex.model import expert_forward, gate_estimates, gating_forward, random_state
from moex.tasks import Dataset, TaskConfig, make_task, task_config
from moex.train import phase2_targets, train_experts, train_gating
from moex.verbs.train import run as run_train
from tests.helpers import backend_params

QUICK = EvalConfig(num_samples=3, lyapunov_steps=400, transient=50, plot_steps=100)


def _trained(task: TaskConfig, model: ModelConfig, R=2, steps=(30, 20)):
    cfg = Config(task=task, model=model, num_runs=R)
    data = load_task(cfg)
    series = torch.as_tensor(data.series)
    S, _, D = series.shape
    experts, gating = initial_parameters(cfg, S, D, torch.float64)
    beta = None
    if D:
        experts, beta, _ = train_experts(experts, series, model, ExpertPhaseConfig(steps[0]),
                                         TrainConfig(), backend=get_backend())
    targets = phase2_targets(beta, data, R, torch.float64)
    gating, _ = train_gating(gating, targets, series[:, :-1] if D else series, model,
                             GatingPhaseConfig(steps[1]), rule=TrainConfig(), backend=get_backend())
    return data, experts, beta, gating


def test_the_metric_table_of_a_lissajous_task():
    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 4, 5
    data, experts, beta, gating = _trained(task_config("lissajous2", num_series=2, length=60,
                                                      num_test_series=1), model)
    rows = pd.DataFrame(evaluate(experts, beta, gating, data, 1, cfg=QUICK,
                                 generator=torch.Generator().manual_seed(0),
                                 backend=get_backend()).rows)
    series = torch.as_tensor(data.series)
    outputs, _ = expert_forward(experts, series[:, :-1])
    ghat = gate_estimates(beta)
    np.testing.assert_allclose(rows["E"], objectives.mixture_mse(outputs, series[:, 1:], ghat))
    log_gates, _ = gating_forward(gating, ghat, series[:, :-1], 1)
    kl = objectives.gating_kl(log_gates, ghat[:, :, 1:]) / (2 * 58 * 2)
    np.testing.assert_allclose(rows["E_g"], kl)
    assert (rows["lyapunov_positive"] == (rows["max_lyapunov"] > 0)).all()
    assert rows["positive_sample_fraction"].between(0, 1).all()
    assert (np.isfinite(rows["max_lyapunov_se"]) & (rows["max_lyapunov_se"] > 0)).all()
    for column in ("switch_prob", "switch_prob_gates", "nonperiodic_fraction"):
        assert rows[column].dropna().between(0, 1).all(), column
    truth = [segment_symbols(data.symbol_of[labels], data.period) for labels in data.labels]
    assert (rows["data_switch_prob"] == switch_probability(truth)).all()
    assert (rows["E_closed"] >= 0).all() and rows["block_kl_test"].notna().all()
    assert (rows[["num_samples", "lyapunov_samples", "lyapunov_steps"]] == [3, 3, 400]).all().all()
    labels = [chaos_label(m, se, 400) for m, se in
              zip(rows["max_lyapunov"], rows["max_lyapunov_se"], strict=True)]
    assert (rows["chaos"] == labels).all()
    # undetermined runs get more samples until decided or eval.decide_samples is spent; the
    # first num_samples are the same draws as without (the symbol statistics keep only those)
    decided = pd.DataFrame(evaluate(experts, beta, gating, data, 1,
                                    cfg=dataclasses.replace(QUICK, decide_samples=9),
                                    generator=torch.Generator().manual_seed(0),
                                    backend=get_backend()).rows)
    for first, then in zip(rows.itertuples(), decided.itertuples(), strict=True):
        assert then.lyapunov_samples == (3 if first.chaos != "undetermined" else
                                         then.lyapunov_samples) in (3, 6, 9)
        assert then.switch_prob == first.switch_prob or math.isnan(first.switch_prob)


def test_a_networks_evaluation_is_the_same_alone_and_in_a_batch():
    """With a generator per run (`evaluation_generators`), run 0 evaluated beside another network
    draws the same initial states, tangents and noise as alone: its metrics agree (the closed
    loop of a batch equals its runs alone to rounding); with one generator shared by the batch
    (before 2026-12-04) its random initial states depended on the batch."""
    from moex.verbs.train import evaluation_generators

    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 4, 5
    data, experts, beta, gating = _trained(task_config("lissajous2", num_series=2, length=60,
                                                      num_test_series=1), model)
    noisy = dataclasses.replace(QUICK, noise_var=1e-3)

    def run0(runs: int, generators) -> pd.Series:
        first = {k: v[:runs] for k, v in experts.items()}, beta[:runs], {
            k: v[:runs] for k, v in gating.items()}
        return pd.DataFrame(evaluate(first[0], first[1], first[2], data, 1, cfg=noisy,
                                     generator=generators, backend=get_backend()).rows).iloc[0]

    alone, batch = run0(1, evaluation_generators(7, 1)), run0(2, evaluation_generators(7, 2))
    for column in ("E_closed", "block_kl_train", "block_kl_test", "max_lyapunov",
                   "max_lyapunov_noisy", "max_lyapunov_se", "switch_prob"):
        assert batch[column] == pytest.approx(alone[column], rel=1e-9, abs=1e-12), column
    shared = run0(2, torch.Generator().manual_seed(evaluation_generators(7, 1)[0].initial_seed()))
    assert shared["max_lyapunov"] != pytest.approx(alone["max_lyapunov"], rel=1e-9, abs=1e-12)


def test_metrics_a_task_cannot_have_are_left_out():
    model = ModelConfig(num_experts=7)
    model.gating.context_size = 4
    data, experts, beta, gating = _trained(task_config("reber", num_series=2, length=30),
                                           model)
    rows = evaluate(experts, beta, gating, data, 1, cfg=dataclasses.replace(QUICK, block_length=3),
                    generator=torch.Generator().manual_seed(0), backend=get_backend()).rows
    assert not {"E", "E_closed"} & set(rows[0]) and "block_kl_test" in rows[0]
    # the C code's symbol rule on the same closed loop: a step with no gate above 0.5 becomes a
    # symbol of its own, so the KLs may differ; λ_max and E^g are untouched
    threshold = evaluate(experts, beta, gating, data, 1,
                         cfg=dataclasses.replace(QUICK, block_length=3, symbol_rule="threshold"),
                         generator=torch.Generator().manual_seed(0), backend=get_backend())
    for key in ("max_lyapunov", "E_g"):
        assert threshold.rows[0][key] == rows[0][key]
    assert threshold.samples["transition"].shape[-1] == 8  # 7 gates and "none"
    # a user's series: no held-out data, no true labels
    lissajous = make_task(task_config("lissajous2", num_series=2, length=40, num_test_series=0), 0)
    mine = Dataset(lissajous.series, -np.ones((2, 40), int), [], np.zeros(0, int))
    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 3, 4
    cfg = Config(model=model, num_runs=1)
    experts, gating = initial_parameters(cfg, 2, 2, torch.float64)
    beta = torch.zeros(1, 2, 39, 2)
    rows = evaluate(experts, beta, gating, mine, 1, cfg=QUICK,
                    generator=torch.Generator().manual_seed(0), backend=get_backend()).rows
    assert not {"block_kl_test", "data_switch_prob"} & set(rows[0])
    assert all(not isinstance(v, float) or not math.isnan(v)
               for k, v in rows[0].items() if k not in ("switch_prob", "switch_prob_gates",
                                                         "mean_residence"))


def test_undetermined_runs_are_sampled_again_until_decided_or_the_budget_is_spent():
    """`_decided` draws num_samples more per run while a run's label is undetermined: a run that
    is decided keeps its samples, one that becomes decided stops, one that never does stops at
    eval.decide_samples."""
    cfg = dataclasses.replace(QUICK, num_samples=2, lyapunov_steps=1000, decide_samples=6)
    first = np.array([[[0.5], [0.52]],     # chaotic from the start
                      [[0.5], [-0.4]],     # undetermined, then decided by more samples
                      [[1e-4], [-1e-4]]])  # a limit cycle: undetermined whatever comes
    rounds = iter([np.array([[[9.0], [9.0]], [[0.5], [0.52]], [[2e-4], [-2e-4]]]),
                   np.array([[[9.0], [9.0]], [[0.51], [0.5]], [[1e-4], [-1e-4]]])])
    runs = _decided(first, cfg, lambda: next(rounds))
    assert [len(lam) for lam in runs] == [2, 6, 6]
    assert [chaos_label(lam.mean(), standard_error(lam[:, 0]), 1000) for lam in runs] == [
        "chaotic", "chaotic", "undetermined"]
    assert len(_decided(first, dataclasses.replace(cfg, decide_samples=0), None)[2]) == 2


def test_tracking_during_training(tmp_path):
    """eval.every tracks the training-data block KL and λ_max in the phase-2 history; the last
    tracked block KL is that of the trained network."""
    cfg = Config(task=task_config("lissajous2", num_series=2, length=40, num_test_series=0),
                 num_runs=2)
    cfg.model.experts.context_size, cfg.model.gating.context_size = 4, 5
    cfg.train = TrainConfig(experts=ExpertPhaseConfig(steps=6),
                            gating=GatingPhaseConfig(steps=5, log_every=100))
    cfg.eval = EvalConfig(enabled=False, every=2, track_samples=2, track_steps=100,
                          transient=10)
    saved = run_train(cfg, tmp_path)
    history = pd.read_csv(tmp_path / "history.csv")
    tracked = history[(history["phase"] == "gating") & history["block_kl_train"].notna()]
    assert sorted(tracked["step"].unique()) == [0, 2, 4]
    assert tracked["max_lyapunov"].notna().all()
    assert (tracked["max_lyapunov_se"] > 0).all()  # two samples: an error per tracking point
    data = load_task(cfg)
    series = torch.as_tensor(data.series)
    targets = gate_estimates(saved.beta)
    closed = generate(saved.experts, saved.gating,
                      trained_state(saved.experts, saved.gating, targets, series, delay=1),
                      targets.shape[2], backend=get_backend())
    last = tracked[tracked["step"] == 4].sort_values("run")["block_kl_train"]
    np.testing.assert_allclose(last, _train_block_kl(targets, closed["gates"], cfg.eval))

    # eval.track_from: only the end of training is tracked (Fig. 15's flip at the last steps);
    # the training itself is the same
    cfg.eval = EvalConfig(enabled=False, every=2, track_from=3, track_samples=2,
                          track_steps=100, transient=10)
    late = run_train(cfg, tmp_path / "late")
    history = pd.read_csv(tmp_path / "late" / "history.csv")
    tracked = history[(history["phase"] == "gating") & history["block_kl_train"].notna()]
    assert sorted(tracked["step"].unique()) == [4]
    for k, v in saved.gating.items():
        assert torch.equal(late.gating[k], v), k


@pytest.mark.parametrize("backend", backend_params(slow_interpreted=True), indirect=True)
def test_lyapunov_of_a_closed_loop_with_zero_weights_is_the_slowest_decay(backend):
    """With every weight and bias zero, each potential decays as u_n = (1 - ε) u_{n-1} and the
    outputs and gates are constant: the largest exponent is ln(1 - min ε) exactly, here that of
    the gating RNN, ln(1 - ε^g)."""
    model = ModelConfig()
    model.gating.epsilon = 0.07
    cfg = Config(model=model, num_runs=2)
    experts, gating = initial_parameters(cfg, 2, 2, torch.float64)
    for params in (experts, gating):
        for name, value in params.items():
            if name not in ("tau", "u0"):
                params[name] = torch.zeros_like(value)
    state = random_state(experts, gating, 3, num_features=2, delay=1,
                         generator=torch.Generator().manual_seed(0))
    # (a long transient: the experts' faster decay must leave the tangents first)
    lam = closed_loop_lyapunov(experts, gating, state, 200, 400,
                               generator=torch.Generator().manual_seed(1),
                               num_exponents=1 if backend.caps.interpreted else 2, backend=backend)
    torch.testing.assert_close(lam, torch.full_like(lam, math.log(1 - 0.07)), rtol=0,
                               atol=1e-10)


def test_noise_enters_only_the_metrics_it_is_said_to():
    """With ρ² > 0, λ_max is still that of the noiseless loop (bit for bit the exponent of an
    evaluation without noise), the noisy exponent stands beside it, and the noisy columns are
    named."""
    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 4, 5
    data, experts, beta, gating = _trained(task_config("lissajous2", num_series=2, length=60,
                                                      num_test_series=1), model)

    def table(noise_var):
        cfg = dataclasses.replace(QUICK, noise_var=noise_var)
        return pd.DataFrame(evaluate(experts, beta, gating, data, 1, cfg=cfg,
                                     generator=torch.Generator().manual_seed(0),
                                     backend=get_backend()).rows)

    clean, noisy = table(0.0), table(0.01)
    assert "max_lyapunov_noisy" not in clean and "noise_enters" not in clean
    for column in ("max_lyapunov", "positive_sample_fraction", "E", "E_g", "E_closed",
                   "block_kl_train"):
        assert (clean[column] == noisy[column]).all(), column
    assert (noisy["max_lyapunov_noisy"] != noisy["max_lyapunov"]).all()
    named = set(noisy["noise_enters"].iloc[0].split())
    assert {"switch_prob", "nonperiodic_fraction", "max_lyapunov_noisy"} <= named
    assert not {"max_lyapunov", "E_closed"} & named


def test_trained_initial_states_start_each_sample_from_its_series():
    """eval.initial_states=trained (the paper's Fig. 16 protocol): sample n starts from the
    trained state of series n mod S, so λ_max is that of closed loops started there, the same
    as computed directly from those states with the same generator."""
    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 4, 5
    data, experts, beta, gating = _trained(task_config("lissajous2", num_series=2, length=60,
                                                      num_test_series=1), model)
    cfg = dataclasses.replace(QUICK, initial_states="trained", num_samples=4)
    rows = pd.DataFrame(evaluate(experts, beta, gating, data, 1, cfg=cfg,
                                 generator=torch.Generator().manual_seed(0),
                                 backend=get_backend()).rows)
    series = torch.as_tensor(data.series)
    state = trained_state(experts, gating, gate_estimates(beta), series, delay=1, rows=[0, 1, 0, 1])
    direct = closed_loop_lyapunov(experts, gating, state, cfg.lyapunov_steps, cfg.transient,
                                  generator=torch.Generator().manual_seed(0),
                                  backend=get_backend())
    np.testing.assert_allclose(rows["max_lyapunov"], direct.mean(1)[:, 0], rtol=1e-12)
    with pytest.raises(ValueError, match="eval.initial_states='nope'; choose random or trained"):
        EvalConfig(initial_states="nope")


def test_figures_of_a_noisy_evaluation_say_so(tiny_cfg, tmp_path, monkeypatch):
    """With eval.noise_var > 0 the closed-loop figures are of the noisy loop: every title of
    trajectory, gates, runs and residence times names ρ²; without noise none does."""
    from moex import plotting

    titles = {}

    def keep(fig, path, fmt="png"):
        texts = [ax.get_title() for ax in fig.axes] + (
            [fig._suptitle.get_text()] if fig._suptitle is not None else [])
        titles[path.stem] = " ".join(texts)

    monkeypatch.setattr(plotting, "save_figure", keep)
    tiny_cfg.eval = dataclasses.replace(tiny_cfg.eval, num_samples=2, lyapunov_steps=200,
                                        transient=20, plot_steps=100, noise_var=0.001)
    run_train(tiny_cfg, tmp_path / "noisy")
    for name in ("trajectory", "gates", "runs", "residence_times"):
        assert "ρ² = 0.001" in titles[name], name
    titles.clear()
    tiny_cfg.eval = dataclasses.replace(tiny_cfg.eval, noise_var=0.0)
    run_train(tiny_cfg, tmp_path / "clean")
    assert titles and not any("ρ²" in t for t in titles.values())
    page = (tmp_path / "clean" / "report.md").read_text()
    assert "2 random initial states × 200 closed-loop steps" in page
    # a run whose closed loop sits still is called a fixed point in its panel, and only then
    with np.load(tmp_path / "clean" / "samples.npz") as samples:
        still = [np.ptp(out, axis=0).max() < 1e-3 for out in samples["outputs"]]
    assert titles["runs"].count("a fixed point") == sum(still)
    # re-evaluated from the trained initial states: the page says so
    from moex.config import EvalOverrides, EvaluateConfig
    from moex.verbs.evaluate import run as run_evaluate

    run_evaluate(EvaluateConfig(run_dir=str(tmp_path / "clean"),
                                eval=EvalOverrides(initial_states="trained")),
                 tmp_path / "trained")
    page = (tmp_path / "trained" / "report.md").read_text()
    assert "2 trained initial states (sample n from series n mod S) × 200" in page
    assert "random initial states" not in page


def test_eval_test_series_draws_more_held_out_data_that_begins_with_the_runs_own(tiny_cfg,
                                                                                  tmp_path):
    """eval.test_series=N scores the test KL on N held-out series drawn as the task draws them:
    the training series are the run's, the first held-out series are the run's own, and N equal
    to the task's own count changes nothing. A user's files have none to draw: refused."""
    for task in (tiny_cfg.task, task_config("reber", num_series=2, length=50,
                                           num_test_series=2)):
        cfg = dataclasses.replace(tiny_cfg, task=task)
        if task.name == "reber":
            cfg.model = dataclasses.replace(cfg.model, num_experts=7)
        own = load_task(cfg)
        more = load_task(dataclasses.replace(cfg, eval=dataclasses.replace(cfg.eval,
                                                                           test_series=5)))
        same = load_task(dataclasses.replace(cfg, eval=dataclasses.replace(
            cfg.eval, test_series=task.num_test_series)))
        assert same is own
        np.testing.assert_array_equal(more.series, own.series)
        np.testing.assert_array_equal(more.labels, own.labels)
        assert len(more.test.labels) == 5
        n = len(own.test.labels)
        np.testing.assert_array_equal(more.test.labels[:n], own.test.labels)
        np.testing.assert_array_equal(more.test.series[:n], own.test.series)
    np.save(tmp_path / "a.npy", np.zeros((30, 2)))
    files = dataclasses.replace(tiny_cfg, task=task_config("csv", path=str(tmp_path),
                                                          length=0),
                                eval=dataclasses.replace(tiny_cfg.eval, test_series=3))
    with pytest.raises(ValueError, match="eval.test_series=3: task csv is a user's files"):
        load_task(files)
    with pytest.raises(ValueError, match="eval.test_series=-1 must be >= 0"):
        EvalConfig(test_series=-1)
    # `moex evaluate` of a finished run: only the test KL moves
    from moex.config import EvalOverrides, EvaluateConfig
    from moex.verbs.evaluate import run as run_evaluate

    tiny_cfg.eval = dataclasses.replace(QUICK, block_length=2)
    run_train(tiny_cfg, tmp_path / "run")
    trained = pd.read_csv(tmp_path / "run" / "metrics.csv")
    for count in (1, 4):
        again = run_evaluate(EvaluateConfig(run_dir=str(tmp_path / "run"),
                                            eval=EvalOverrides(test_series=count)),
                             tmp_path / f"test_series_{count}")
        for column in ("E_g", "block_kl_train", "max_lyapunov", "switch_prob"):
            np.testing.assert_array_equal(again[column], trained[column])
        moved = again["block_kl_test"] != trained["block_kl_test"]
        assert not moved.any() if count == tiny_cfg.task.num_test_series else moved.all()
