"""moex: a mixture of RNN experts that learns stochastic switching by chaos (Namikawa & Tani).

The Python API is `fit` (train on your own arrays) and the `Fitted` it returns (`evaluate`,
`generate`, `save`), and `load` (a run folder of `moex train` as a `Fitted`); the building blocks
below are what it is made of. Each name is imported on first use, so that the `moex` command can
start compiling kernels before it imports PyTorch (`moex.launch`).
"""

import importlib

_HOMES = {
    "moex.api": ("Fitted", "fit", "load"),
    "moex.closed_loop": ("closed_loop_lyapunov", "generate", "trained_state"),
    "moex.config": ("Config",),
    "moex.errors": ("ConfigError",),
    "moex.config.evaluation": ("EvalConfig",),
    "moex.config.model": ("ModelConfig",),
    "moex.config.train": ("TrainConfig",),
    "moex.evaluation": ("evaluate",),
    "moex.kernels": ("get_backend",),
    "moex.metrics.lyapunov": ("lyapunov_exponents",),
    "moex.model": ("expert_forward", "gate_estimates", "gating_forward",
                   "init_experts", "init_gating", "leaky_scan", "random_state"),
    "moex.tasks": ("Dataset", "TaskConfig", "make_task", "task_config"),
    "moex.train": ("train_experts", "train_gating"),
    "moex.verbs.train": ("run_train",),
}
_NAMED = {"run_train": "run"}  # a public name whose module calls it otherwise (the verb's `run`)
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}
__all__ = sorted(_HOME_OF)


def __getattr__(name: str):
    if name not in _HOME_OF:
        raise AttributeError(f"module 'moex' has no attribute {name!r}")
    value = getattr(importlib.import_module(_HOME_OF[name]), _NAMED.get(name, name))
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))

