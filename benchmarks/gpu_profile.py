"""Where a training epoch's time goes on the gpu backend: a few epochs of each phase under
PyTorch's profiler, the device time of every kernel and operator per epoch beside the epoch's
wall time, so that the kernels' share and the host's share (launches, the update's passes,
synchronisations) can be told apart; then the closed loop with one Lyapunov tangent (the
evaluation's), per chunk of 500 steps of runs × samples trajectories.

    python benchmarks/gpu_profile.py [--runs 90] [--epochs 20] [--samples 50] [--chunks 2]
                                     [--device cuda]

Two-Lissajous sizes (10 series x 1000 steps, the task's defaults), float64. Without CUDA it runs
the same on the CPU (`--device cpu --backend cpu`; Triton's interpreter is far too slow to say
anything), so that CI runs this script too.
"""

import argparse
import time

import torch
from bench_epochs import trainers, warm_up
from bench_lyapunov import closed_loop
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile


def profiled(fn, epochs: int, cuda: bool) -> tuple[float, list, list]:
    """Wall ms per epoch; (name, µs per epoch, calls per epoch), longest first, of the work on
    the device (kernels and copies; empty without CUDA) and of the host's operators (self CPU
    time: launches, synchronisations, PyTorch's own work)."""
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities) as prof:
        start = time.perf_counter()
        fn(epochs)
        if cuda:
            torch.cuda.synchronize()
        wall = (time.perf_counter() - start) * 1e3 / epochs
    device, host = [], []
    for event in prof.key_averages():
        on_device = event.device_type == DeviceType.CUDA
        us = event.device_time_total if on_device else event.self_cpu_time_total
        if us > 0:
            (device if on_device else host).append((event.key, us / epochs, event.count / epochs))
    return wall, *(sorted(rows, key=lambda r: -r[1]) for rows in (device, host))


def table(rows: list, what: str, top: int, per: str = "epoch") -> str:
    lines = [f"| {what} | ms per {per} | calls per {per} |", "|---|---|---|"]
    lines += [f"| {name[:60]} | {us / 1e3:.3f} | {calls:.1f} |" for name, us, calls in rows[:top]]
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=90)
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--backend", default="gpu")
    parser.add_argument("--top", type=int, default=8)
    parser.add_argument("--samples", type=int, default=50,
                        help="closed-loop samples per network (0: no closed loop)")
    parser.add_argument("--chunks", type=int, default=2,
                        help="closed-loop chunks of 500 steps profiled (one tangent)")
    args = parser.parse_args()
    fns, backend = trainers("lissajous2", args.runs, args.backend, device=args.device)
    cuda = backend.device.startswith("cuda")
    counts = {phase: (args.epochs, "epoch") for phase in fns}
    if args.samples:
        loop, _ = closed_loop(args.runs, args.samples, 1, args.backend, args.device)
        fns["closed loop, one tangent"] = lambda n: loop(500 * n)
        counts["closed loop, one tangent"] = (args.chunks, "chunk of 500 steps")
    for phase, fn in fns.items():
        warm_up(fn, 1, 1)  # (the closed loop's chunk lengths: every call 500 · n steps)
        epochs, per = counts[phase]
        wall, device, host = profiled(fn, epochs, cuda)
        print(f"\n{phase}, {args.runs} networks: {wall:.2f} ms wall per {per} (profiled); "
              f"device busy {sum(r[1] for r in device) / 1e3:.2f} ms in "
              f"{sum(r[2] for r in device):.0f} kernels and copies; host operators "
              f"{sum(r[1] for r in host) / 1e3:.2f} ms in {sum(r[2] for r in host):.0f} calls")
        if device:
            print(table(device, "on the device", args.top, per))
        print(table(host, "on the host (self CPU time)", args.top, per))


if __name__ == "__main__":
    main()
