"""The input noise of phase 2 (`train.gating.input_noise_var`), the same draws on every backend."""

import numpy as np


def input_noise(seeds: list[int], step: int, shape: tuple, variance: float, dtype) -> np.ndarray:
    """(R, *shape) Gaussian noise of `variance` for training step `step`, run r drawn from
    (seeds[r], step) alone: a run sees the same noise batched or alone, fresh or resumed.
    `dtype`: a numpy or a torch dtype, that of the result (drawn and scaled in float64, then
    rounded once)."""
    name = str(dtype)
    dtype = np.dtype(name.removeprefix("torch.") if name.startswith("torch.") else dtype)
    return (np.stack([np.random.default_rng([seed, step]).standard_normal(shape)
                      for seed in seeds]) * np.sqrt(variance)).astype(dtype)
