"""moex's cpu backend against the authors' C tools (mregn's mre-learn and gn-learn), per network
and epoch, on one data file, one thread each, in one sitting: the ratio table of BENCHMARKS.md.

    python benchmarks/bench_vs_mregn.py <mregn checkout> [--runs 1 30] [--steps 100] [--repeats 3]

The tools are built from the checkout you name (`tools/build_mregn.sh`, into a temporary folder;
their code is never copied into moex). Both sides train on moex's two-Lissajous data (task
lissajous2, data seed 0: 10 series x 1000 steps, 2 experts of 10 units, a gating RNN of 15),
written in the tools' target format. Each figure is the marginal CPU time of an epoch: a training
of `--base` + `--steps` epochs minus one of `--base` epochs (so start-up, reading and writing
files are left out); moex's side trains through the whole training loop (`bench_epochs`). The
`--repeats` rounds take C and moex in turn, cell by cell, and each round gives a ratio: on a
shared machine whose speed drifts from minute to minute, a ratio of two measurements taken one
after the other holds where two separately measured minima do not. C: OMP_NUM_THREADS=1; moex:
1 numba thread.
"""

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_epochs import marginal, ratios, trainers, warm_up

from moex.config import Config
from moex.data import load_task
from moex.mregn_format import write_targets
from moex.tasks import task_config

ROOT = Path(__file__).resolve().parent.parent
# the paper's settings (Sec. 3.2.1), as studies/mregn_control.py trains Table 2's control
PHASE1 = "{bin}/mre-learn -s 1 -z 2 -n 10 -t 5 -d 1 -k 1 -g 10 -e {epochs} -x 0.01 -m 0.9 " \
         "-l {epochs} -o mre.dat {data}"
PHASE2 = "{bin}/gn-learn -s 1 -n 15 -t 25 -e {epochs} -x 0.01 -m 0.9 -a -l {epochs} -o gn.dat " \
         "start.dat"


def _cpu_seconds(command: str, cwd: Path) -> float:
    """CPU time (user + system) of one finished run of `command`."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(command.split(), cwd=cwd, check=True, stdout=subprocess.DEVNULL,
                   env={**os.environ, "OMP_NUM_THREADS": "1"})
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def c_epoch_ms(template: str, steps: int, base: int, **fields) -> float:
    """Marginal CPU ms per epoch of one of the tools, from one pair of runs."""
    short = _cpu_seconds(template.format(epochs=base, **fields), fields["cwd"])
    long = _cpu_seconds(template.format(epochs=base + steps, **fields), fields["cwd"])
    return 1e3 * (long - short) / steps


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkout", type=Path, help="a checkout of github.com/jnamika/mregn")
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 30])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--base", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    templates = {"phase 1, fixed rate": PHASE1, "phase 1, adaptive rate":
                 PHASE1.replace(" -o ", " -a -o "), "phase 2, adaptive rate": PHASE2}
    c_ms = {phase: [] for phase in templates}
    moex_ms = {(phase, runs): [] for phase in templates for runs in args.runs}
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        built = subprocess.run(["bash", str(ROOT / "tools" / "build_mregn.sh"),
                                str(args.checkout), str(work / "bin")], capture_output=True,
                               text=True)
        if built.returncode:
            print(f"bench_vs_mregn: building the tools failed:\n{built.stderr}", file=sys.stderr)
            return 2
        data = load_task(Config(task=task_config("lissajous2")))
        target = write_targets(work / "data.txt", data.series, "moex lissajous2, data seed 0")
        fields = dict(bin=work / "bin", data=target, cwd=work)
        subprocess.run(PHASE1.format(epochs=10, **fields).replace("mre.dat", "start.dat").split(),
                       cwd=work, check=True, stdout=subprocess.DEVNULL)
        moex = {runs: trainers("lissajous2", runs, "cpu")[0]
                for runs in args.runs}
        for fns in moex.values():  # compile (or load) every kernel at the timed sizes first
            for fn in fns.values():
                warm_up(fn, args.steps, args.base)
        for _ in range(args.repeats):  # C and moex in turn, so that a drift hits both
            for phase, template in templates.items():
                c_ms[phase].append(c_epoch_ms(template, args.steps, args.base, **fields))
                for runs in args.runs:
                    moex_ms[(phase, runs)].append(
                        1e3 * marginal(moex[runs][phase], args.steps, args.base)[1] / runs)
    print(f"# {os.uname().nodename}, {os.cpu_count()} CPUs; C: gcc -O2 -fopenmp, 1 thread; "
          f"moex: cpu backend, float64, 1 thread, MOEX_CPU_SIZES="
          f"{os.environ.get('MOEX_CPU_SIZES', 'compiled')}; {args.repeats} rounds, C and moex in "
          f"turn")
    head = " | ".join(f"moex R = {r} | C / moex R = {r}" for r in args.runs)
    print(f"\n| work | C ms | {head} |\n|---|---|" + "---|---|" * len(args.runs))
    for phase, c in c_ms.items():
        cells = " | ".join(
            f"{statistics.median(moex_ms[(phase, r)]):.2f} | "
            f"{ratios(c, moex_ms[(phase, r)], 1, 'x')}"
            for r in args.runs)
        print(f"| {phase} | {statistics.median(c):.2f} | {cells} |")
    print("\nmedians over the rounds; a ratio is the median (min-max) of the rounds' ratios, each "
          "of a C and a moex measurement taken one after the other")
    return 0


if __name__ == "__main__":
    sys.exit(main())
