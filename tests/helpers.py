"""What test modules share besides fixtures (those are in conftest.py, which pytest imports first
and which chooses Triton's interpreter where there is no CUDA): seeded generators and the
backends' parameters."""

import pytest
import torch

from moex.kernels import REGISTRY, available


def generators(seeds):
    return [torch.Generator().manual_seed(s) for s in seeds]


# the backends that run slowly here (gpu without CUDA: Triton's interpreter), by capability
INTERPRETED = tuple(name for name in REGISTRY
                    if (here := available(name)[0]) is not None and here.caps.interpreted)


def backend_params(reference: bool = True, slow_interpreted: bool = False) -> list:
    """Params of the `backend` fixture (with `indirect=True`): every backend of the registry
    (`moex.kernels.REGISTRY`), the reference too unless a test compares against it; with
    `slow_interpreted`, a backend interpreted here (gpu without CUDA) is marked slow."""
    return [pytest.param(name, id=name, marks=pytest.mark.slow
                         if slow_interpreted and name in INTERPRETED else ())
            for name in REGISTRY if reference or name != "reference"]
