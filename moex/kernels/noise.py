"""The input noise of phase 2 (`train.gating.input_noise_var`), the same draws on every backend."""

import numpy as np


def input_noise(seeds: list[int], step: int, shape: tuple, variance: float, dtype) -> np.ndarray:
    """(R, *shape) Gaussian noise of `variance` for training step `step`, run r drawn from
    (seeds[r], step) alone: a run sees the same noise batched or alone, fresh or resumed.
    `dtype`: a numpy or a torch dtype."""
    dtype = np.dtype(str(dtype).removeprefix("torch."))
    return np.stack([np.random.default_rng([seed, step]).standard_normal(shape)
                     for seed in seeds]).astype(dtype) * np.sqrt(variance)
