"""A run folder's checkpoint: its config rebuilt from the plain dict it stores (as older versions
wrote it, too), and whether it may be continued: only by the config that wrote it (its
evaluation settings aside)."""

import dataclasses
from pathlib import Path

from moex import checkpoint, io
from moex.config import Config
from moex.errors import ConfigError
from moex.tasks import own_keys, typed_config


def check_same_training(saved: dict, cfg: Config, path: Path) -> None:
    """A checkpoint may only be resumed by the config that wrote it (eval settings aside)."""
    now = dataclasses.asdict(cfg)
    if now["train"]["experts"]["gate_prior_std"] == "auto":  # the pilot's choice, if it ran
        chosen = io.chosen_gate_prior(Path(path).parent)
        now["train"]["experts"]["gate_prior_std"] = "auto" if chosen is None else chosen
    saved = dataclasses.asdict(config_from_dict(saved))
    for key in ("task", "model", "train", "seed", "num_runs", "precision"):
        if saved[key] != now[key]:
            differ = _first_difference(saved[key], now[key], key)
            raise ConfigError(f"{path} was trained with {differ[0]}={differ[1]}, not "
                              f"{differ[2]}; use another output folder or the same overrides")


def _first_difference(then, now, key: str) -> tuple[str, object, object]:
    """The first dotted key whose value differs between two config trees, with both values."""
    if isinstance(then, dict) and isinstance(now, dict):
        for k in then:
            if then[k] != now.get(k):
                return _first_difference(then[k], now.get(k), f"{key}.{k}")
    return key, then, now


def open_checkpoint(cfg: Config, out_dir: Path) -> checkpoint.Checkpoint | None:
    """The checkpoint of a run folder, checked against the config that would continue it (a
    `ConfigError` if it was trained with another); None for a new folder."""
    path = Path(out_dir) / checkpoint.NAME
    if not path.exists():
        return None
    saved = checkpoint.load(path)
    check_same_training(saved.config, cfg, path)
    return saved


def config_from_dict(data: dict) -> Config:
    """Rebuild (and re-validate) a `Config` from the plain dict stored in a checkpoint: the task's
    keys into its own config class (checkpoints written before tasks had their own classes hold
    every task's keys; the task's own are kept)."""
    if "dtype" in data:  # checkpoints written before `dtype` was renamed `precision`
        data = {**{k: v for k, v in data.items() if k != "dtype"}, "precision": data["dtype"]}
    model = data.get("model", {})
    if any("time_constant" in model.get(net, {}) for net in ("experts", "gating")):
        # written before `time_constant` (which held ε, not τ) was renamed `epsilon`
        model = {**model, **{net: {("epsilon" if k == "time_constant" else k): v
                                   for k, v in model[net].items()}
                             for net in ("experts", "gating") if net in model}}
        data = {**data, "model": model}
    task = own_keys(dict(data.get("task", {})), Config().task.name)
    return typed_config(Config, {**data, "task": task})
