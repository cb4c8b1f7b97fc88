"""`moex <verb> [overrides]`, the only module that imports Hydra.

Overrides are composed and validated with Hydra's compose API before the run starts, so a bad
value or unknown key ends with one line on stderr and exit code 2, and nothing is written.
"""

import hashlib
import json
import logging
import sys
import time
from pathlib import Path

import hydra
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from hydra.types import RunMode
from omegaconf import OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException
from tqdm.contrib.logging import logging_redirect_tqdm

from moex import pipeline, report
from moex.config import register_configs
from moex.errors import ConfigError
from moex.io import atomic_write
from moex.train import TrainingInterrupted

_PACKAGE_CONF = Path(__file__).resolve().parent / "conf"
log = logging.getLogger("moex")
CONF_DIR = str(_PACKAGE_CONF if _PACKAGE_CONF.is_dir() else _PACKAGE_CONF.parent.parent / "conf")

def _job_dirname(overrides: str) -> str:
    """Multirun subfolder: the job's overrides as one folder name ('/' in a value becomes '_'),
    shortened with a hash of the overrides when too long for a path."""
    name = overrides.replace("/", "_")
    if len(name) <= 120:
        return name
    return f"{name[:100]}...{hashlib.sha1(overrides.encode()).hexdigest()[:8]}"


# registered at import so Hydra's launchers (joblib workers too) can resolve the sweep subdir
OmegaConf.register_new_resolver("moex_dirname", _job_dirname, replace=True)

USAGE = """usage: moex <verb> [-m] [key=value ...]

verbs:
  train      train both phases on a task, evaluate, and write a run folder
  evaluate   recompute metrics.csv, samples.npz and figures of a run folder (run_dir=...)
  generate   closed-loop samples from random initial states (run_dir=... steps=... noise_var=...)
  report     tables and phase plots of a multirun folder (moex report outputs/multirun/<date>)

examples:
  moex train task=lissajous2
  moex train task=reber model.gating.context_size=50
  moex train -m task.switch_prob=0.5,0.25,0.125 num_runs=30
  moex evaluate run_dir=outputs/lissajous2/2026-11-24_12-00-00 eval.noise_var=0.001
  moex generate run_dir=outputs/lissajous2/2026-11-24_12-00-00 steps=10000 noise_var=0.001
  moex train -m experiment=paper_table2 hydra/launcher=joblib
  moex report outputs/multirun/2026-11-24_12-00-00
"""


def _one_line(exc: BaseException) -> str:
    """A readable single line from a Hydra / OmegaConf / moex exception."""
    text = str(exc).strip()
    first = text.splitlines()[0] if text else type(exc).__name__
    cause = exc.__cause__
    if "Could not override" in first and cause is not None:
        return f"unknown key {first.split(chr(39))[1]} ({str(cause).splitlines()[0]})"
    if "Error merging override" in first and cause is not None:
        key = first.split()[-1].split("=")[0]
        return f"{key}: {str(cause).splitlines()[0]}"
    if "Could not find" in first and "Available options" in text:
        group, option = first.split("'")[-2].rsplit("/", 1)
        listing = text.split("Available options")[1].split("Config search path")[0]
        options = listing.strip().splitlines()[1:]
        return f"{group}={option} is unknown; choose one of {', '.join(o.strip() for o in options)}"
    full_key = getattr(exc, "full_key", None)
    if full_key and full_key not in first:
        return f"{full_key}: {first}"
    return first


def _override_variants(args: list[str]) -> list[list[str]]:
    """Override lists to validate: the first value of every sweep, then each other value alone."""
    parsed = OverridesParser.create().parse_overrides(
        [a for a in args if not a.startswith("hydra.")])
    choices = [[o.input_line] if not o.is_sweep_override()
               else [f"{o.get_key_element()}={v}" for v in o.sweep_string_iterator()]
               for o in parsed]
    base = [c[0] for c in choices]
    variants = [base]
    for i, options in enumerate(choices):
        variants += [base[:i] + [v] + base[i + 1:] for v in options[1:]]
    return variants


def validate(config_name: str, args: list[str]):
    """Compose every override variant, build its config and load its data (or run folder);
    raise `ConfigError` on the first problem. Returns the first variant's config."""
    register_configs()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            configs = []
            for overrides in _override_variants(args):
                composed = compose(config_name, overrides=overrides, return_hydra_config=True)
                with open_dict(composed):
                    del composed["hydra"]
                configs.append(OmegaConf.to_object(composed))
            for cfg in configs:
                VERBS_CHECK[config_name](cfg)
            return configs[0]
    except (HydraException, OmegaConfBaseException, ConfigError) as exc:
        message = _one_line(exc)
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        for plugin, extra in (("submitit", "slurm"), ("joblib", "parallel")):
            if plugin in first:
                message = (f"hydra/launcher: the {plugin} launcher plugin is not installed; "
                           f"pip install -e '.[{extra}]'")
        raise ConfigError(message) from None
    finally:
        GlobalHydra.instance().clear()


STATUS = "status.json"


def _write_status(out_dir: Path, **status) -> None:
    text = json.dumps(status, indent=1)
    atomic_write(out_dir / STATUS, lambda tmp: Path(tmp).write_text(text))


def _job(run, verb: str):
    """A Hydra task function calling `run(cfg, out_dir, stop)`.

    Bad input exits 2; SIGINT/SIGTERM save a checkpoint and exit 128 + signal; any other error
    is logged with its traceback to the job's log and, in a multirun, does not stop the sweep.
    `moex train` leaves a status.json (done, failed or interrupted) in every job folder.
    """

    def task_function(dict_cfg) -> None:
        cfg = OmegaConf.to_object(dict_cfg)
        hydra_cfg = HydraConfig.get()
        out_dir = Path(hydra_cfg.runtime.output_dir)
        status = (lambda **kw: _write_status(out_dir, verb=verb, **kw)) if verb == "train" \
            else (lambda **kw: None)
        started = time.time()
        try:
            with logging_redirect_tqdm(), pipeline.StopRequest() as stop:
                run(cfg, out_dir, stop)
        except ConfigError as exc:
            log.error("%s", exc)
            status(status="failed", error=str(exc))
            print(f"moex: error: {exc}", file=sys.stderr)
            sys.exit(2)
        except TrainingInterrupted as exc:
            log.warning("%s; checkpoint saved in %s", exc, out_dir)
            status(status="interrupted", error=str(exc))
            print(f"moex: interrupted ({exc}); re-run the same command with "
                  f"hydra.run.dir={out_dir} (or resume=true) to continue", file=sys.stderr)
            sys.exit(128 + stop.signum)
        except Exception as exc:
            log.exception("job failed")
            status(status="failed", error=f"{type(exc).__name__}: {exc}")
            if hydra_cfg.mode == RunMode.MULTIRUN:
                return  # the sweep goes on; moex report lists failed jobs
            print(f"moex: error: {type(exc).__name__}: {exc} (traceback in {out_dir})",
                  file=sys.stderr)
            sys.exit(1)
        status(status="done", seconds=round(time.time() - started, 1))
        print(f"moex: run folder {out_dir}")

    return task_function


VERBS = {
    "train": ("config", _job(pipeline.run_train, "train")),
    "evaluate": ("evaluate", _job(lambda tool, _, __: pipeline.run_evaluate(tool), "evaluate")),
    "generate": ("generate", _job(lambda tool, _, __: pipeline.run_generate(tool), "generate")),
}
VERBS_CHECK = {"config": pipeline.load_task, "evaluate": pipeline.load_run,
               "generate": pipeline.load_run}


def _latest_run(task: str) -> Path:
    """The newest outputs/<task>/<date> folder holding a checkpoint, for `resume=true`."""
    runs = sorted(Path("outputs", task).glob("*/checkpoint.pt"))
    if not runs:
        raise ConfigError(f"resume=true but outputs/{task}/ holds no run with a checkpoint; "
                          f"name the folder with hydra.run.dir=")
    return runs[-1].parent


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return
    verb, args = argv[0], argv[1:]
    if verb == "report":  # a folder in, tables out: plain argparse, no Hydra
        report.main(args)
        return
    if verb not in VERBS:
        print(f"moex: error: unknown verb {verb!r}; choose one of {', '.join(VERBS)}, report",
              file=sys.stderr)
        sys.exit(2)
    config_name, task_function = VERBS[verb]
    hydra_flags = [a for a in args if a.startswith("-")]
    overrides = [a for a in args if not a.startswith("-")]
    if not {"--help", "-h", "--hydra-help", "--info", "--cfg", "-c"} & set(hydra_flags):
        try:
            cfg = validate(config_name, overrides)
            if verb == "train" and cfg.resume and not {"-m", "--multirun"} & set(hydra_flags) \
                    and not any(a.startswith("hydra.run.dir=") for a in args):
                args = args + [f"hydra.run.dir={_latest_run(cfg.task.name)}"]
        except ConfigError as exc:
            print(f"moex: error: {exc}", file=sys.stderr)
            sys.exit(2)
    register_configs()
    entry = hydra.main(version_base="1.3", config_path=CONF_DIR,
                       config_name=config_name)(task_function)
    sys.argv = [f"moex {verb}"] + args
    entry()
