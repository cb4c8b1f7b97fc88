"""`moex report DIR [DIR ...]`: tables and figures of any run and sweep folders (`moex.report`:
the paper's Tables 1-2 and Figs. 9, 14, 16 where the jobs have their settings). Its arguments are
folders, not a config: `main` reads them with argparse, not Hydra (`CONFIG` is None)."""

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from moex import errors
from moex.config.plot import FORMATS
from moex.errors import ConfigError, never
from moex.progress import packed
from moex.report import report, short_summary

NAME, CONFIG = "report", None


@dataclass
class ReportConfig:
    """The folders to compare, where the report goes (None: the one folder; with several,
    outputs/report/<date>) and the figures' format."""

    folders: list[Path]
    out: Path | None = None
    format: str = "png"


def check(cfg: ReportConfig) -> None:
    """Every folder exists (before anything is written)."""
    for folder in cfg.folders:
        errors.check(folder.is_dir(), f"{folder} is not a folder")


def out_folder(cfg: ReportConfig) -> Path:
    """The given `--out`, else the one folder, else a dated folder as every other verb's."""
    if cfg.out is not None:
        return cfg.out
    if len(cfg.folders) > 1:
        return Path("outputs", "report", time.strftime("%Y-%m-%d_%H-%M-%S"))
    return cfg.folders[0]


def run(cfg: ReportConfig, out_dir: Path, stop=never) -> dict[str, pd.DataFrame]:
    """The report of `cfg.folders` into `out_dir` (tables/, figures/, summary.csv), and a few
    lines on the terminal: jobs not done, networks counted once, the summary, what was written."""
    out = report(cfg.folders, out_dir, cfg.format)
    jobs = out["jobs"]
    errors.check(not jobs.empty, f"{' '.join(map(str, cfg.folders))} holds no job folder "
                                 f"(.hydra/config.yaml)")
    recorded = jobs.loc[jobs["provenance"] != "not recorded", "provenance"]
    if recorded.nunique() > 1:
        print(f"moex: warning: the jobs come from {recorded.nunique()} different machines or "
              f"package versions (column provenance of tables/jobs.csv; each folder's "
              f"provenance.json): their numbers are comparable, not bit-identical")
    for _, job in jobs[jobs["status"] != "done"].iterrows():
        print(f"job {job['job']}: {job['status']} {job['error']}".rstrip())
    repeats = out.get("repeats", pd.DataFrame())
    if len(repeats):
        print(f"moex: {len(repeats)} run(s) are networks another job already holds (same "
              f"settings, seed and run index: trained again, copied or evaluated again); each "
              f"is counted once (tables/repeats.csv)")
    if "summary" in out:
        print(short_summary(out["summary"], out.get("keys", [])))
    written = sorted(str(p.relative_to(out_dir)) for p in Path(out_dir).glob("tables/*.md"))
    print("\n".join(packed(f"moex: {(jobs['status'] == 'done').sum()} of {len(jobs)} jobs done; "
                           f"wrote", ["summary.csv", *written, "figures/"], width=100)))
    print(f"moex: report written to {out_dir}")  # last: the one line a path may make long
    return out


def main(argv: list[str] | None = None) -> None:
    """`moex report` from its command-line arguments; a refusal is one line and exit 2."""
    parser = argparse.ArgumentParser(prog="moex report", description=__doc__)
    parser.add_argument("folders", type=Path, nargs="+",
                        help="run or multirun folders (or any parents of jobs) to compare")
    parser.add_argument("--out", type=Path, help="where to write the report (default: the one "
                                                 "folder; with several, outputs/report/<date>)")
    parser.add_argument("--format", default="png", choices=FORMATS,
                        help="of the figures (pdf and svg are vector graphics)")
    args = parser.parse_args(argv)
    cfg = ReportConfig(args.folders, args.out, args.format)
    try:
        check(cfg)
        run(cfg, out_folder(cfg))
    except ConfigError as exc:
        parser.exit(2, f"moex: error: {exc}\n")
