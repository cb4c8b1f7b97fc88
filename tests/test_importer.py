"""moex.importer: networks the authors' C tools trained (tests/data/mregn: written by mre-learn,
gn-learn, rnn-learn and mregn-generate of jnamika/mregn 6a92a19, built by tools/build_mregn.sh,
on moex's data files) imported with the errors their own logs report, run in moex's closed loop
as their generator runs them, and exported back to the same files."""

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from moex import checkpoint
from moex.closed_loop import generate, trained_state
from moex.config import ImportConfig
from moex.config.model import ModelConfig
from moex.errors import ConfigError
from moex.evaluation import _teacher_forced
from moex.importer import export_run, import_networks
from moex.kernels import get_backend
from moex.mregn_format import read_save, write_save
from moex.tasks import make_task, task_config
from moex.train import phase2_targets
from moex.verbs import importing

DATA = Path(__file__).parent / "data" / "mregn"
TASKS = {"mixture": task_config("lissajous2", num_series=2, length=60),
         "gating": task_config("reber", num_series=2, length=60, num_test_series=4)}


def _imported(kind: str, source=None):
    task = TASKS[kind]
    cfg = ImportConfig(task=task, source=[str(source or DATA / kind)],
                       model=ModelConfig(num_experts=2 if kind == "mixture" else 7))
    dataset = make_task(task, 0)
    return (*import_networks(cfg, dataset), dataset)


def _last_log_row(path: Path) -> np.ndarray:
    rows = [line.split() for line in path.read_text().splitlines() if line and line[0] != "#"]
    return np.array(rows[-1][1:], dtype=float)


def test_imported_mixture_has_the_errors_the_c_tools_logged():
    """E (mre-error.log, column 1 of each series) and E^g (gn-error.log, column 1) of the last
    epoch, recomputed by moex from the imported parameters: the import maps every weight, bias,
    σ, β and (bias-shifted) initial state as the C code uses them."""
    cfg, record, dataset = _imported("mixture")
    series = record.series
    targets = phase2_targets(record.beta, dataset, 1, series.dtype)
    error, error_g = _teacher_forced(record.experts, record.beta, record.gating, series,
                                     delay=cfg.model.delay, targets=targets)
    mre_log, gn_log = _last_log_row(DATA / "mixture/mre-error.log"), \
        _last_log_row(DATA / "mixture/gn-error.log")
    # the C code logs per series Σ½‖ŷ-t‖²/(L d), moex the mean over series of Σ‖ŷ-t‖²/(T d)/2
    assert error.item() == pytest.approx(mre_log[0::3].mean(), rel=1e-5)
    assert error_g.item() == pytest.approx(gn_log[0::2].mean(), rel=1e-5)


def test_imported_gating_network_has_the_error_rnn_learn_logged():
    cfg, record, dataset = _imported("gating")
    targets = phase2_targets(None, dataset, 1, record.series.dtype)
    _, error_g = _teacher_forced({}, None, record.gating, record.series, delay=cfg.model.delay,
                                 targets=targets)
    assert error_g.item() == pytest.approx(_last_log_row(DATA / "gating/error.log").mean(),
                                           rel=1e-5)


def test_imported_mixture_generates_what_mregn_generate_prints():
    """`mregn-generate -i 1 -n 40` (the trained initial state of series 1) against moex's closed
    loop from the same state: equal to the 6 decimals the tool prints."""
    cfg, record, dataset = _imported("mixture")
    targets = phase2_targets(record.beta, dataset, 1, record.series.dtype)
    k = [1]
    state = trained_state({n: v[:, k] if n == "u0" else v for n, v in record.experts.items()},
                          {n: v[:, k] if n == "u0" else v for n, v in record.gating.items()},
                          targets[:, k], record.series[k], delay=cfg.model.delay)
    with torch.no_grad():
        outputs = generate(record.experts, record.gating, state, 40,
                           backend=get_backend())["outputs"][0, 0].numpy()
    printed = np.loadtxt(DATA / "mixture/generate_from_series1.txt")
    assert np.abs(outputs - printed).max() <= 5e-7 + 1e-12


@pytest.mark.parametrize("kind", ["mixture", "gating"])
def test_import_then_export_gives_the_same_files(tmp_path, kind):
    """The law of the pair: a network imported and exported back over its own files (for the
    fields moex does not keep: momentum, priors, connection tables) is the same network, every
    array equal to rounding (1e-12) and every other field byte for byte."""
    _, record, _ = _imported(kind)
    names = ["rnn.dat"] if kind == "gating" else ["mre.dat", "gn.dat"]
    templates = {n: read_save(DATA / kind / n) for n in names}
    for path in export_run(record, 0, templates, tmp_path):
        _assert_same(read_save(path), templates[path.name], path.name)


def _assert_same(a, b, where):
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _assert_same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{i}]")
    else:
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12, err_msg=where)


def test_import_refuses_networks_of_other_data():
    task = task_config("lissajous2", num_series=2, length=60, switch_prob=0.25)
    cfg = ImportConfig(task=task, source=[str(DATA / "mixture")])
    with pytest.raises(ConfigError, match="trained on other data"):
        import_networks(cfg, make_task(cfg.task, 0))


def test_import_refuses_a_folder_without_save_files(tmp_path):
    cfg = ImportConfig(task=TASKS["mixture"], source=[str(tmp_path)])
    with pytest.raises(ConfigError, match="holds neither rnn.dat nor mre.dat"):
        import_networks(cfg, make_task(cfg.task, 0))


def test_moex_import_writes_a_run_folder_of_every_network(tmp_path):
    """Two copies of the network: R = 2 runs, each the imported one; the folder evaluates."""
    for i in range(2):
        shutil.copytree(DATA / "mixture", tmp_path / f"net{i}")
    cfg = ImportConfig(task=TASKS["mixture"], source=[str(tmp_path / "net*")])
    cfg.eval.enabled = False
    record = importing.run(cfg, tmp_path / "run")
    saved = checkpoint.load(tmp_path / "run")
    assert saved.config["num_runs"] == 2 and saved.phase == "done"
    assert torch.equal(saved.gating["w_rec"][0], saved.gating["w_rec"][1])
    assert torch.equal(saved.beta, record.beta)
    sources = pd.read_csv(tmp_path / "run" / "imported_from.csv")
    assert sources["network"].tolist() == [0, 0, 1, 1]  # mre.dat and gn.dat of each network
    epochs = sources.set_index(sources["file"].map(lambda f: Path(f).name))["epochs"]
    page = (tmp_path / "run" / "report.md").read_text()  # the C tools' epochs, not moex's steps
    assert (f"trained by the authors' C tools (epochs: gn.dat {epochs['gn.dat'].iloc[0]}, "
            f"mre.dat {epochs['mre.dat'].iloc[0]}), imported") in page
    assert "training steps" not in page


def test_networks_of_different_sizes_are_one_clear_error(tmp_path):
    shutil.copytree(DATA / "mixture", tmp_path / "a")
    shutil.copytree(DATA / "mixture", tmp_path / "b")
    gn = read_save(tmp_path / "b" / "gn.dat")
    net = gn["net"]  # drop one context unit of the gating network in b
    M = net["c_state_size"] - 1
    for key in ("weight_ci", "weight_cc", "delta_weight_ci", "delta_weight_cc", "prior_weight_ci",
                "prior_weight_cc", "threshold_c", "tau", "eta", "delta_threshold_c", "delta_tau",
                "prior_threshold_c", "prior_tau", "const_init_c", "connection_ci",
                "connection_cc"):
        net[key] = net[key][:M]
    for key in ("weight_cc", "delta_weight_cc", "prior_weight_cc", "weight_oc",
                "delta_weight_oc", "prior_weight_oc"):
        net[key] = net[key][:, :M]
    net["connection_cc"], net["connection_oc"] = net["connection_cc"][:, :M + 1], \
        net["connection_oc"][:, :M + 1]
    net["c_state_size"] = M
    for series in net["series"]:
        for key in ("init_c_inter_state", "init_c_state", "delta_init_c_inter_state"):
            series[key] = series[key][:M]
    write_save(tmp_path / "b" / "gn.dat", gn, "gn.dat")
    cfg = ImportConfig(task=TASKS["mixture"], source=[str(tmp_path / "a"), str(tmp_path / "b")])
    with pytest.raises(ConfigError, match=r"b has w_in of shape \(4, 4\), .*a \(5, 4\); one import "
                                          r"holds networks of one shape"):
        import_networks(cfg, make_task(cfg.task, 0))


def test_imported_gating_network_generates_what_rnn_generate_prints():
    """`rnn-generate -i 1 -n 40` (its output fed back as the next input) against moex's closed
    loop of the gating network alone from the same trained state. moex records at step n the
    gates in use (g_n, from the delay line), the tool prints the new output g_{n+1}."""
    cfg, record, dataset = _imported("gating")
    targets = phase2_targets(None, dataset, 1, record.series.dtype)
    state = trained_state({}, {n: v[:, [1]] if n == "u0" else v for n, v in
                               record.gating.items()}, targets[:, [1]], record.series[[1]],
                          delay=cfg.model.delay)
    with torch.no_grad():
        gates = generate({}, record.gating, state, 41, backend=get_backend())["gates"][0, 0].numpy()
    printed = np.loadtxt(DATA / "gating/generate_from_series1.txt")
    assert np.abs(gates[1:] - printed).max() <= 5e-7 + 1e-12
