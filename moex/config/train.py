"""The training config of both phases (paper Sec. 2.1): steps, rates, momentum, the adaptive
rate of Sec. 2.1.4, the departures studied beside the paper, checkpoints."""

from dataclasses import dataclass, field
from typing import Any

from moex.errors import check, check_positive, check_range, positive_or_auto

MOMENTUM_FORMS = ("paper", "mregn")


@dataclass
class AdaptiveLRConfig:
    """The adaptive rule of Sec. 2.1.4: while r > max_ratio retry with α·decrease and the whole
    step (momentum part included) shrunk alike; α·increase after a step with r < 1; give up
    (reject the step, zero the momentum) after max_retries."""

    max_ratio: float = 1.1  # r_th
    decrease: float = 0.7  # α_dec
    increase: float = 1.05  # α_inc
    max_retries: int = 1000


@dataclass
class PhaseConfig:
    steps: int = 10000
    learning_rate: float = 0.01  # α̃
    momentum: float = 0.9  # η
    adaptive_lr: bool = True  # Sec. 2.1.4; criterion: the teacher-forced KL (phase 2)
    attraction: bool = False  # the C code's u_0 attraction term (not in the paper)
    log_every: int = 100


@dataclass
class ExpertPhaseConfig(PhaseConfig):
    steps: int = 30000
    adaptive_lr: bool = False  # as the C code's -a; criterion: the mixture MSE E
    gate_prior_std: Any = 10.0  # ς of the Brownian prior on β (Eq. 13); auto: a pilot
    # run chooses it from the data (moex.pilot)
    pilot_steps: int = 2000  # phase-1 steps of gate_prior_std=auto's pilot (at most `steps`)


@dataclass
class GatingPhaseConfig(PhaseConfig):
    """Phase 2. Two departures from the paper, off by default, for the study of what makes the
    switching chaotic: `target_temperature` fits the gating RNN to softmax(β / temperature)
    instead of ĝ = softmax(β) (1 = the paper; below 1 sharper; 0 = one-hot argmax), and
    `input_noise_var` adds Gaussian noise of that variance to the inputs x_n it reads, drawn
    afresh at every training step (Sec. 4.3 adds such noise to the trained closed loop)."""

    target_temperature: float = 1.0
    input_noise_var: float = 0.0


@dataclass
class TrainConfig:
    """Both phases. `momentum_form`: `paper` keeps the step Δθ = αg + ηΔθ in the momentum
    buffer (Eq. 17); `mregn` keeps the raw gradient sum and scales the whole step by the adaptive
    rate. The two agree whenever the rate is constant."""

    experts: ExpertPhaseConfig = field(default_factory=ExpertPhaseConfig)
    gating: GatingPhaseConfig = field(default_factory=GatingPhaseConfig)
    adaptive: AdaptiveLRConfig = field(default_factory=AdaptiveLRConfig)
    momentum_form: str = "paper"
    checkpoint_every: int = 1000  # steps between resumable checkpoints (0 = only at the end)

    def __post_init__(self):
        check(self.checkpoint_every >= 0,
              f"train.checkpoint_every={self.checkpoint_every} must be >= 0")
        for key, phase in (("train.experts", self.experts), ("train.gating", self.gating)):
            check(phase.steps >= 0, f"{key}.steps={phase.steps} must be >= 0")
            check_positive(f"{key}.learning_rate", phase.learning_rate)
            check_range(f"{key}.momentum", phase.momentum, 0.0, 1.0)
            check(phase.log_every >= 1, f"{key}.log_every={phase.log_every} must be >= 1")
        self.experts.gate_prior_std = positive_or_auto("train.experts.gate_prior_std",
                                                       self.experts.gate_prior_std)
        check(self.experts.pilot_steps >= 1,
              f"train.experts.pilot_steps={self.experts.pilot_steps} must be >= 1")
        check(self.gating.target_temperature >= 0,
              f"train.gating.target_temperature={self.gating.target_temperature} must be >= 0 "
              f"(1 = the paper's ĝ, 0 = one-hot)")
        check(self.gating.input_noise_var >= 0,
              f"train.gating.input_noise_var={self.gating.input_noise_var} must be >= 0")
        check(self.adaptive.max_ratio >= 1,
              f"train.adaptive.max_ratio={self.adaptive.max_ratio} must be >= 1")
        check_range("train.adaptive.decrease", self.adaptive.decrease, 0.0, 1.0, low_open=True)
        check(self.adaptive.increase >= 1,
              f"train.adaptive.increase={self.adaptive.increase} must be >= 1")
        check(self.adaptive.max_retries >= 1,
              f"train.adaptive.max_retries={self.adaptive.max_retries} must be >= 1")
        check(self.momentum_form in MOMENTUM_FORMS,
              f"train.momentum_form={self.momentum_form!r}; choose paper or mregn")
