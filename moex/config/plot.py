"""The figures' config: which run the single-run figures show, and in which format."""

from dataclasses import dataclass

from moex.errors import check

FORMATS = ("png", "pdf", "svg")


@dataclass
class PlotConfig:
    """Which run the single-run figures show: -1 picks the run with the highest λ_max (the most
    chaotic; failed runs never), k picks run k. `format`: png, pdf or svg (vector)."""

    run: int = -1
    format: str = "png"

    def __post_init__(self):
        check(self.run >= -1, f"plot.run={self.run} must be -1 (the run with the highest "
                              f"λ_max) or a run index >= 0")
        check(self.format in FORMATS, f"plot.format={self.format!r}; choose png, pdf or svg")
