"""The authors' own C tools (mregn, rnn-learn) as a control: trained on moex's data files at the
paper's settings, then imported into moex run folders (`moex import`) and scored by moex.

    python -m studies.mregn_control run <bin folder> <out folder> [--networks 20] [--workers 2]

    python -m studies.mregn_control lyapunov <bin folder> <out folder>   # their own λ_max tool

    python -m studies.mregn_control compare <out folder>     # after `moex import` of each design

<bin folder> holds the tools built by `bash tools/build_mregn.sh <mregn checkout> <bin folder>`
(their Makefile's defines: "the C code's default build"); a design that needs another build
(`BUILDS`) finds it in <bin folder>/<build>/, and `run` names the command that builds it where it
is missing. Each network trains in <out>/<design>/net<seed>/ and is skipped once its `done` file
exists, so the same command resumes. Designs (paper Secs. 3.1, 3.2.1; the data of moex's seed-0
runs):
  reber_nc20, reber_nc30: rnn-learn, 4 x 500 Reber symbols, NC 20/30, tau 10, rho 0.01, adaptive
  reber_nc20_no_attraction: reber_nc20 built without the attraction of u0 (one factor changed)
  table2_p05, table2_p025: mre-learn (2 experts x 10 units, tau 5, gamma 10, 30000 epochs,
      rho 0.01) then gn-learn (15 units, tau 25, 10000 epochs, rho 0.01, adaptive); tau learned
      and the variance floor 0.001 (sigma floor 0.032), as the C code does by default
  table2_p05_paper, table2_p025_paper: the same at the paper's stated settings (Sec. 3.2.1):
      time constants fixed at epsilon 0.2 and epsilon^g 0.04 (their config key `fixed_tau`) and
      sigma floor 0.05 (MIN_VARIANCE 0.0025, compiled in)
`lyapunov` scores each trained network with the authors' own estimator at moex's evaluation
sizes (`LYAPUNOV`): a mixture (Table 2's designs) with `mregn-lyapunov`, 50 samples from random
initial states x 100 000 steps after 1000 transient ones; a Reber RNN with `rnn-lyapunov`, 200
samples x 10 000 steps after 1000. Each prints one sample's λ_max per line with 6 decimals, kept
in <net>/lyapunov.txt (skipped once there); the rows go to docs/mregn_control_lyapunov.csv.
"""

import argparse
import math
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import yaml

from moex.config import CONF_DIR
from moex.errors import check
from moex.mregn_format import write_targets
from moex.tasks import make_task, task_config
from studies.common import DOCS

_REBER = ("{bin}/rnn-learn -s {seed} -n NC -t 10 -k 1 -d 1 -e 10000 -x 0.01 -m 0.9 -a -l 1000 "
          "-o rnn.dat {data}")
_MIXTURE = ["{bin}/mre-learn -s {seed} -z 2 -n 10 -t 5 -d 1 -k 1 -g 10 -e 30000 -x 0.01 -m 0.9 "
            "-l 1000 {conf}-o mre.dat {data}",
            "{bin}/gn-learn -s {seed} -n 15 -t 25 -e 10000 -x 0.01 -m 0.9 -a -l 1000 {conf}"
            "-o gn.dat mre.dat"]
_REBER_TASK = {"name": "reber", "num_series": 4, "length": 500}
DESIGNS = {  # name: (task overrides, build, time constants fixed, commands with {bin}, {seed},
    #                 {data}, {conf})
    "reber_nc20": (_REBER_TASK, "default", False, [_REBER.replace("NC", "20")]),
    "reber_nc30": (_REBER_TASK, "default", False, [_REBER.replace("NC", "30")]),
    "reber_nc20_no_attraction": (_REBER_TASK, "no_attraction", False,
                                 [_REBER.replace("NC", "20")]),
    "table2_p05": ({"name": "lissajous2", "switch_prob": 0.5}, "default", False, _MIXTURE),
    "table2_p025": ({"name": "lissajous2", "switch_prob": 0.25}, "default", False, _MIXTURE),
    "table2_p05_paper": ({"name": "lissajous2", "switch_prob": 0.5}, "sigma05", True, _MIXTURE),
    "table2_p025_paper": ({"name": "lissajous2", "switch_prob": 0.25}, "sigma05", True,
                          _MIXTURE),
}
# build: the extra CFLAGS for tools/build_mregn.sh (gcc reads -D and -U in order, so -U undoes
# one of the Makefile's defines); each build but the default lives in <bin folder>/<build>/
BUILDS = {"default": [], "sigma05": ["-DMIN_VARIANCE=0.0025"],
          "no_attraction": ["-UENABLE_ATTRACTION_OF_INIT_C"]}


def build_dir(bin_dir: Path, design: str) -> Path:
    """Where a design's tools are: the default build in <bin folder>, any other in a subfolder."""
    build = DESIGNS[design][1]
    return bin_dir if build == "default" else bin_dir / build


def data_file(design: str, out: Path) -> Path:
    """The design's training data (moex's seed-0 data set) as a C target file."""
    overrides = DESIGNS[design][0]
    task_file = CONF_DIR / "task" / f"{overrides['name']}.yaml"  # the task's own sizes first
    own = yaml.safe_load(task_file.read_text())["task"]
    dataset = make_task(task_config(**{**own, **overrides}), seed=0)
    series = dataset.series if dataset.gate_targets is None else dataset.gate_targets
    path = out / design / "data.txt"
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_targets(path, series, f"moex task {overrides}, data seed 0, shape "
                                       f"{series.shape}")


LYAPUNOV = {  # the tool and moex's evaluation sizes, by the file the network is saved in
    "gn.dat": "{bin}/mregn-lyapunov -s {seed} -n 100000 -c 50 -t 1000 -l 1 mre.dat gn.dat",
    "rnn.dat": "{bin}/rnn-lyapunov -s {seed} -n 10000 -c 200 -t 1000 -l 1 rnn.dat"}


def their_lyapunov(design: str, bin_dir: Path, out: Path) -> list[dict]:
    """Each trained network of a design scored by the authors' own estimator (`LYAPUNOV`): one
    row per network, the mean of its samples' λ_max and how many samples are positive."""
    import statistics

    rows = []
    for folder in sorted((out / design).glob("net*")):
        if not (folder / "done").exists():
            continue
        result = folder / "lyapunov.txt"
        if not result.exists():
            tool = next(LYAPUNOV[name] for name in LYAPUNOV if (folder / name).exists())
            line = tool.format(bin=build_dir(bin_dir, design), seed=int(folder.name[3:]))
            done = subprocess.run(line.split(), cwd=folder, capture_output=True, text=True)
            check(done.returncode == 0, f"{folder}: {line} exited {done.returncode}")
            result.write_text(done.stdout)
        samples = [float(v) for v in result.read_text().split()]
        rows.append({"design": design, "network": folder.name, "samples": len(samples),
                     "max_lyapunov": statistics.fmean(samples),
                     "positive_samples": sum(v > 0 for v in samples)})
    return rows


def train_one(design: str, seed: int, bin_dir: Path, out: Path) -> str:
    folder = out / design / f"net{seed:03d}"
    if (folder / "done").exists():
        return f"{folder}: done before"
    folder.mkdir(parents=True, exist_ok=True)
    started = time.time()
    _, _, fixed_tau, commands = DESIGNS[design]
    conf = ""
    if fixed_tau:  # their learners read `fixed_tau` only from a config file (-c)
        (folder / "fixed_tau.conf").write_text("fixed_tau\n")
        conf = "-c fixed_tau.conf "
    for command in commands:
        line = command.format(bin=build_dir(bin_dir, design), seed=seed, conf=conf,
                              data=(out / design / "data.txt").resolve())
        with open(folder / "tool.log", "a") as log:
            log.write(f"$ {line}\n")
            log.flush()
            code = subprocess.call(line.split(), cwd=folder, stdout=log, stderr=log)
        if code:
            return f"{folder}: {line.split()[0]} exited {code} (see tool.log)"
    (folder / "done").write_text(f"{time.time() - started:.1f} s\n")
    return f"{folder}: trained in {time.time() - started:.0f} s"


# design: (moex's per-network CSV in docs/, its filter, the paper's table and setting, metrics)
COMPARED = {
    "reber_nc20": ("table1_summary.csv", ("model.gating.context_size", 20), ("Table 1", 20),
                   ("E_g", "block_kl_train", "block_kl_test", "max_lyapunov")),
    "reber_nc30": ("table1_summary.csv", ("model.gating.context_size", 30), ("Table 1", 30),
                   ("E_g", "block_kl_train", "block_kl_test", "max_lyapunov")),
    "table2_p05": ("table2_summary.csv", ("task.switch_prob", 0.5), ("Table 2", 0.5),
                   ("switch_prob", "max_lyapunov")),
    "table2_p025": ("table2_summary.csv", ("task.switch_prob", 0.25), ("Table 2", 0.25),
                    ("switch_prob", "max_lyapunov")),
    "reber_nc20_no_attraction": ("table1_summary.csv", ("model.gating.context_size", 20),
                                 ("Table 1", 20),
                                 ("E_g", "block_kl_train", "block_kl_test", "max_lyapunov")),
    "table2_p05_paper": ("table2_summary.csv", ("task.switch_prob", 0.5), ("Table 2", 0.5),
                         ("switch_prob", "max_lyapunov")),
    "table2_p025_paper": ("table2_summary.csv", ("task.switch_prob", 0.25), ("Table 2", 0.25),
                          ("switch_prob", "max_lyapunov")),
}


def _difference(a, b, permutations: int = 20000) -> tuple[float, float, float]:
    """Difference of means a - b, its (Welch) standard error, and the two-sided permutation p of
    the difference (the observed split counted, so p is never 0; seeded, so reruns agree)."""
    import numpy as np

    a, b = np.asarray(a, float), np.asarray(b, float)
    diff = a.mean() - b.mean()
    se = math.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    pooled, rng = np.concatenate([a, b]), np.random.default_rng(0)
    split = pooled[np.array([rng.permutation(len(pooled)) for _ in range(permutations)])]
    null = split[:, :len(a)].mean(1) - split[:, len(a):].mean(1)
    hits = (np.abs(null) >= abs(diff) - 1e-12).sum()
    return diff, se, (hits + 1) / (permutations + 1)


def collect(out: Path) -> Path:
    """Every control network's metrics (<out>/<design>/moex/metrics.csv, written by `moex import`)
    into docs/mregn_control_networks.csv, one row per network; the rows of a design not imported
    under <out> are kept from the file as it was (designs are imported in different sittings)."""
    import pandas as pd

    found = [d for d in COMPARED if (out / d / "moex" / "metrics.csv").exists()]
    check(bool(found), f"nothing imported under {out}/<design>/moex/")
    frames = [pd.read_csv(out / d / "moex" / "metrics.csv").assign(design=d) for d in found]
    path = DOCS / "mregn_control_networks.csv"
    if path.exists():
        kept = pd.read_csv(path)
        frames.insert(0, kept[~kept["design"].isin(found)])
    pd.concat(frames, ignore_index=True).to_csv(path, index=False)
    return path


def table():
    """One row per (design, metric), from docs/mregn_control_networks.csv and moex's per-network
    CSVs: moex's networks, the authors' code scored by moex, the paper, the control's distance to
    moex (Welch's standard error, permutation p) and to the paper: in standard errors of the
    control's mean alone (the paper's mean taken as exact) and with the paper's sampling error
    added, assuming its networks spread as the control's (its n: 50 in Table 1, 30 in Table 2)."""
    import pandas as pd

    from moex.tasks.paper import PAPER_TABLE1, PAPER_TABLE2

    networks = pd.read_csv(DOCS / "mregn_control_networks.csv")
    theirs = (pd.read_csv(DOCS / "mregn_control_lyapunov.csv")
              if (DOCS / "mregn_control_lyapunov.csv").exists()
              else pd.DataFrame(columns=["design", "max_lyapunov"]))
    rows = []
    for design, (csv, (key, value), (name, setting), metrics) in COMPARED.items():
        control = networks[(networks["design"] == design) & ~networks["failed"].astype(bool)]
        if control.empty:
            continue
        ours = pd.read_csv(DOCS / csv)
        ours = ours[(ours[key] == value) & ~ours["failed"].astype(bool)]
        paper_frame, paper_key, n_paper = ((PAPER_TABLE1, "model.gating.context_size", 50)
                                           if name == "Table 1"
                                           else (PAPER_TABLE2, "task.switch_prob", 30))
        paper_row = paper_frame.set_index(paper_key).loc[setting]
        their = theirs.loc[theirs["design"] == design, "max_lyapunov"].astype(float)
        for metric in (*metrics, "positive_percent"):
            if metric == "positive_percent":
                c, m = (control["max_lyapunov"] > 0) * 100.0, (ours["max_lyapunov"] > 0) * 100.0
            else:
                c, m = control[metric].dropna(), ours[metric].dropna()
            paper = float(paper_row[f"paper_{metric}"])
            diff, se, p = _difference(c, m)
            se_c = c.std(ddof=1) / math.sqrt(len(c))
            with_paper = math.sqrt(se_c**2 + c.var(ddof=1) / n_paper)
            tool = {"max_lyapunov": their, "positive_percent": (their > 0) * 100.0}.get(
                metric, their.iloc[:0])
            rows.append({"design": design, "metric": metric, "paper": paper,
                         "their_tool": tool.mean() if len(tool) else math.nan,
                         "their_tool_sd": tool.std(ddof=1) if len(tool) > 1 else math.nan,
                         "their_tool_n": len(tool),
                         "moex": m.mean(), "moex_sd": m.std(ddof=1), "moex_n": len(m),
                         "control": c.mean(), "control_sd": c.std(ddof=1), "control_n": len(c),
                         "control_minus_moex": diff, "difference_se": se, "permutation_p": p,
                         "control_vs_paper_se": (c.mean() - paper) / se_c if se_c else math.nan,
                         "control_vs_paper_se_paper_error":
                             (c.mean() - paper) / with_paper if with_paper else math.nan})
    return pd.DataFrame(rows)


def labels_table():
    """Per design, from docs/mregn_control_networks.csv: networks, how many fit (E^g < 0.02),
    the chaos label with its error (moex.metrics.lyapunov.chaos_label) beside the paper's
    λ_max > 0, and how the closed loop switches (Table 2) or its test KL (Reber)."""
    import pandas as pd

    from moex.metrics.lyapunov import CHAOS_LABELS, chaos_labels

    networks = pd.read_csv(DOCS / "mregn_control_networks.csv")
    rows = []
    for design, group in networks.groupby("design", sort=False):
        group = group[~group["failed"].astype(bool)]
        labels = chaos_labels(group)
        row = {"design": design, "networks": len(group),
               "fit (E^g < 0.02)": int((group["E_g"] < 0.02).sum()),
               " / ".join(CHAOS_LABELS): " / ".join(str(int((labels == name).sum()))
                                                   for name in CHAOS_LABELS),
               "λ_max > 0 (the paper's criterion)": int((group["max_lyapunov"] > 0).sum())}
        if design.startswith("table2"):
            row["switching: strict alternation (≥ 0.99) / one curve (≤ 0.01)"] = (
                f"{int((group['switch_prob'] >= 0.99).sum())} / "
                f"{int((group['switch_prob'] <= 0.01).sum())}")
        else:
            row["test KL, median"] = f"{group['block_kl_test'].median():.3f}"
        rows.append(row)
    return pd.DataFrame(rows)


def _se(value: float) -> str:
    """A distance in standard errors; n/a where the control's networks do not spread (sd 0)."""
    return "n/a (sd 0)" if not math.isfinite(value) else f"{value:+.1f}"


def markdown(rows) -> str:
    """The table REPRODUCTION.md and docs/mregn_control.md quote."""
    lines = ["| design | metric | paper | moex (n) | authors' code, scored by moex (n) | "
             "code − moex (p) | code − paper, SE (with the paper's error) | authors' code, "
             "scored by their tool (n) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows.itertuples():
        tool = (f"{r.their_tool:.4g} ± {r.their_tool_sd:.2g} ({r.their_tool_n})"
                if r.their_tool_n else "—")
        lines.append(
            f"| {r.design} | {r.metric} | {r.paper:.4g} | {r.moex:.4g} ± {r.moex_sd:.2g} "
            f"({r.moex_n}) | {r.control:.4g} ± {r.control_sd:.2g} ({r.control_n}) | "
            f"{r.control_minus_moex:+.3g} ± {r.difference_se:.2g} (p {r.permutation_p:.2g}) | "
            f"{_se(r.control_vs_paper_se)} ({_se(r.control_vs_paper_se_paper_error)}) | "
            f"{tool} |")
    return "\n".join(lines)


def labels_markdown(frame) -> str:
    """The labels table as Markdown (missing cells as —)."""
    from moex.report import to_markdown

    return to_markdown(frame.fillna("—")).rstrip("\n")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=["run", "lyapunov", "compare"])
    parser.add_argument("paths", type=Path, nargs="+",
                        help="run, lyapunov: <bin> <out>; compare: <out>")
    parser.add_argument("--designs", nargs="+", default=list(DESIGNS), choices=list(DESIGNS))
    parser.add_argument("--networks", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    if args.mode == "compare":
        print(f"per-network metrics: {collect(args.paths[0])}")
        rows = table()
        rows.to_csv(DOCS / "mregn_control_summary.csv", index=False)
        print(markdown(rows))
        print()
        print(labels_markdown(labels_table()))
        return 0
    if len(args.paths) != 2:
        parser.error(f"{args.mode} needs <bin folder> <out folder>")
    args.bin, args.out = args.paths
    tools = ("mregn-lyapunov", "rnn-lyapunov") if args.mode == "lyapunov" else (
        "rnn-learn", "mre-learn", "gn-learn")
    for design in args.designs:
        where = build_dir(args.bin, design)
        missing = [t for t in tools if not (where / t).is_file()]
        if missing:
            flags = " ".join(BUILDS[DESIGNS[design][1]])
            print(f"mregn_control: {where} lacks {', '.join(missing)} (design {design}); build "
                  f"them with bash tools/build_mregn.sh <mregn checkout> {where} {flags}".rstrip(),
                  file=sys.stderr)
            return 2
    if args.mode == "lyapunov":
        import pandas as pd

        frame = pd.DataFrame([row for d in args.designs
                              for row in their_lyapunov(d, args.bin.resolve(), args.out)])
        frame.to_csv(DOCS / "mregn_control_lyapunov.csv", index=False)
        print(frame.to_string(index=False))
        return 0
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
