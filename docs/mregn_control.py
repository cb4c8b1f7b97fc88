"""The authors' own C tools (mregn, rnn-learn) as a control: trained on moex's data files at the
paper's settings, then imported into moex run folders (`moex import`) and scored by moex.

    python docs/mregn_control.py run <bin folder> <out folder> [--networks 20] [--workers 2]

<bin folder> holds the tools built by `bash tools/build_mregn.sh <mregn checkout> <bin folder>`.
Each network trains in <out>/<design>/net<seed>/ and is skipped once its `done` file exists, so
the same command resumes. Designs (paper Secs. 3.1, 3.2.1; the data of moex's seed-0 runs):
  reber_nc20, reber_nc30: rnn-learn, 4 x 500 Reber symbols, NC 20/30, tau 10, rho 0.01, adaptive
  table2_p05, table2_p025: mre-learn (2 experts x 10 units, tau 5, gamma 10, 30000 epochs,
      rho 0.01) then gn-learn (15 units, tau 25, 10000 epochs, rho 0.01, adaptive)
"""

import argparse
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import yaml

from moex.config import CONF_DIR
from moex.mregn_format import write_targets
from moex.tasks import TaskConfig, make_task

DESIGNS = {  # name: (task overrides, commands with {bin}, {seed}, {data})
    "reber_nc20": ({"name": "reber", "num_series": 4, "length": 500}, [
        "{bin}/rnn-learn -s {seed} -n 20 -t 10 -k 1 -d 1 -e 10000 -x 0.01 -m 0.9 -a -l 1000 "
        "-o rnn.dat {data}"]),
    "reber_nc30": ({"name": "reber", "num_series": 4, "length": 500}, [
        "{bin}/rnn-learn -s {seed} -n 30 -t 10 -k 1 -d 1 -e 10000 -x 0.01 -m 0.9 -a -l 1000 "
        "-o rnn.dat {data}"]),
    "table2_p05": ({"name": "lissajous2", "switch_prob": 0.5}, [
        "{bin}/mre-learn -s {seed} -z 2 -n 10 -t 5 -d 1 -k 1 -g 10 -e 30000 -x 0.01 -m 0.9 "
        "-l 1000 -o mre.dat {data}",
        "{bin}/gn-learn -s {seed} -n 15 -t 25 -e 10000 -x 0.01 -m 0.9 -a -l 1000 -o gn.dat "
        "mre.dat"]),
    "table2_p025": ({"name": "lissajous2", "switch_prob": 0.25}, [
        "{bin}/mre-learn -s {seed} -z 2 -n 10 -t 5 -d 1 -k 1 -g 10 -e 30000 -x 0.01 -m 0.9 "
        "-l 1000 -o mre.dat {data}",
        "{bin}/gn-learn -s {seed} -n 15 -t 25 -e 10000 -x 0.01 -m 0.9 -a -l 1000 -o gn.dat "
        "mre.dat"]),
}


def data_file(design: str, out: Path) -> Path:
    """The design's training data (moex's seed-0 data set) as a C target file."""
    overrides, _ = DESIGNS[design]
    task_file = CONF_DIR / "task" / f"{overrides['name']}.yaml"  # the task's own sizes first
    own = yaml.safe_load(task_file.read_text())["task"]
    dataset = make_task(TaskConfig(**{**own, **overrides}), seed=0)
    series = dataset.series if dataset.gate_targets is None else dataset.gate_targets
    path = out / design / "data.txt"
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_targets(path, series, f"moex task {overrides}, data seed 0, shape "
                                       f"{series.shape}")


def train_one(design: str, seed: int, bin_dir: Path, out: Path) -> str:
    folder = out / design / f"net{seed:03d}"
    if (folder / "done").exists():
        return f"{folder}: done before"
    folder.mkdir(parents=True, exist_ok=True)
    started = time.time()
    for command in DESIGNS[design][1]:
        line = command.format(bin=bin_dir, seed=seed, data=(out / design / "data.txt").resolve())
        with open(folder / "tool.log", "a") as log:
            log.write(f"$ {line}\n")
            log.flush()
            code = subprocess.call(line.split(), cwd=folder, stdout=log, stderr=log)
        if code:
            return f"{folder}: {line.split()[0]} exited {code} (see tool.log)"
    (folder / "done").write_text(f"{time.time() - started:.1f} s\n")
    return f"{folder}: trained in {time.time() - started:.0f} s"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=["run"])
    parser.add_argument("bin", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--designs", nargs="+", default=list(DESIGNS), choices=list(DESIGNS))
    parser.add_argument("--networks", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    missing = [t for t in ("rnn-learn", "mre-learn", "gn-learn") if not (args.bin / t).is_file()]
    if missing:
        print(f"mregn_control: {args.bin} lacks {', '.join(missing)}; build them with bash "
              f"tools/build_mregn.sh <mregn checkout> {args.bin}", file=sys.stderr)
        return 2
    for design in args.designs:
        data_file(design, args.out)
    # seeds interleaved across designs, so that a cut-short run leaves every design similar n
    jobs = [(d, s) for s in range(1, args.networks + 1) for d in args.designs]
    with ThreadPoolExecutor(args.workers) as pool:
        for message in pool.map(lambda job: train_one(*job, args.bin.resolve(), args.out), jobs):
            print(message, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
