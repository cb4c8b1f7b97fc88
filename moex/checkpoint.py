"""`checkpoint.pt`, the one record of a run's training: written and read here only.

A plain dict of tensors, numbers, strings and nested dicts on disk (`torch.load(path,
weights_only=True)` reads it without moex); `Checkpoint` is its typed form. Loading checks every
field, so that a damaged, truncated or foreign file ends in one `ConfigError` naming the file and
what is wrong, before anything is written.
"""

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from moex.errors import ConfigError
from moex.io import atomic_write

NAME = "checkpoint.pt"
FORMAT_VERSION = 2  # 2 added data_scale; version 1 files load with an identity scale
PHASES = ("experts", "gating", "done")
_NET = {"w_in", "w_rec", "w_out", "b_c", "b_o", "tau", "u0"}
REQUIRED = {"experts": _NET | {"log_sigma"}, "gating": _NET}  # when the group is present


@dataclass
class Checkpoint:
    """A run's state. Tensors have a leading run axis R where they are per network.

    Attributes:
        config: the training `Config` as a plain dict.
        phase: the phase to continue (`experts`, `gating`), or `done`.
        series: (S, L, D) the training series in model units; labels: (S, L) true primitives.
        experts: phase-1 parameters (empty until phase 1 ends, and for symbolic tasks).
        beta: (R, S, T, K) the gate logits of phase 1, or None.
        gating: phase-2 parameters (empty until training ends).
        experts_rows: the phase-1 history rows.
        gating_rows: the phase-2 history rows (set when training ends; absent before 0.1.1).
        failed: per run, whether it became non-finite (set when training ends).
        train_state: the resumable state of the unfinished phase, or None.
        track_rng: the generator state of the metrics tracked while training, or None.
        data_scale: offset and factor (D,) of `task.scale=auto` ({} for none).
    """

    config: dict
    phase: str
    series: torch.Tensor
    labels: torch.Tensor
    experts: dict = field(default_factory=dict)
    beta: torch.Tensor | None = None
    gating: dict = field(default_factory=dict)
    experts_rows: list = field(default_factory=list)
    gating_rows: list = field(default_factory=list)
    failed: list | None = None
    train_state: dict | None = None
    track_rng: torch.Tensor | None = None
    data_scale: dict = field(default_factory=dict)

    def save(self, path: Path) -> Path:
        payload = {"format_version": FORMAT_VERSION, **dataclasses.asdict(self)}
        payload["data_scale"] = {k: torch.as_tensor(v) for k, v in self.data_scale.items()}
        return atomic_write(path, lambda tmp: torch.save(payload, tmp))

    def scale_arrays(self) -> dict[str, np.ndarray]:
        return {k: torch.as_tensor(v).numpy() for k, v in self.data_scale.items()}


def _fail(path: Path, what: str) -> None:
    raise ConfigError(f"{path}: {what}; it is not a usable moex checkpoint (train again into "
                      f"another folder, or restore the file)")


def _validate(path: Path, c: Checkpoint) -> None:
    """Types and shapes that every reader relies on."""
    if c.phase not in PHASES:
        _fail(path, f"phase {c.phase!r} is not one of {', '.join(PHASES)}")
    if not isinstance(c.config, dict) or "num_runs" not in c.config:
        _fail(path, "its config is missing")
    if not isinstance(c.series, torch.Tensor) or c.series.ndim != 3:
        _fail(path, "series is not an (S, L, D) tensor")
    if not isinstance(c.labels, torch.Tensor) or c.labels.shape != c.series.shape[:2]:
        _fail(path, "labels do not match the series")
    R = c.config["num_runs"]
    for group, names in REQUIRED.items():
        missing = sorted(names - set(getattr(c, group))) if getattr(c, group) else []
        if missing:
            _fail(path, f"its {group} network lacks {', '.join(missing)}")
        for name, value in getattr(c, group).items():
            if not isinstance(value, torch.Tensor) or value.shape[:1] != (R,):
                _fail(path, f"{group}.{name} is not a tensor with one entry per run ({R})")
    if c.phase == "done":
        if not c.gating or c.failed is None or len(c.failed) != R:
            _fail(path, "it says training is done but holds no trained gating network")
        if c.series.shape[-1] > 0 and (not c.experts or c.beta is None):
            _fail(path, "it says training is done but holds no trained experts")
    if c.phase == "gating" and c.series.shape[-1] > 0 and c.beta is None:
        _fail(path, "phase 2 is due but phase 1's β is missing")


def load(path: Path) -> Checkpoint:
    """The checkpoint of a run folder (or a `.pt` file); a `ConfigError` if it is missing,
    unreadable, of another format or inconsistent."""
    given = Path(path)
    path = given / NAME if given.is_dir() or given.suffix != ".pt" else given
    if not path.is_file():
        raise ConfigError(f"run_dir={given} holds no {NAME}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt or foreign files
        _fail(path, f"it cannot be read ({type(exc).__name__}: {str(exc).splitlines()[0]})")
    version = payload.get("format_version") if isinstance(payload, dict) else None
    if version not in (1, FORMAT_VERSION):
        _fail(path, f"its format is {version}; this moex reads formats 1 and {FORMAT_VERSION}")
    names = {f.name for f in dataclasses.fields(Checkpoint)}
    missing = sorted({"config", "phase", "series", "labels"} - set(payload))
    if missing:
        _fail(path, f"it lacks {', '.join(missing)}")
    record = Checkpoint(**{k: v for k, v in payload.items() if k in names})
    _validate(path, record)
    return record
