"""A real recording, segmented by moex and, on the same arrays, by a Gaussian HMM and k-means.

The data: BasicMotions (Clements, UEA multivariate archive), shipped inside sktime: a smart
watch's 3-axis accelerometer and 3-axis gyroscope (6 channels, 10 Hz, 10 s per exemplar) while
its wearer stands, walks, runs or plays badminton; 40 exemplars for training and 40 for
testing, 10 per activity each. Exemplars are joined into series by a Markov chain over the
activities (stay with probability 0.5, else one of the other three): 6 training series of 10
exemplars (1000 steps) from the training exemplars, 4 held-out series from the test exemplars.
Each channel is standardised with the training series' mean and SD.

Then, with the CLI: `moex train task=csv task.labels=<file> task.scale=auto` (4 experts, 3 runs,
σ̄ from the data as the csv task does by default; with the paper's β prior ς = 10, with ς = 1,
and with ς chosen by a pilot run, `train.experts.gate_prior_std=auto`) and `moex segment` on
the held-out series (with the run's own ς, and with ς chosen on those series by
cross-validation, `gate_prior_std=auto`); beside it hmmlearn's GaussianHMM (4 states, Viterbi
path, 3 seeds; full covariances, and one variance per state as moex's σ_k² I) and
scikit-learn's KMeans (4 clusters on the steps' 6-vectors; 3 seeds), fitted to the
training series and applied to both. Every method is scored by moex.metrics.segmentation:
adjusted Rand index, normalised mutual information, accuracy after the best one-to-one matching.

    pip install -e ".[compare]"      # hmmlearn, scikit-learn, sktime (the data)
    python examples/activity.py OUT  # writes OUT/scores.csv, OUT/summary.md, the run folders

Re-running the same command keeps finished work (the trained run, the segmentation).
"""

import argparse
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from moex.metrics.segmentation import scores
from moex.tasks.scaling import fit_scale

STAY = 0.5  # the Markov chain's probability of repeating an activity
VARIANTS = {  # moex's rows: the csv task's defaults (σ̄ from the data), a tighter β prior, ς
    "moex": [],  # chosen by a pilot run
    "moex, ς = 1": ["train.experts.gate_prior_std=1"],
    "moex, ς auto": ["train.experts.gate_prior_std=auto"],
}
ABLATION = {  # --ablation: the paper's σ̄ = 0.05 instead of the data's, each ς (one factor each)
    "moex, σ̄ = 0.05": ["model.sigma_min=0.05"],
    "moex, σ̄ = 0.05, ς = 1": ["model.sigma_min=0.05", "train.experts.gate_prior_std=1"],
}
SEEDS = (0, 1, 2)
MOEX = [sys.executable, "-c", "from moex.launch import main; main()"]


def chain(exemplars: dict[int, np.ndarray], count: int, per_series: int,
          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`count` series of `per_series` exemplars (T, D each) joined along time, the activity
    drawn by the Markov chain (stay STAY, else uniform over the others); each exemplar is drawn
    at random from its activity. Returns series (count, T, D) and labels (count, T)."""
    classes = sorted(exemplars)
    series, labels = [], []
    for _ in range(count):
        c, parts, tags = rng.choice(classes), [], []
        for _ in range(per_series):
            pick = exemplars[c][rng.integers(len(exemplars[c]))]
            parts.append(pick)
            tags.append(np.full(len(pick), c))
            if rng.random() >= STAY:
                c = rng.choice([o for o in classes if o != c])
        series.append(np.concatenate(parts))
        labels.append(np.concatenate(tags))
    return np.stack(series), np.stack(labels)


def recording(rng: np.random.Generator):
    """Training and held-out series with their labels, and the activities' names."""
    from sktime.datasets import load_basic_motions

    split = {}
    for name in ("train", "test"):
        X, y = load_basic_motions(split=name, return_type="numpy3D")
        split[name] = (X.transpose(0, 2, 1), y)  # (exemplars, T, D)
    names = sorted(set(split["train"][1]))
    exemplars = {name: {i: X[y == n] for i, n in enumerate(names)}
                 for name, (X, y) in split.items()}
    train, train_labels = chain(exemplars["train"], 6, 10, rng)
    test, test_labels = chain(exemplars["test"], 4, 10, rng)
    mean, sd = train.mean((0, 1)), train.std((0, 1))
    return (train - mean) / sd, train_labels, (test - mean) / sd, test_labels, names


def baselines(train, train_labels, test, test_labels) -> list[dict]:
    """The HMM's and k-means' scores on both sets, one row per method, data and seed."""
    from hmmlearn.hmm import GaussianHMM
    from sklearn.cluster import KMeans

    rows = []
    K = len(np.unique(train_labels))
    steps = train.reshape(-1, train.shape[-1])
    for seed in SEEDS:
        hmm, spherical = (GaussianHMM(K, covariance_type=kind, n_iter=200, random_state=seed)
                          .fit(steps, [train.shape[1]] * len(train))
                          for kind in ("full", "spherical"))
        kmeans = KMeans(K, n_init=10, random_state=seed).fit(steps)
        for method, model in (("Gaussian HMM", hmm), ("Gaussian HMM, spherical", spherical),
                              ("k-means", kmeans)):
            for data, x, y in (("train", train, train_labels), ("test", test, test_labels)):
                found = np.stack([model.predict(s) for s in x])
                rows.append({"method": method, "data": data, "run": seed,
                             **_scores(y, found)})
    return rows


def _scores(truth, found) -> dict:
    got = scores(truth, found)
    return {k: float(v) for k, v in got.items() if k != "label_of_expert"}


def folder_name(method: str) -> str:
    """A variant's run folder: "moex, σ̄ = 0.05, ς = 1" -> "moex_floor_0.05_prior_1"."""
    named = method.replace("σ̄", "floor").replace("ς", "prior")
    return "_".join(re.findall(r"[A-Za-z0-9.]+", named))


def moex_rows(out: Path, train, train_labels, test, test_labels, steps,
              variants: dict) -> list[dict]:
    """moex trained and segmenting with the CLI, once per entry of `variants`; its scores on
    both sets, one row per run."""
    for name, array in (("train", train), ("train_labels", train_labels), ("test", test),
                        ("test_labels", test_labels)):
        np.save(out / f"{name}.npy", array)
    rows = []
    for method, keys in variants.items():
        run = out / folder_name(method)
        if not (run / "metrics.csv").is_file():
            subprocess.run(MOEX + ["train", "task=csv", f"task.path={out}/train.npy",
                                   f"task.labels={out}/train_labels.npy", "task.scale=auto",
                                   "model.num_experts=4", f"num_runs={len(SEEDS)}",
                                   "eval=quick", f"train.experts.steps={steps[0]}",
                                   f"train.gating.steps={steps[1]}", *keys,
                                   f"hydra.run.dir={run}"], check=True)
        columns = ["segment_ari", "segment_nmi", "segment_accuracy"]
        rows += [{"method": method, "data": "train", **row}
                 for row in pd.read_csv(run / "metrics.csv")[["run", *columns]].to_dict("records")]
        for prior_std, named in (("0", method), ("auto", f"{method}, held-out ς auto")):
            segmented = run / f"segment_{prior_std}"
            if not (segmented / "segment_scores.csv").is_file():
                subprocess.run(MOEX + ["segment", f"run_dir={run}", f"task.path={out}/test.npy",
                                       f"task.labels={out}/test_labels.npy",
                                       f"gate_prior_std={prior_std}", f"out_dir={segmented}"],
                               check=True)
            tested = pd.read_csv(segmented / "segment_scores.csv")[["run", *columns]]
            rows += [{"method": named, "data": "test", **row} for row in tested.to_dict("records")]
    return rows


NAMES = {"segment_ari": "adjusted Rand index", "segment_nmi": "normalised mutual information",
         "segment_accuracy": "accuracy after matching"}


def summary(frame: pd.DataFrame) -> str:
    """The page's table: median (smallest-largest) over runs or seeds, per method and data."""
    lines = ["| method | data | runs | " + " | ".join(NAMES.values()) + " |",
             "|---|---|---|" + "---|" * len(NAMES)]
    for (method, data), part in frame.groupby(["method", "data"], sort=False):
        cells = [f"{part[c].median():.2f} ({part[c].min():.2f}-{part[c].max():.2f})"
                 for c in NAMES]
        lines.append(f"| {method} | {data} | {len(part)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def activities(train, train_labels, names) -> str:
    """Per activity, in the units moex trains in (task.scale=auto): the RMS of the one-step
    change x_{n+1} - x_n, and the SD of x (both per feature, averaged): what a one-step
    predictor with the floor σ̄ can tell apart."""
    x, _ = fit_scale(train, "auto", "train")
    change, now = np.diff(x, axis=1), train_labels[:, 1:]
    lines = ["| activity | steps | one-step change, RMS | SD of x |", "|---|---|---|---|"]
    for c, name in enumerate(names):
        lines.append(f"| {name} | {int((train_labels == c).sum())} | "
                     f"{np.sqrt(np.mean(change[now == c] ** 2)):.3f} | "
                     f"{x[train_labels == c].std(0).mean():.3f} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--steps", type=int, nargs=2, default=(5000, 2000),
                        metavar=("PHASE1", "PHASE2"))
    parser.add_argument("--ablation", action="store_true",
                        help="also train with the paper's sigma_min = 0.05 (two more rows)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    train, train_labels, test, test_labels, names = recording(np.random.default_rng(0))
    print(f"activities {', '.join(names)}; training {train.shape}, held-out {test.shape}")
    variants = {**VARIANTS, **(ABLATION if args.ablation else {})}
    rows = moex_rows(args.out, train, train_labels, test, test_labels, args.steps, variants)
    rows += baselines(train, train_labels, test, test_labels)
    frame = pd.DataFrame(rows)
    frame.to_csv(args.out / "scores.csv", index=False)
    text = f"{summary(frame)}\n\n{activities(train, train_labels, names)}\n"
    (args.out / "summary.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
