"""The trained mixture run as an autonomous system (paper Sec. 2.2, 4): initial states, closed-loop
generation and Lyapunov exponents averaged over samples, on any backend, in chunks of bounded
memory. The dynamics themselves are `moex.model.closed_loop_step` and a backend's `closed_loop`."""

import torch

from moex import progress
from moex.draws import draw
from moex.errors import never, stop_if_asked
from moex.kernels import Backend
from moex.metrics.lyapunov import benettin, chunks, initial_tangents
from moex.model import ClosedLoopState

CHUNK = 500  # closed-loop steps per call of the time loop (bounds the memory of the records)


def trained_state(experts, gating, gate_targets, series, *, delay,
                  rows: list[int] | None = None) -> ClosedLoopState:
    """The trained initial state of every series (N = S), or of series `rows[n]` for sample n:
    u_0, and data / ĝ in the delay lines.

    Args:
        experts, gating: trained parameters (experts empty for symbolic tasks).
        gate_targets: (R, S, T, K) the gate estimates the gating RNN was trained on.
        series: (S, L, D) the training series; delay: τ.
        rows: the series each sample starts from (default: each series once).
    """
    if rows is not None:
        experts = {n: v[:, rows] if n == "u0" else v for n, v in experts.items()}
        gating = {n: v[:, rows] if n == "u0" else v for n, v in gating.items()}
        gate_targets, series = gate_targets[:, rows], series[rows]
    R = gate_targets.shape[0]
    experts_u = experts["u0"] if experts else series.new_zeros(R, series.shape[0], 0, 0)
    inputs = series[None, :, :delay].expand(R, -1, -1, -1)
    return ClosedLoopState(experts_u, gating["u0"], inputs, gate_targets[:, :, :delay])


def _noise(state: ClosedLoopState, steps: int, noise_std: float, generator):
    """(R, N, steps, D) Gaussian noise on x_m, or None; drawn one step at a time so that the
    random stream does not depend on how the steps are chunked."""
    if noise_std <= 0:
        return None
    x = state.inputs[..., 0, :]
    return torch.stack([noise_std * draw(torch.randn, x.shape, generator, x.dtype)
                        for _ in range(steps)], 2)


def generate(experts, gating, state: ClosedLoopState, steps: int, *, backend: Backend,
             noise_std: float = 0.0, generator=None, stop=never
             ) -> dict[str, torch.Tensor]:
    """Run the closed loop for `steps` steps on `backend`; `stop` is
    asked between chunks (`Interrupted` when it says so).

    Returns:
        outputs (R, N, T, D), gates (R, N, T, K) and gating potentials (R, N, T, H).
    """
    parts = []
    for _, size in chunks(steps, CHUNK):  # (well under a second each)
        stop_if_asked(stop, "the closed loop was")
        run = backend.closed_loop(experts, gating, state, size,
                                  noise=_noise(state, size, noise_std, generator))
        state = run.state
        parts.append((run.outputs, run.gates, run.gating_u))
    return {name: torch.cat([p[i] for p in parts], 2)
            for i, name in enumerate(("outputs", "gates", "gating_u"))}


def closed_loop_lyapunov(experts, gating, state: ClosedLoopState, steps: int, transient: int, *,
                         generator, backend: Backend, num_exponents: int = 1,
                         noise_std: float = 0.0, uniform_gates: bool = False, on_chunk=None,
                         keep_potentials: int = 0, stop=never) -> torch.Tensor:
    """The first k Lyapunov exponents (R, N, k) of the whole closed loop (Benettin's method).

    Tangent vectors start random and orthonormal, are propagated by the exact Jacobian and
    re-orthonormalised every step; `transient` steps align them, the next `steps` are averaged.

    Args:
        experts, gating, state: the trained mixture and its initial states (R, N, ...).
        generator: draws the initial tangents and the noise.
        num_exponents: k; noise_std: ρ of the noise on x_m (Sec. 4.3).
        uniform_gates: differentiate the mixture with g = 1/K, as `mregn-lyapunov` does.
        on_chunk: receives the `ClosedLoopRun` of every chunk after the transient.
        keep_potentials: record u^g in the chunks that reach into the last so many steps (None
            in the others: at the paper's scale it would be gigabytes).
        backend: where the closed loop runs (`moex.kernels.get_backend`).
        stop: asked between chunks; `Interrupted` is raised when it returns True.
    """

    def advance(tangents, size, counted, done):
        nonlocal state
        keep = counted and done + size > steps - keep_potentials
        run = backend.closed_loop(experts, gating, state, size,
                                  noise=_noise(state, size, noise_std, generator),
                                  tangents=tangents, count=counted, uniform_gates=uniform_gates,
                                  potentials=keep)
        state = run.state
        if counted and on_chunk is not None:
            on_chunk(run)
        bar.update(size)
        return run.tangents, run.growth

    with progress.bar(total=transient + steps, desc="lyapunov") as bar:
        return benettin(advance, initial_tangents(state.flat(), num_exponents, generator), steps,
                        transient=transient, chunk=CHUNK, stop=stop)
