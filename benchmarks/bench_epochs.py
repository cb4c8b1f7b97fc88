"""CPU time per network-epoch of both training phases, through the whole training loop
(`train_experts` / `train_gating`: kernel calls, momentum update, adaptive retries).

Two-Lissajous sizes: 10 series x 1000 steps, N = 2 experts, M = 10, M_g = 15, τ = 1; Reber sizes
(--task reber): 4 series x 500 symbols, phase 2 only, NC from --context-sizes.

    python benchmarks/bench_epochs.py --runs 1 30 --threads 1 2
    python benchmarks/bench_epochs.py --task reber --context-sizes 20 50 --runs 50 --threads 1
    python benchmarks/bench_epochs.py --backends gpu --device cuda --runs 90 900 --threads 1
    python benchmarks/bench_epochs.py --runs 1 30 --threads 1 --dtype float64 float32 --repeats 6

Each number is the marginal cost of an epoch (a run of 5 + --steps epochs minus a run of 5, so
the set-up of a training call is left out), the best of --repeats such pairs after a warm-up
(compilation), per network (divided by R). CPU time is process time (user + system, all
threads), so with 2 threads it shows the cost and the wall time shows the speed-up. On more
than one thread (cpu) a step's calls go to its stepper's crew (`moex.kernels.cpu.threads.Crew`),
whose loop the warm-up compiles, as a training compiles it for a phase of `step.LONG` seconds or
more (a shorter phase's calls go through the pool unless numba's cache holds the loop).

With two --dtype (cpu): both precisions' trainers in one process, each phase timed in both in
turn, --repeats rounds, each round a pair (`marginal`, CPU time) and a ratio: the medians and the
ratio's median (min-max). Separate processes' best times swung by a fifth within minutes on a
shared VM; a pair's two sides see the same minute.

With --threads 1 N and --paired (cpu): the same, for one set of trainers run on one thread and on N
in turn (`numba.set_num_threads` between the runs): wall ms per network-epoch on each, the
speed-up (one thread's wall time over N's) as median (min-max) and as the ratio of the two sides'
best rounds, and N threads' CPU time over one's (what the threads cost in all). And a control
timed in the same rounds: the same networks as N separate trainings (R / N runs each, one thread
each) all at once, which share nothing but the machine: their speed-up over one thread is what
this machine gives N threads of this work at that minute, and N threads' speed-up over theirs
shows what the kernels' threads lose to each other (the handoffs, the chunks' balance, the
stages on one thread). On the 2-vCPU AMD EPYC VM the machine's own two-thread rate moved from
1.0x to 2.0x within minutes (`bench_peak.py`'s last line: FMA chains on two threads at once), and
a round's two sides then swung by a fifth or more. Contention only adds time, so each side's best
round is the nearest to its uncontended time; the N-thread side needs every vCPU free at once
and reaches it less often, so the best rounds' ratio errs low.

    python benchmarks/bench_epochs.py --runs 30 --threads 1 2 --paired --steps 40 --repeats 6
"""

import argparse
import gc
import itertools
import os
import statistics
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial

import numba
import torch

from moex.config import Config
from moex.data import load_task
from moex.jobs import run_seeds
from moex.kernels import Backend, get_backend
from moex.kernels.cpu import step
from moex.model import init_experts, init_gating
from moex.tasks import task_config
from moex.train import train_experts, train_gating


def _clock(fn, steps: int, sync: bool) -> tuple[float, float]:
    """(wall, cpu) seconds of fn(steps), Python's cyclic garbage collector paused (as `timeit`
    does): a full collection takes ~0.14 s here, more than 5 epochs, and made a pair's marginal
    time negative now and then."""
    gc.collect()
    gc.disable()
    try:
        start, start_cpu = time.perf_counter(), time.process_time()
        fn(steps)
        if sync:
            torch.cuda.synchronize()
        return time.perf_counter() - start, time.process_time() - start_cpu
    finally:
        gc.enable()


def warm_up(fn, steps: int, base: int) -> None:
    """Both lengths once, so that every kernel is compiled (or loaded from the cache) at the
    timed sizes, and the allocator has seen them. Not for a backend in Triton's interpreter
    (`Capabilities.interpreted`): it compiles nothing, and its epochs take seconds."""
    fn(base)
    fn(base + steps)


def marginal(fn, steps: int, base: int, sync: bool = False) -> tuple[float, float]:
    """(wall, cpu) seconds per epoch from one pair: (time of base + steps epochs - time of base
    epochs) / steps, which leaves out the set-up of a training call."""
    short, long = _clock(fn, base, sync), _clock(fn, base + steps, sync)
    return (long[0] - short[0]) / steps, (long[1] - short[1]) / steps


def outside_pairs(fn, targets: list[tuple[object, str]], steps: int, base: int, repeats: int
                  ) -> list[tuple[float, float]]:
    """`repeats` pairs (epoch, outside) of seconds per epoch of `fn(n)` (n epochs) after
    `warm_up`: marginal, `base + steps` epochs minus `base`, and of that the time outside the
    calls of each `owner.<name>` of `targets` (wrapped while this runs; a call inside another
    counts once, in the outer one). Each epoch's own calls are subtracted, not the least of many
    calls: an epoch's time includes all of the machine's jitter."""
    inside, depth, calls = [0.0], [0], [getattr(owner, name) for owner, name in targets]

    def timer(call):
        def timed(*args):
            if depth[0]:
                return call(*args)
            depth[0], start = 1, time.perf_counter()
            try:
                return call(*args)
            finally:
                inside[0] += time.perf_counter() - start
                depth[0] = 0
        return timed

    def clocked(n: int) -> tuple[float, float]:
        inside[0] = 0.0
        wall = _clock(fn, n, False)[0]
        return wall, wall - inside[0]

    for (owner, name), call in zip(targets, calls, strict=True):
        setattr(owner, name, timer(call))
    try:
        warm_up(fn, steps, base)
        pairs = []
        for _ in range(repeats):
            (short, short_out), (long, long_out) = clocked(base), clocked(base + steps)
            pairs.append(((long - short) / steps, (long_out - short_out) / steps))
        return pairs
    finally:
        for (owner, name), call in zip(targets, calls, strict=True):
            setattr(owner, name, call)


def _time(fn, steps: int, repeats: int, base: int = 5, sync: bool = False, warm: bool = True
          ) -> tuple[float, float]:
    """(wall, cpu) seconds per epoch (`marginal`), the best of `repeats` pairs after `warm_up`
    (none where not `warm`)."""
    if warm:
        warm_up(fn, steps, base)
    pairs = [marginal(fn, steps, base, sync) for _ in range(repeats)]
    return min(p[0] for p in pairs), min(p[1] for p in pairs)


def ratios(a: list[float], b: list[float], digits: int = 2, unit: str = "") -> str:
    """The rounds' ratios a / b, paired round by round, as "median (min-max)"."""
    r = [x / y for x, y in zip(a, b, strict=True)]
    return f"{statistics.median(r):.{digits}f}{unit} ({min(r):.{digits}f}-{max(r):.{digits}f})"


def gate_targets(runs: int, S: int, T: int, K: int) -> torch.Tensor:
    """(runs, S, T, K) random ĝ (softmax of normal draws, seed 0): phase 2's targets where the
    task has no gate targets of its own."""
    return torch.softmax(torch.randn(runs, S, T, K, generator=torch.Generator().manual_seed(0)),
                         -1)


def trainers(task: str, runs: int, backend: str, *, threads: int = 1, context_size: int = 15,
             dtype: str = "float64", device: str = "cpu", series: int = 0,
             length: int = 0, noise: float = 0.0, phases: tuple = ()) -> tuple[dict, Backend]:
    """{phase name: fn(n) training n epochs of `runs` networks} and the backend they train on
    (`moex.kernels.Backend`); `series` and `length` (0: the task's) shrink the data; `noise`:
    phase 2's input noise variance (`train.gating.input_noise_var`, named in the phase's name);
    `phases`: only the phases whose names contain one of these (all where empty)."""
    chosen = get_backend(backend, device if backend != "cpu" else "cpu")
    # the compiled kernels' threads do the parallel work (`moex.kernels.cpu.threads`); every
    # phase counts as long (`step.LONG`): its stepper's crew loop is compiled in the warm-up, as
    # a training's phase of 5 minutes or more compiles it (or loads it from the cache)
    torch.set_num_threads(1 if chosen.name == "cpu" else threads)
    step.LONG = 0.0
    numba.set_num_threads(threads)
    cfg = Config(task=task_config(task))
    if task == "reber":
        cfg.task.num_series, cfg.task.length = 4, 500
        cfg.model.num_experts, cfg.model.gating.epsilon = 7, 0.1
    cfg.task.num_series = series or cfg.task.num_series
    cfg.task.length = length or cfg.task.length
    cfg.model.gating.context_size = context_size
    cfg.train.gating.input_noise_var = noise
    dtype = getattr(torch, dtype)
    data = load_task(cfg)
    series = torch.as_tensor(data.series, dtype=dtype)
    S, _, D = series.shape
    gens = [torch.Generator().manual_seed(s) for s in run_seeds(0, runs)]
    out = {}
    if D > 0:
        experts = init_experts(cfg.model, S, D, gens, dtype)
        for adaptive in (False, True):
            def phase1(n, adaptive=adaptive):
                cfg.train.experts.steps, cfg.train.experts.adaptive_lr = n, adaptive
                train_experts(experts, series, cfg.model, cfg.train.experts, cfg.train,
                              backend=chosen)

            out[f"phase 1, {'adaptive' if adaptive else 'fixed'} rate"] = phase1
        targets = gate_targets(runs, S, series.shape[1] - 1, 2)
        inputs = series[:, :-1]
    else:
        targets = torch.as_tensor(data.gate_targets, dtype=dtype).expand(runs, -1, -1, -1)
        inputs = series
    gating = init_gating(cfg.model, S, D, gens, dtype)

    def phase2(n):
        cfg.train.gating.steps = n
        train_gating(gating, targets.to(dtype), inputs, cfg.model, cfg.train.gating, rule=cfg.train,
                     backend=chosen)

    out["phase 2, adaptive rate" + (f", input noise {noise:g}" if noise else "")] = phase2
    return {k: fn for k, fn in out.items() if not phases or any(p in k for p in phases)}, chosen


def bench(task: str, runs: int, backend: str, *, threads: int, steps: int, repeats: int,
          context_size: int, dtype: str, device: str = "cpu", series: int = 0,
          length: int = 0, base: int = 5, noise: float = 0.0, phases: tuple = ()) -> list[dict]:
    """Rows of ms per network-epoch (`trainers` for the arguments)."""
    fns, chosen = trainers(task, runs, backend, threads=threads, context_size=context_size,
                           dtype=dtype, device=device, series=series, length=length,
                           noise=noise, phases=phases)
    results = []
    for name, fn in fns.items():
        wall, cpu = _time(fn, steps, repeats, base, chosen.device.startswith("cuda"),
                          warm=not chosen.caps.interpreted)
        results.append({"task": task, "phase": name, "runs": runs, "backend": backend,
                        "threads": threads, "context_size": context_size,
                        "wall_ms": 1e3 * wall / runs, "cpu_ms": 1e3 * cpu / runs})
        print(f"| {task} | {name} | {runs} | {backend} | {threads} | {context_size} | "
              f"{1e3 * cpu / runs:.2f} | {1e3 * wall / runs:.2f} |", flush=True)
    return results


def rounds(sides: list[tuple], steps: int, base: int, repeats: int) -> list[list[tuple]]:
    """Per side (prepare, fn): `repeats` pairs (`marginal`: wall, cpu seconds per epoch) of
    fn(n) (n epochs), prepare() called before each, all sides warmed up first and then timed in
    turn, round by round, the order alternating."""
    for prepare, fn in sides:
        prepare()
        warm_up(fn, steps, base)
    times = [[] for _ in sides]
    for round_ in range(repeats):
        for i in range(len(sides))[::-1 if round_ % 2 else 1]:
            prepare, fn = sides[i]
            prepare()
            times[i].append(marginal(fn, steps, base))
    return times


def dtype_pairs(task: str, runs: int, *, threads: int, steps: int, repeats: int,
                context_size: int, dtypes: list[str], base: int = 5, noise: float = 0.0,
                phases: tuple = ()) -> None:
    """Prints a row per phase: CPU ms per network-epoch in each of two precisions, medians of
    `repeats` rounds that time both in turn (`rounds`), and their ratio round by round."""
    fns = {d: trainers(task, runs, "cpu", threads=threads, context_size=context_size,
                       dtype=d, noise=noise, phases=phases)[0] for d in dtypes}
    for name in fns[dtypes[0]]:
        a, b = ([1e3 * cpu / runs for _, cpu in side] for side in rounds(
            [(lambda: None, fns[d][name]) for d in dtypes], steps, base, repeats))
        print(f"| {task} | {name} | {runs} | {threads} | {context_size} | "
              f"{statistics.median(a):.2f} | {statistics.median(b):.2f} | {ratios(a, b)} |",
              flush=True)


def thread_pairs(task: str, runs: int, *, threads: int, steps: int, repeats: int,
                 context_size: int, dtype: str, base: int = 5, noise: float = 0.0,
                 phases: tuple = ()) -> None:
    """Prints a row per phase: wall ms per network-epoch on one thread and on `threads`, medians
    of `repeats` rounds that time each side in turn (`rounds`); the speed-up and the CPU time ratio
    round by round, and the speed-up of the two sides' best rounds; and the control: the same
    `runs` networks as `threads` separate trainings of a part of the runs each, one thread each,
    all at once (`at_once`): their speed-up over one thread, and the threads' speed-up over
    theirs, round by round."""
    parts = [trainers(task, runs * (i + 1) // threads - runs * i // threads, "cpu", threads=1,
                      context_size=context_size, dtype=dtype, noise=noise, phases=phases)[0]
             for i in range(threads)]
    fns, _ = trainers(task, runs, "cpu", threads=threads, context_size=context_size,
                      dtype=dtype, noise=noise, phases=phases)
    with ThreadPoolExecutor(threads) as pool:
        for name, fn in fns.items():
            sides = [(partial(numba.set_num_threads, t), fn) for t in (1, threads)]
            sides.append((lambda: None, at_once(pool, [part[name] for part in parts])))
            timed = rounds(sides, steps, base, repeats)
            one, many, apart = ([1e3 * w / runs for w, _ in side] for side in timed)
            cpu = [[c for _, c in side] for side in timed]
            print(f"| {task} | {name} | {runs} | {context_size} | {statistics.median(one):.2f} | "
                  f"{statistics.median(many):.2f} | {ratios(one, many, unit='x')} | "
                  f"{min(one) / min(many):.2f}x | {ratios(cpu[1], cpu[0])} | "
                  f"{ratios(one, apart, unit='x')} | {ratios(apart, many)} |", flush=True)


def at_once(pool: ThreadPoolExecutor, fns: list):
    """fn(n): each of `fns` trains n epochs on a thread of `pool` of its own, one kernel thread
    each (`numba.set_num_threads` is per thread), all at once; returns when all are done."""
    def train(fn, n):
        numba.set_num_threads(1)
        fn(n)

    def fn(n):
        list(pool.map(train, fns, [n] * len(fns)))
    return fn


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="lissajous2", choices=["lissajous2", "reber"])
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 30])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--backends", nargs="+", default=["cpu"])
    parser.add_argument("--device", default="cpu", help="for reference and gpu: cpu or cuda")
    parser.add_argument("--context-sizes", type=int, nargs="+", default=[15])
    parser.add_argument("--dtype", nargs="+", default=["float64"], choices=["float64", "float32"],
                        help="two: both in one process, paired round by round (cpu)")
    parser.add_argument("--series", type=int, default=0, help="series per network (0: task's)")
    parser.add_argument("--length", type=int, default=0, help="steps per series (0: task's)")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--base", type=int, default=5, help="epochs of the subtracted run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--noise", type=float, default=0.0,
                        help="phase 2's input noise variance (train.gating.input_noise_var)")
    parser.add_argument("--phases", nargs="+", default=[],
                        help="only the phases whose names contain one of these (default: all)")
    parser.add_argument("--kernels", action="store_true",
                        help="then print each compiled Triton kernel's registers and spills")
    parser.add_argument("--paired", action="store_true",
                        help="two --threads in one process, paired round by round (cpu)")
    args = parser.parse_args()
    if args.paired and (len(args.threads) != 2 or args.threads[0] != 1 or len(args.dtype) != 1
                        or args.backends != ["cpu"]):
        parser.error("--paired takes two --threads, the first 1, one --dtype and the cpu backend")
    if args.paired and min(args.runs) < args.threads[1]:
        parser.error(f"--paired --runs {min(args.runs)}: at least one run per thread "
                     f"({args.threads[1]})")
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "no GPU"
    print(f"# {os.uname().nodename}, {gpu}, {os.cpu_count()} CPUs; {' and '.join(args.dtype)}"
          + (f"; phase 2 with input noise of variance {args.noise:g}" if args.noise else ""))
    if args.paired:
        second = args.threads[1]
        print(f"| task | phase | runs | NC | wall ms per network-epoch, 1 thread | {second} "
              f"threads | speed-up | best round over best round | CPU time, {second} / 1 | "
              f"{second} trainings at once: speed-up | {second} threads over them |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|")
        for runs, size in itertools.product(args.runs, args.context_sizes):
            thread_pairs(args.task, runs, threads=second, steps=args.steps, repeats=args.repeats,
                         context_size=size, dtype=args.dtype[0], base=args.base,
                         noise=args.noise, phases=tuple(args.phases))
        return
    if len(args.dtype) == 2:
        first, second = args.dtype
        print(f"| task | phase | runs | threads | NC | CPU ms per network-epoch, {first} | "
              f"{second} | {first} / {second} |\n|---|---|---|---|---|---|---|---|")
        for runs, threads, size in itertools.product(args.runs, args.threads, args.context_sizes):
            dtype_pairs(args.task, runs, threads=threads, steps=args.steps, repeats=args.repeats,
                        context_size=size, dtypes=args.dtype, base=args.base, noise=args.noise,
                        phases=tuple(args.phases))
        return
    print("| task | phase | runs | backend | threads | NC | CPU ms per network-epoch | "
          "wall ms per network-epoch |")
    print("|---|---|---|---|---|---|---|---|")
    for runs in args.runs:
        for backend in args.backends:
            for threads in args.threads:
                for size in args.context_sizes:
                    bench(args.task, runs, backend, threads=threads, steps=args.steps,
                          repeats=args.repeats, context_size=size, dtype=args.dtype[0],
                          device=args.device, series=args.series, length=args.length,
                          base=args.base, noise=args.noise, phases=tuple(args.phases))
    if args.kernels:
        print_kernels()


def print_kernels() -> None:
    """Registers, spills and warps of every Triton kernel this process compiled (CUDA only)."""
    from moex.kernels import available

    gpu, why = available("gpu")
    rows = gpu.module.kernel_report() if gpu is not None else []
    print("| kernel | registers | spills | warps |\n|---|---|---|---|")
    for row in rows:
        print(f"| {row['kernel']} | {row['registers']} | {row['spills']} | {row['num_warps']} |")
    if not rows:
        print(f"| (none compiled: {why or 'the kernels ran in Triton' + chr(39) + 's interpreter'})"
              " | | | |")


if __name__ == "__main__":
    main()
