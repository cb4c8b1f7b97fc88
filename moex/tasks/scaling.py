"""A user's data mapped into the range the model can produce (task `csv` and `moex.fit`).

The experts' outputs are tanh-bounded (Eq. 3), so data beyond ±1 cannot be fitted.
`task.scale=none` (the default) refuses such data with a message that says how to scale it;
`auto` maps each feature linearly onto [-LIMIT, LIMIT] and keeps the map, so that generated
outputs are returned in the data's own units.
"""

from dataclasses import dataclass

import numpy as np

from moex.errors import check

SCALES = ("none", "auto")
LIMIT = 0.8  # |x| after `auto`: room below tanh's bound of 1


@dataclass(frozen=True)
class Scale:
    """x_model = (x - offset) / factor per feature (D,); identity when both are None."""

    offset: np.ndarray | None = None
    factor: np.ndarray | None = None

    def to_data(self, values: np.ndarray) -> np.ndarray:
        """Model outputs (..., D) in the data's units."""
        return values if self.offset is None else values * self.factor + self.offset

    def to_model(self, values: np.ndarray) -> np.ndarray:
        """Data (..., D) in the model's units (new data of a trained run)."""
        return values if self.offset is None else (values - self.offset) / self.factor

    def as_dict(self) -> dict:
        return {} if self.offset is None else {"offset": self.offset, "factor": self.factor}


def fit_scale(series: np.ndarray, mode: str, source: str) -> tuple[np.ndarray, Scale]:
    """The series (S, T, D) in model units and the map back; `source` names the data in errors.

    `none` checks that every value lies in [-1, 1]; `auto` maps each feature's range onto
    [-LIMIT, LIMIT] (a constant feature is only shifted to 0)."""
    check(mode in SCALES, f"task.scale={mode!r}; choose none or auto")
    low, high = series.min((0, 1)), series.max((0, 1))
    if mode == "none":
        bad = np.flatnonzero((low < -1) | (high > 1))
        check(not len(bad), f"{source}: feature {bad[0] if len(bad) else 0} spans "
                            f"[{low[bad[0]] if len(bad) else 0:.4g}, "
                            f"{high[bad[0]] if len(bad) else 0:.4g}], outside [-1, 1], the "
                            f"range of the model's tanh outputs; set task.scale=auto to map "
                            f"each feature onto [-{LIMIT}, {LIMIT}] (outputs are mapped back), "
                            f"or rescale the data yourself")
        return series, Scale()
    offset = (high + low) / 2
    half = (high - low) / 2
    factor = np.where(half > 0, half / LIMIT, 1.0)
    return (series - offset) / factor, Scale(offset, factor)


WINDOW = 50  # steps per window of `noise_floor`
FLOOR = 1e-3  # the smallest σ̄ `noise_floor` gives


def noise_floor(series: np.ndarray) -> float:
    """σ̄ for `model.sigma_min=auto`: half the 10th percentile, over windows of WINDOW steps of
    every series (S, T, D), of the one-step change's RMS per feature, at least FLOOR. An expert
    can then fit the quietest regime's own variability instead of a floor above it (with the
    paper's σ̄ = 0.05, regimes whose steps change by less are told apart by nothing)."""
    change = np.diff(series, axis=1)
    T = change.shape[1]
    windows = [np.sqrt(np.mean(change[s, w:w + WINDOW] ** 2))
               for s in range(len(change)) for w in range(0, max(T - WINDOW, 0) + 1, WINDOW)]
    return max(0.5 * float(np.percentile(windows, 10)), FLOOR)
