"""The paper's tables, each declared with the task it belongs to and the setting that keys its
rows, so that `moex report` sets a sweep beside them without naming any task itself."""

from dataclasses import dataclass

import pandas as pd

PAPER_TABLE1 = pd.DataFrame({  # Reber, mean of 50 trials (Table 1)
    "model.gating.context_size": [10, 20, 30, 50],
    "paper_E_g": [0.144868, 0.010118, 0.005721, 0.004339],
    "paper_block_kl_train": [2.511791, 0.258037, 0.051233, 0.006338],
    "paper_block_kl_test": [2.388665, 0.309089, 0.327273, 0.290858],
    "paper_max_lyapunov": [0.203512, 0.215117, 0.160728, 0.116574],
    "paper_positive_percent": [88, 98, 100, 100],
})
PAPER_TABLE2 = pd.DataFrame({  # two Lissajous curves, mean of 30 trials (Table 2)
    "task.switch_prob": [0.5, 0.25, 0.125],
    "paper_switch_prob": [0.451033, 0.275999, 0.150866],
    "paper_max_lyapunov": [0.001076, 0.002080, 0.002829],
    "paper_positive_percent": [93, 96, 96],
})


@dataclass(frozen=True)
class PaperTable:
    """A table of the paper: its name in a report, the task whose sweeps it compares, the setting
    (report column) its rows are keyed by, the paper's numbers, our columns beside them, whether
    a sweep must vary that setting to be set beside it, and the order of its rows."""

    name: str
    task: str
    key: str
    numbers: pd.DataFrame
    columns: tuple[str, ...]
    needs_several: bool = False
    descending: bool = False


PAPER_TABLES = (
    PaperTable("table1", "reber", "model.gating.context_size", PAPER_TABLE1,
               ("E_g_mean", "block_kl_train_mean", "block_kl_test_mean", "max_lyapunov_mean",
                "positive_percent", "chaotic_percent", "undetermined_count", "num_runs")),
    PaperTable("table2", "lissajous2", "task.switch_prob", PAPER_TABLE2,
               ("data_switch_prob_mean", "switch_prob_mean", "switch_prob_std",
                "near_data_percent", "max_lyapunov_mean", "max_lyapunov_std", "positive_percent",
                "positive_ci_low", "positive_ci_high", "chaotic_percent", "undetermined_count",
                "nonperiodic_fraction_mean", "num_runs"),
               needs_several=True, descending=True),
)
