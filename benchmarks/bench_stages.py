"""Where a training step's wall time goes on the cpu backend, stage by stage, on one and on two
threads: each call the stepper (`moex.kernels.cpu.step`) and the problems' `evaluate` make — the
chunks or blocks the threads share (`threads.share`), the update's stages over the runs
(`threads.over`, or one thread below `threads.SPLIT`), the run sums and σ² on the calling thread —
timed from the calling thread, per training step (the marginal cost: `base + steps` epochs
minus `base`), and what is left (the training loop's Python). Two-Lissajous sizes at --runs
networks (`bench_epochs.trainers`).

    python benchmarks/bench_stages.py --runs 30 --threads 1 2
    python benchmarks/bench_stages.py --runs 30 --threads 1 --dtype float32 --phases adaptive

A stage whose time does not halve on two threads is where a two-thread step loses its speed-up
(memory-bound passes, a thread waiting): BENCHMARKS.md quotes these rows. The last row is the
speed-up the code allows (Amdahl's law): the first thread count's step with its threads' calls
divided among t threads and the rest (one thread's stages, the loop's Python) as it was. A
machine whose second core is busy with other work falls short of it; the code cannot exceed it.
"""

import argparse
import functools
import threading
import time
from collections import Counter, defaultdict

import numba
from bench_epochs import _clock, trainers, warm_up

from moex.kernels.cpu import phases, threads

THREADED = ("shared by the threads", "over the threads")  # the stages the threads divide
_time: defaultdict = defaultdict(float)
_calls: Counter = Counter()
_inside = [False]  # a call inside a timed call counts once, in the outer one


def _name(kernel) -> str:
    kernel = getattr(kernel, "func", kernel)  # (a functools.partial)
    return getattr(kernel, "__name__", type(kernel).__name__)


def _timed(label: str, call, named: bool):
    """`call` timed under "label: kernel name" (`named`: its first argument is the kernel) where
    the calling thread makes it outside another timed call."""
    @functools.wraps(call)  # (its name: a wrapped kernel handed to `share` is named by it)
    def timed(*args):
        if _inside[0] or threading.current_thread() is not threading.main_thread():
            return call(*args)
        _inside[0], start = True, time.perf_counter()
        try:
            return call(*args)
        finally:
            key = f"{label}: {_name(args[0]) if named else _name(call)}"
            _time[key] += time.perf_counter() - start
            _calls[key] += 1
            _inside[0] = False
    return timed


def install() -> None:
    """Wraps the stages (after a warm-up: a kernel compiled while its own name is wrapped would
    call the wrapper in its recursion)."""
    threads.over = _timed("over the threads", threads.over, True)
    threads.share = _timed("shared by the threads", threads.share, True)
    threads.one = _timed("one thread", threads.one, True)
    for name in ("_expert_items", "gating_items", "_variances"):
        setattr(phases, name, _timed("calling thread", getattr(phases, name), False))


def stages(fn, steps: int, base: int) -> tuple[float, dict]:
    """(wall ms per step, {stage: (ms per step, calls per step)}) of fn(base + steps) minus
    fn(base)."""
    results = []
    for n in (base, base + steps):
        _time.clear()
        _calls.clear()
        wall = _clock(fn, n, False)[0]
        results.append((wall, dict(_time), dict(_calls)))
    (wall0, time0, calls0), (wall1, time1, calls1) = results
    rows = {k: ((time1[k] - time0.get(k, 0.0)) / steps * 1e3,
                (calls1[k] - calls0.get(k, 0)) / steps) for k in time1}
    return (wall1 - wall0) / steps * 1e3, rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--base", type=int, default=5)
    parser.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    parser.add_argument("--phases", nargs="+", default=["fixed", "adaptive", "phase 2"],
                        help="the phases whose names contain one of these")
    parser.add_argument("--series", type=int, default=0, help="fewer series (0: the task's)")
    parser.add_argument("--length", type=int, default=0, help="shorter series (0: the task's)")
    args = parser.parse_args()
    counts = [t for t in args.threads if t <= numba.config.NUMBA_NUM_THREADS]
    if counts != args.threads:
        parser.error(f"--threads {args.threads}: this machine runs at most "
                     f"{numba.config.NUMBA_NUM_THREADS}")
    fns = {t: trainers("lissajous2", args.runs, "cpu", threads=t, dtype=args.dtype,
                       series=args.series, length=args.length)[0] for t in counts}
    names = [n for n in fns[counts[0]] if any(p in n for p in args.phases)]
    for fn in (fns[t][n] for t in counts for n in names):
        numba.set_num_threads(counts[0])
        warm_up(fn, args.steps, args.base)
    install()
    print(f"# {args.runs} networks, {args.dtype}; ms per training step (marginal of "
          f"{args.base} + {args.steps} over {args.base} epochs), calls per step")
    for name in names:
        measured = {}
        for t in counts:
            numba.set_num_threads(t)
            measured[t] = stages(fns[t][name], args.steps, args.base)
        keys = sorted({k for t in counts for k in measured[t][1]},
                      key=lambda k: -measured[counts[0]][1].get(k, (0.0, 0))[0])
        print(f"\n## {name}\n")
        print("| stage | " + " | ".join(f"{t} thread(s): ms (calls)" for t in counts) + " |")
        print("|---|" + "---|" * len(counts))
        for k in keys:
            cells = [measured[t][1].get(k, (0.0, 0.0)) for t in counts]
            print(f"| {k} | " + " | ".join(f"{ms:.3f} ({n:.2f})" for ms, n in cells) + " |")
        outside = [measured[t][0] - sum(ms for ms, _ in measured[t][1].values()) for t in counts]
        print("| the rest (the training loop's Python) | "
              + " | ".join(f"{ms:.3f}" for ms in outside) + " |")
        print("| **a step** | " + " | ".join(f"**{measured[t][0]:.3f}**" for t in counts) + " |")
        step, rows = measured[counts[0]]
        shared = sum(ms for k, (ms, _) in rows.items() if k.startswith(THREADED))
        print(f"| speed-up at best (the threads' calls of {counts[0]} thread(s) divided, the rest "
              "as it is) | " + " | ".join(
                  f"{step / (step - shared + shared * counts[0] / t):.2f}x" for t in counts)
              + " |")


if __name__ == "__main__":
    main()
