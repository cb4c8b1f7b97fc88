"""Random draws for R runs at once, each run from its own generator where one is given per run:
what run r draws then does not depend on how many runs are drawn beside it, so a network's
evaluation is the same in a batch of R as alone (as its training is, `moex.jobs.run_seeds`)."""

import torch

Generators = torch.Generator | list[torch.Generator] | None


def draw(sample, shape: tuple, generator: Generators, dtype=torch.float64) -> torch.Tensor:
    """`sample(shape)` (torch.rand or torch.randn) of shape (R, ...): run r's slice from
    generator[r] where `generator` is a list of R generators, else one draw from one generator."""
    if isinstance(generator, list):
        if len(generator) != shape[0]:
            raise ValueError(f"{len(generator)} generators for {shape[0]} runs")
        return torch.stack([sample(tuple(shape[1:]), generator=g, dtype=dtype)
                            for g in generator])
    return sample(tuple(shape), generator=generator, dtype=dtype)
