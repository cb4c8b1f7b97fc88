"""Output errors (paper Sec. 3 and 4.2): E^closed of the closed loop against the training data."""

import numpy as np


def closed_loop_mse(outputs: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """E^closed = Σ ½‖y^teach_n - y^closed_n‖² / (T d) per leading index (Eq. 23).

    Args:
        outputs: (..., S, T, D) closed-loop outputs from the trained initial states.
        targets: (S, T, D) training outputs.

    Returns:
        (...) the error, T summed over series.
    """
    S, T, D = targets.shape
    return 0.5 * ((np.asarray(outputs) - targets) ** 2).sum((-1, -2, -3)) / (S * T * D)
