"""The model's config: sizes and constants of the mixture (paper Sec. 3.2 defaults)."""

from dataclasses import dataclass, field
from typing import Any

from moex.errors import check, check_range, positive_or_auto

INIT_SCHEMES = ("paper", "mregn")


@dataclass
class ExpertsConfig:
    context_size: int = 10  # M
    epsilon: float = 0.2  # ε of Eq. 1, the paper's "time constant" (τ = 1/ε in the C code)


@dataclass
class GatingConfig:
    context_size: int = 15  # H (the paper's M_g, NC)
    epsilon: float = 0.04  # ε^g of Eq. 5


@dataclass
class ModelConfig:
    """Sizes and constants of the mixture (paper Sec. 3.2 defaults).

    `init`: `paper` draws every weight and bias from U[-1/M, 1/M] and u_0 from U[-1, 1]
    (Sec. 2.1.5); `mregn` follows the authors' C code (mregn): input weights U[±1/inputs], biases
    U[±1], u_0 = 0. `learn_time_constants` learns τ = 1/ε per neuron, clamped to τ >= 1, as the C
    code does by default; the paper keeps ε fixed.
    """

    num_experts: int = 2  # K (the paper's N)
    delay: int = 1  # τ, feedback delay of Eq. 5 and of the closed loop
    sigma_min: Any = 0.05  # σ̄, the floor of every expert's σ (v = e^{2s} + σ̄², as in the C code);
    # "auto": from the data's one-step variability when the data are read (tasks.noise_floor)
    init: str = "paper"
    learn_time_constants: bool = False
    experts: ExpertsConfig = field(default_factory=ExpertsConfig)
    gating: GatingConfig = field(default_factory=GatingConfig)

    def __post_init__(self):
        check(self.num_experts >= 1, f"model.num_experts={self.num_experts} must be >= 1")
        check(self.delay >= 1, f"model.delay={self.delay} must be >= 1 (τ >= 1)")
        self.sigma_min = positive_or_auto("model.sigma_min", self.sigma_min)
        check(self.init in INIT_SCHEMES, f"model.init={self.init!r}; choose paper or mregn")
        for key, sub in (("model.experts", self.experts), ("model.gating", self.gating)):
            check(sub.context_size >= 1, f"{key}.context_size={sub.context_size} must be >= 1")
            check_range(f"{key}.epsilon", sub.epsilon, 0.0, 1.0, low_open=True)
