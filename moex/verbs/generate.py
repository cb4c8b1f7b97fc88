"""`moex generate`: closed-loop samples of a finished run's networks, from random initial states
or a series' trained state, with or without noise, into a folder of their own."""

import logging
from pathlib import Path

import torch

from moex import io
from moex.closed_loop import generate, trained_state
from moex.config import GenerateConfig
from moex.data import in_data_units
from moex.errors import never
from moex.figures import plot_samples
from moex.jobs import run_generators
from moex.model import random_state
from moex.train import phase2_targets
from moex.verbs.trained import load_run

log = logging.getLogger(__name__)

NAME, CONFIG = "generate", "generate"
check = load_run


def run(tool: GenerateConfig, out_dir: Path, stop=never) -> dict:
    """Closed-loop samples of every run from random initial states (or the trained state of
    series `from_series`) into `out_dir`: samples.npz and figures."""
    run = load_run(tool)
    cfg, saved, dataset = run.cfg, run.saved, run.dataset
    experts, gating = saved.experts, saved.gating
    generator = run_generators(tool.seed, len(gating["w_out"]))  # run r's samples: (seed, r)
    D = dataset.series.shape[2]
    if tool.from_series < 0:
        state = random_state(experts, gating, tool.num_samples, num_features=D,
                             delay=cfg.model.delay, generator=generator)
    else:  # the trained initial state of one series, repeated for every (noisy) sample
        estimates = phase2_targets(saved.beta, dataset, cfg.num_runs,
                                   gating["w_out"].dtype, cfg.train.gating.target_temperature)
        k = [tool.from_series] * tool.num_samples
        state = trained_state(experts, gating, estimates, saved.series, delay=cfg.model.delay,
                              rows=k)
    with torch.no_grad():
        out = generate(experts, gating, state, tool.steps, noise_std=tool.noise_var**0.5,
                       generator=generator, backend=run.backend, stop=stop)
    samples = {k: v.numpy() for k, v in out.items()}
    samples["symbols"] = dataset.symbolize(samples["outputs"], samples["gates"],
                                           run.backend.nearest_symbols)
    samples = in_data_units(samples, dataset)
    out_dir = Path(out_dir)
    io.save_arrays(out_dir / io.SAMPLES, samples)
    first = {k: v[:, 0] for k, v in samples.items()}
    plot_samples(first, dataset, cfg, out_dir, noise_var=tool.noise_var)
    log.info("generated %d samples x %d steps per run (noise variance %g, from %s) into %s",
             tool.num_samples, tool.steps, tool.noise_var,
             "random states" if tool.from_series < 0 else f"series {tool.from_series}",
             out_dir / io.SAMPLES)
    return samples
