"""`moex import`: networks trained by the authors' C tools (mre-learn + gn-learn, or rnn-learn for
a gating network alone) as one moex run folder, so that moex's evaluator scores them and their
users can bring old runs over; `export_run` writes a moex run back in their format.

The C code keeps the bias inside the leaky integrator (u_C = u + v_1, c = tanh(u_C)); moex keeps it
outside (c = tanh(u + v_1), Eq. 2), so initial states move by the bias: u_0 = u_0,C - v_1 exactly.
Everything else maps one to one: W_ci → w_in, W_cc → w_rec, W_oc → w_out, thresholds → b_c, b_o,
τ → tau, s → log_sigma (σ² = e^{2s} + MIN_VARIANCE, moex's sigma_min² = MIN_VARIANCE), β → beta.
"""

import glob
import hashlib
import math
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np
import torch

from moex import checkpoint, io
from moex.config import Config, ImportConfig
from moex.errors import ConfigError, check
from moex.mregn_format import read_save, write_save
from moex.resume import config_from_dict
from moex.tasks import Dataset


def network_folders(patterns: list[str]) -> list[Path]:
    """The folders the `source` patterns name (sorted within each pattern, no repeats)."""
    check(bool(patterns), "source is required: source=[<folder with mre.dat and gn.dat, or "
                          "rnn.dat>, ...] (globs allowed)")
    folders: list[Path] = []
    for pattern in patterns:
        found = sorted(Path(p) for p in glob.glob(pattern)) or [Path(pattern)]
        for folder in found:
            check(folder.is_dir(), f"source: {folder} is not a folder")
            check(folder not in folders, f"source: {folder} is named twice")
            folders.append(folder)
    return folders


def _read(folder: Path) -> dict:
    """The save files of one network: {"kind": mixture | gating, "mre"?, "gn"}."""
    try:
        if (folder / "rnn.dat").is_file():
            return {"kind": "gating", "gn": read_save(folder / "rnn.dat")}
        if (folder / "mre.dat").is_file() and (folder / "gn.dat").is_file():
            return {"kind": "mixture", "mre": read_save(folder / "mre.dat"),
                    "gn": read_save(folder / "gn.dat")}
    except (ValueError, OSError) as exc:
        raise ConfigError(f"source: {exc}") from None
    raise ConfigError(f"source: {folder} holds neither rnn.dat nor mre.dat with gn.dat")


def _series_of(net: dict, delay: int) -> np.ndarray:
    """(S, L, I) the data a C network was trained on: its inputs, then the last τ targets."""
    return np.stack([np.concatenate([s["in_state"], s["teach_state"][-delay:]])
                     for s in net["series"]])


def _rnn_params(net: dict) -> dict[str, np.ndarray]:
    """One C network in moex's names; u0 (S, M) shifted by the bias (see the module doc)."""
    b_c = net["threshold_c"]
    return {"w_in": net["weight_ci"], "w_rec": net["weight_cc"], "w_out": net["weight_oc"],
            "b_c": b_c, "b_o": net["threshold_o"], "tau": net["tau"],
            "u0": np.stack([s["init_c_inter_state"] - b_c for s in net["series"]])}


def _stack(per_run: list[dict], dtype) -> dict[str, torch.Tensor]:
    return {k: torch.as_tensor(np.stack([p[k] for p in per_run]), dtype=dtype)
            for k in per_run[0]}


def _same_shapes(nets: list[dict], folders: list[Path]) -> None:
    first = {k: np.shape(v) for k, v in nets[0].items()}
    for net, folder in zip(nets[1:], folders[1:], strict=True):
        shapes = {k: np.shape(v) for k, v in net.items()}
        if shapes != first:
            bad = next(k for k in first if shapes.get(k) != first[k])
            raise ConfigError(f"source: {folder} has {bad} of shape {shapes.get(bad)}, "
                              f"{folders[0]} {first[bad]}; one import holds networks of one "
                              f"shape")


def import_networks(cfg: ImportConfig, dataset: Dataset) -> tuple[Config, checkpoint.Checkpoint]:
    """The moex config and finished checkpoint of the networks in `cfg.source`, which must have
    been trained on `dataset` (the data of the config's task and seed: checked)."""
    dataset_series, gate_targets = dataset.series, dataset.gate_targets
    folders = network_folders(cfg.source)
    files = [_read(f) for f in folders]
    kinds = {f["kind"] for f in files}
    check(len(kinds) == 1, "source: some folders hold rnn.dat, others mre.dat + gn.dat; import "
                           "one kind at a time")
    symbolic = kinds == {"gating"}
    check(symbolic == (gate_targets is not None),
          f"source: {'rnn.dat (a gating network alone)' if symbolic else 'mre.dat + gn.dat'} "
          f"does not fit task={cfg.task.name}, which {'has' if gate_targets is None else 'has no'}"
          f" experts")
    dtype = getattr(torch, cfg.precision)
    delay = files[0]["gn"]["delay"] if symbolic else files[0]["mre"]["delay"]
    gn_delay = files[0]["gn"]["delay"]
    check(gn_delay == delay, f"source: gn-learn's delay {gn_delay} differs from mre-learn's "
                             f"{delay}; moex uses one delay τ for both")
    expected = gate_targets if symbolic else dataset_series
    for folder, f in zip(folders, files, strict=True):
        net = f["gn"]["net"] if symbolic else f["mre"]["net"]["experts"][0]
        data = _series_of(net, delay)
        if data.shape != expected.shape or not np.allclose(data, expected, rtol=0, atol=1e-12):
            raise ConfigError(
                f"source: {folder} was trained on other data (shape {data.shape}) than "
                f"task={cfg.task.name} with seed={cfg.seed} (shape {expected.shape}); name the "
                f"task and seed that generated its data file")
    per_gating = [_rnn_params(f["gn"]["net"]) for f in files]
    _same_shapes(per_gating, folders)  # before stacking: a clear error, not numpy's
    gating = _stack(per_gating, dtype)
    R, H = gating["b_c"].shape
    K = gating["b_o"].shape[1]
    experts, beta = {}, None
    if not symbolic:
        per_run = []
        for f in files:
            nets = [_rnn_params(e) for e in f["mre"]["net"]["experts"]]
            one = {k: np.stack([n[k] for n in nets]) for k in nets[0]}
            one["u0"] = one["u0"].transpose(1, 0, 2)  # (K, S, M) -> (S, K, M)
            one["log_sigma"] = np.array([e["sigma"] for e in f["mre"]["net"]["experts"]])
            per_run.append(one)
        _same_shapes(per_run, folders)
        experts = _stack(per_run, dtype)
        beta = torch.as_tensor(np.stack([np.stack([s["beta"].T for s in f["mre"]["net"]["series"]])
                                         for f in files]), dtype=dtype)
    model = cfg.model
    model.num_experts, model.delay = K, int(delay)
    model.sigma_min, model.init, model.learn_time_constants = math.sqrt(cfg.min_variance), \
        "mregn", True
    model.gating.context_size = H
    if experts:
        model.experts.context_size = experts["w_rec"].shape[-1]
    own = {f.name for f in fields(Config)}
    plain = {k: v for k, v in asdict(cfg).items() if k in own}
    plain["num_runs"] = R
    run_cfg = config_from_dict(plain)
    params = experts | gating
    failed = [not all(bool(torch.isfinite(v[r]).all()) for v in params.values())
              for r in range(R)]
    record = checkpoint.Checkpoint(
        asdict(run_cfg), "done", torch.as_tensor(dataset_series, dtype=dtype),
        torch.as_tensor(dataset.labels), experts=experts, beta=beta,
        gating=gating, failed=failed)
    return run_cfg, record


def sources(folders: list[Path]) -> list[dict]:
    """Each imported file with its sha256 and the C tool's epoch count and adaptive rate."""
    rows = []
    for network, folder in enumerate(folders):
        for name in ("mre.dat", "gn.dat", "rnn.dat"):
            path = folder / name
            if path.is_file():
                saved = read_save(path)
                rows.append({"network": network,
                             "file": str(path.resolve()), "sha256": hashlib.sha256(
                                 path.read_bytes()).hexdigest(),
                             "epochs": int(saved["epoch"]), "adapt_lr": float(saved["adapt_lr"])})
    return rows


def _rnn_record(template: dict, params: dict, r: int, inputs: np.ndarray,
                targets: np.ndarray) -> dict:
    """A C `recurrent_neural_network` record with run r's parameters (template: the layout's
    other fields, e.g. momentum buffers, taken from an imported file or zero)."""
    net = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in template.items()}
    p = {k: v[r].detach().cpu().numpy().astype(np.float64) for k, v in params.items()}
    net.update(weight_ci=p["w_in"], weight_cc=p["w_rec"], weight_oc=p["w_out"],
               threshold_c=p["b_c"], threshold_o=p["b_o"], tau=p["tau"], eta=1 / p["tau"])
    net["series"] = [{**old, "init_c_inter_state": u + p["b_c"],
                      "init_c_state": np.tanh(u + p["b_c"]), "in_state": x, "teach_state": t}
                     for old, u, x, t in zip(template["series"], p["u0"], inputs, targets,
                                             strict=True)]
    return net


def export_run(record: checkpoint.Checkpoint, r: int, templates: dict, out_dir: Path) -> list[Path]:
    """Run r of a finished moex checkpoint as the C tools' save files in `out_dir`, written over
    `templates` (records of `read_save` of the same shapes, for the fields moex does not keep:
    momentum buffers, priors, connection tables). The inverse of `import_networks`."""
    out_dir.mkdir(parents=True, exist_ok=True)
    series = record.series.numpy()
    delay = int(record.config["model"]["delay"])
    written = []
    if "rnn.dat" in templates:
        gates = np.eye(len(record.gating["b_o"][r]))[record.labels.numpy()] \
            if record.beta is None else None
        t = templates["rnn.dat"]
        net = _rnn_record(t["net"], record.gating, r, gates[:, :-delay], gates[:, delay:])
        written.append(write_save(out_dir / "rnn.dat", {**t, "net": net}, "rnn.dat"))
        return written
    t = templates["mre.dat"]
    mre = dict(t["net"])
    experts = {k: v[:, :, None] if k == "log_sigma" else v for k, v in record.experts.items()}
    mre["experts"] = []
    for k, template in enumerate(t["net"]["experts"]):
        one = {n: (v[:, k] if n != "u0" else v[:, :, k]) for n, v in experts.items()}
        net = _rnn_record(template, one, r, series[:, :-delay], series[:, delay:])
        net["sigma"] = float(one["log_sigma"][r, 0])
        mre["experts"].append(net)
    beta = record.beta[r].numpy()
    gates = np.exp(beta) / np.exp(beta).sum(-1, keepdims=True)
    mre["series"] = [{**old, "beta": b.T, "gate": g.T}
                     for old, b, g in zip(t["net"]["series"], beta, gates, strict=True)]
    written.append(write_save(out_dir / "mre.dat", {**t, "net": mre}, "mre.dat"))
    g = templates["gn.dat"]
    ghat = np.concatenate([gates, series[:, :-delay]], axis=-1)  # rows [ĝ, x]
    net = _rnn_record(g["net"], record.gating, r, ghat[:, :-delay], gates[:, delay:])
    written.append(write_save(out_dir / "gn.dat", {**g, "net": net}, "gn.dat"))
    return written


def write_sources(out_dir: Path, folders: list[Path]) -> None:
    io.write_csv(out_dir / "imported_from.csv", sources(folders))
