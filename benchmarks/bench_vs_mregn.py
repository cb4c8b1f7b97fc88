"""moex's cpu backend against the authors' C tools (mregn's mre-learn and gn-learn), per network
and epoch, on one data file, one thread each, in one sitting: the ratio table of BENCHMARKS.md.

    python benchmarks/bench_vs_mregn.py <mregn checkout> [--runs 1 30] [--steps 100] [--repeats 3]

The tools are built from the checkout you name (`tools/build_mregn.sh`, into a temporary folder;
their code is never copied into moex). Both sides train on moex's two-Lissajous data (task
lissajous2, data seed 0: 10 series x 1000 steps, 2 experts of 10 units, a gating RNN of 15),
written in the tools' target format. Each figure is the marginal CPU time of an epoch: a training
of `--base` + `--steps` epochs minus one of `--base` epochs (so start-up, reading and writing
files are left out), the best of `--repeats` pairs; moex's side is `bench_epochs.bench` (through
the whole training loop). C: OMP_NUM_THREADS=1; moex: 1 numba thread.
"""

import argparse
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_epochs import bench

from moex.config import Config
from moex.mregn_format import write_targets
from moex.pipeline import load_task
from moex.tasks import TaskConfig

ROOT = Path(__file__).resolve().parent.parent
# the paper's settings (Sec. 3.2.1), as docs/mregn_control.py trains Table 2's control
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


def c_epoch_ms(template: str, steps: int, base: int, repeats: int, **fields) -> float:
    """Marginal CPU ms per epoch of one of the tools (the best of `repeats` pairs)."""
    best = float("inf")
    for _ in range(repeats):
        short = _cpu_seconds(template.format(epochs=base, **fields), fields["cwd"])
        long = _cpu_seconds(template.format(epochs=base + steps, **fields), fields["cwd"])
        best = min(best, (long - short) / steps)
    return 1e3 * best


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkout", type=Path, help="a checkout of github.com/jnamika/mregn")
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 30])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--base", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        built = subprocess.run(["bash", str(ROOT / "tools" / "build_mregn.sh"),
                                str(args.checkout), str(work / "bin")], capture_output=True,
                               text=True)
        if built.returncode:
            print(f"bench_vs_mregn: building the tools failed:\n{built.stderr}", file=sys.stderr)
            return 2
        data = load_task(Config(task=TaskConfig(name="lissajous2")))
        target = write_targets(work / "data.txt", data.series, "moex lissajous2, data seed 0")
        fields = dict(bin=work / "bin", data=target, cwd=work)
        c = {"phase 1, fixed rate": c_epoch_ms(PHASE1, args.steps, args.base, args.repeats,
                                               **fields),
             "phase 1, adaptive rate": c_epoch_ms(PHASE1.replace(" -o ", " -a -o "), args.steps,
                                                  args.base, args.repeats, **fields)}
        subprocess.run(PHASE1.format(epochs=10, **fields).replace("mre.dat", "start.dat").split(),
                       cwd=work, check=True, stdout=subprocess.DEVNULL)
        c["phase 2, adaptive rate"] = c_epoch_ms(PHASE2, args.steps, args.base, args.repeats,
                                                 **fields)
    print(f"# {os.uname().nodename}, {os.cpu_count()} CPUs; C: gcc -O2 -fopenmp, 1 thread; "
          f"moex: cpu backend, float64, 1 thread")
    moex = {}
    for runs in args.runs:
        for row in bench("lissajous2", runs, "cpu", 1, args.steps, args.repeats, 15, "float64",
                         base=args.base):
            moex[(row["phase"], runs)] = row["cpu_ms"]
    head = " | ".join(f"moex R = {r} | C / moex R = {r}" for r in args.runs)
    print(f"\n| work | C ms | {head} |\n|---|---|" + "---|---|" * len(args.runs))
    for phase, c_ms in c.items():
        cells = " | ".join(f"{moex[(phase, r)]:.2f} | {c_ms / moex[(phase, r)]:.1f}x"
                           for r in args.runs)
        print(f"| {phase} | {c_ms:.2f} | {cells} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
