"""The evaluation's config: sample sizes, the block KL's form, the chaos label's rule (paper
Sec. 3-4 and the departures a user may choose)."""

from dataclasses import dataclass

from moex.errors import check, check_positive
from moex.metrics.symbols import block_kl, block_kl_mregn

SYMBOL_RULES = ("argmax", "threshold")  # Eq. 22 | the C code's gate above 0.5


@dataclass
class EvalConfig:
    """Evaluation settings; the paper's protocol is 50 samples × 100000 steps (Lissajous) and
    200 × 10000 (Reber), after a discarded transient."""

    enabled: bool = True  # `moex train` ends by evaluating
    num_samples: int = 50  # closed-loop runs from random initial states, per network
    lyapunov_steps: int = 100000
    transient: int = 1000
    num_exponents: int = 1  # 1 = the maximum exponent only
    # gates in the Jacobian of the mixture: `real`, or `uniform` (1/K) as the authors'
    # mregn-lyapunov computes them (a bug in that tool), to compare with its exponents
    jacobian_gates: str = "real"
    block_length: int = 5  # m of D_KL^(m) (3 for Reber)
    kl_floor: float = 1e-3  # model probability of data blocks it never produced (renormalised)
    # held-out series the test KL compares with (0: the task's num_test_series); drawn as the
    # task draws them, so that the first ones are the run's own held-out series
    test_series: int = 0
    noise_var: float = 0.0  # ρ², Gaussian noise added to x_n each step (Sec. 4.3)
    max_period: int = 100  # periodicity test of the symbol sequence (Sec. 4.3)
    plot_steps: int = 2000  # closed-loop steps of the first sample kept for figures
    every: int = 0  # track block KL and λ_max every N gating-phase steps (0 = off)
    # tasks whose symbols are the gates (Reber): `argmax` (Eq. 22), or `threshold` as the
    # authors' C code (a gate above 0.5 names the symbol; a step with none is a symbol of its own)
    symbol_rule: str = "argmax"
    # the block KL: `paper` (Eq. 21, model probability kl_floor for a block it lacks) or `mregn`,
    # the authors' C formula (a count of 0.001 for a missing block, plus their second sum)
    kl_form: str = "paper"
    # where the evaluation's samples start: `random` states (Sec. 4), or `trained`: sample n
    # from the trained initial state of series n mod S, as the paper does for Fig. 16
    initial_states: str = "random"
    track_samples: int = 4  # random initial states per network when tracking
    track_steps: int = 5000  # Lyapunov steps per sample when tracking
    track_from: int = 0  # the first gating step tracked (e.g. only the end of training)
    # the chaos label (moex.metrics.lyapunov.chaos_label): λ_max must clear chaos_z standard
    # errors (and 1/lyapunov_steps) to be called chaotic or not chaotic, else undetermined
    chaos_z: float = 2.0
    # an undetermined network gets num_samples more random initial states at a time until its
    # label is decided or it has this many samples in all (0: no further samples)
    decide_samples: int = 0

    def __post_init__(self):
        check(self.every >= 0, f"eval.every={self.every} must be >= 0")
        check(self.track_from >= 0, f"eval.track_from={self.track_from} must be >= 0")
        for key in ("num_samples", "lyapunov_steps", "num_exponents", "block_length",
                    "max_period", "plot_steps", "track_samples", "track_steps"):
            check(getattr(self, key) >= 1, f"eval.{key}={getattr(self, key)} must be >= 1")
        check(self.transient >= 0, f"eval.transient={self.transient} must be >= 0")
        check(self.test_series >= 0, f"eval.test_series={self.test_series} must be >= 0")
        check(self.jacobian_gates in ("real", "uniform"),
              f"eval.jacobian_gates={self.jacobian_gates!r}; choose real or uniform")
        check(self.noise_var >= 0, f"eval.noise_var={self.noise_var} must be >= 0")
        check(self.symbol_rule in SYMBOL_RULES,
              f"eval.symbol_rule={self.symbol_rule!r}; choose argmax or threshold")
        check(self.kl_form in ("paper", "mregn"),
              f"eval.kl_form={self.kl_form!r}; choose paper or mregn")
        check(self.initial_states in ("random", "trained"),
              f"eval.initial_states={self.initial_states!r}; choose random or trained")
        check_positive("eval.kl_floor", self.kl_floor)
        check_positive("eval.chaos_z", self.chaos_z)
        check(self.decide_samples == 0 or self.decide_samples >= self.num_samples,
              f"eval.decide_samples={self.decide_samples} must be 0 (off) or >= "
              f"eval.num_samples={self.num_samples}")

    def block_kl(self, data, model) -> float:
        """D_KL^(m) of this evaluation's form and block length, data first."""
        if self.kl_form == "mregn":
            return block_kl_mregn(data, model, self.block_length)
        return block_kl(data, model, self.block_length, self.kl_floor)
