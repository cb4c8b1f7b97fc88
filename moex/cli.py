"""`moex <verb> [overrides]`, the only module that imports Hydra.

Overrides are composed and validated with Hydra's compose API before the run starts, so a bad
value or unknown key ends with one line on stderr and exit code 2, and nothing is written. A
single run then runs on that composed config (Hydra's `run_job`, as `hydra.main` would call it):
the command line is composed once. Sweeps and Hydra's own flags (--cfg, --info, --help) go
through `hydra.main`, whose launcher composes each job.
"""

import copy
import difflib
import logging
import os
import signal
import sys
import time
from dataclasses import field, make_dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, NamedTuple

import hydra
from hydra import compose, initialize_config_dir
from hydra._internal.callbacks import Callbacks
from hydra._internal.utils import run_and_report
from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import run_job
from hydra.errors import HydraException, OverrideParseException
from hydra.types import HydraContext, RunMode
from omegaconf import OmegaConf, open_dict, read_write
from omegaconf.errors import OmegaConfBaseException
from tqdm.contrib.logging import logging_redirect_tqdm

from moex import config, folders, packing, provenance, verbs
from moex.config import (
    Config,
    EvaluateConfig,
    GenerateConfig,
    ImportConfig,
    SegmentConfig,
)
from moex.errors import ConfigError, Interrupted, check, closest_first
from moex.stop import StopRequest
from moex.tasks import typed_config

log = logging.getLogger("moex")
CONF_DIR = str(config.CONF_DIR)
SHOWS_CONFIG = {"--cfg", "-c", "--info"}  # Hydra flags that print instead of running


def register_configs() -> None:
    """The typed schemas of every verb's config, in Hydra's ConfigStore (done before composing).
    A config with a task has an open `task` node: any task's keys compose into it, and `typed`
    types them by the task's own config class (`moex.tasks.typed_config`)."""
    for name, schema in (("base_config", Config), ("base_evaluate", EvaluateConfig),
                         ("base_generate", GenerateConfig), ("base_import", ImportConfig),
                         ("base_segment", SegmentConfig)):
        node = OmegaConf.structured(schema)
        if issubclass(schema, Config):
            node = OmegaConf.structured(make_dataclass(
                schema.__name__, [("task", Any, field(default_factory=dict))], bases=(schema,),
                namespace={"SCHEMA": schema}))
            OmegaConf.set_struct(node.task, False)
        ConfigStore.instance().store(name=name, node=node)


USAGE = """usage: moex <verb> [-m] [key=value ...]    (moex --version: the installed version)

verbs:
  train      train both phases on a task, evaluate, and write a run folder
  evaluate   recompute metrics.csv, samples.npz and figures of a run folder (run_dir=...)
  generate   closed-loop samples from random initial states (run_dir=... steps=... noise_var=...)
  import     networks trained by the authors' C tools (mregn) as a moex run folder (source=...)
  segment    which expert explains which step of new data (run_dir=... task.path=...)
  report     tables and figures of any run and sweep folders (moex report DIR [DIR ...])

examples:
  moex train task=lissajous2
  moex train task=reber model.gating.context_size=50
  moex train -m task.switch_prob=0.5,0.25,0.125 num_runs=30
  moex evaluate run_dir=outputs/lissajous2/2026-11-24_12-00-00 eval.noise_var=0.001
  moex generate run_dir=outputs/lissajous2/2026-11-24_12-00-00 steps=10000 noise_var=0.001
  moex train -m experiment=paper_table2 hydra/launcher=joblib
  moex import source=[runs/net*] task=lissajous2 task.switch_prob=0.5
  moex segment run_dir=outputs/csv/2026-11-24_12-00-00 task.path=new.csv task.labels=activity
  moex report outputs/multirun/2026-11-24_12-00-00
"""


def _allowed_keys(config_name: str, key: str, groups: list[str]) -> str:
    """The keys allowed beside an unknown `key`, closest spelling first, in the config the
    command line's group choices (`groups`: task=reber, ...) compose."""
    parent, _, leaf = key.rpartition(".")
    try:
        root = compose(config_name, overrides=groups)
        node = OmegaConf.select(root, parent) if parent else root
        if not OmegaConf.is_dict(node):  # the parent itself is misspelt: the closest full keys
            paths = dotted_keys(OmegaConf.to_container(root, resolve=False))
            close = difflib.get_close_matches(key, paths, n=3, cutoff=0.6)
            return f"; did you mean {' or '.join(close)}?" if close else ""
        keys = [str(k) for k in node.keys()]
        # a key given without its group (noise_var for eval.noise_var): its dotted forms first
        nested = [path for path in dotted_keys(OmegaConf.to_container(root, resolve=False))
                  if path.endswith(f".{leaf}")] if not parent else []
    except Exception:  # nothing to compose against: nothing to list
        return ""
    ranked = difflib.get_close_matches(leaf, keys, n=len(keys), cutoff=0)
    names = [f"{parent}.{k}" if parent else k for k in ranked + sorted(set(keys) - set(ranked))]
    hint = f"; did you mean {' or '.join(nested)}?" if nested else ""
    return f"{hint}; allowed keys: {', '.join(names)}"


def dotted_keys(tree: dict, prefix: str = "") -> list[str]:
    """Every leaf key of a nested config as a dotted path."""
    paths = []
    for k, v in tree.items():
        path = f"{prefix}{k}"
        paths += dotted_keys(v, f"{path}.") if isinstance(v, dict) and v else [path]
    return paths


def _one_line(exc: BaseException, config_name: str, groups: list[str]) -> str:
    """A readable single line from a Hydra / OmegaConf / moex exception (`groups`: the command
    line's config group choices, which decide the keys a config has)."""
    text = str(exc).strip()
    first = text.splitlines()[0] if text else type(exc).__name__
    cause = exc.__cause__
    if first.startswith("Ambiguous value for argument"):  # a sweep without -m
        override = first.split("'")[1]
        verb = "train" if config_name == "config" else config_name
        return (f"{override}: several values are a sweep, which needs -m (moex {verb} -m "
                f"{override}); a list is written {override.split('=')[0]}=[a,b]")
    if "Could not override" in first and cause is not None:
        key = first.split(chr(39))[1]
        return f"unknown key {key}{_allowed_keys(config_name, key, groups)}"
    if "Error merging override" in first and cause is not None:
        key = first.split()[-1].split("=")[0]
        return f"{key}: {str(cause).splitlines()[0]}"
    if "Could not find" in first and "Available options" in text:
        group, option = first.split("'")[-2].rsplit("/", 1)
        listing = text.split("Available options")[1].split("Config search path")[0]
        options = closest_first(option, [o.strip() for o in listing.strip().splitlines()[1:]])
        return f"{group}={option} is unknown; choose one of {', '.join(options)}"
    full_key = getattr(exc, "full_key", None)
    if full_key and full_key not in first:
        return f"{full_key}: {first}"
    return first


def _parse(args: list[str]) -> list:
    """Parse overrides one at a time, so that a malformed one is named with its key."""
    parser, parsed = OverridesParser.create(), []
    for arg in args:
        try:
            parsed += parser.parse_overrides([arg])
        except OverrideParseException:
            key = arg.split("=", 1)[0]
            raise ConfigError(f"{key}: cannot parse the override {arg!r}; write key=value, "
                              f"lists as key=[a,b], sweeps as key=a,b, and quote values with "
                              f"spaces") from None
    return parsed


def _override_variants(args: list[str]) -> list[list[str]]:
    """Override lists to validate: the first value of every sweep, then each other value alone
    (hydra.* keys included: Hydra's own config is checked as well)."""
    parsed = _parse(args)
    choices = [[o.input_line] if not o.is_sweep_override()
               else [f"{o.get_key_element()}={v}" for v in o.sweep_string_iterator()]
               for o in parsed]
    base = [c[0] for c in choices]
    variants = [base]
    for i, options in enumerate(choices):
        variants += [base[:i] + [v] + base[i + 1:] for v in options[1:]]
    return variants


def _search_path(args: list[str], flags: list[str]) -> list[str]:
    """The user's config folders, from --config-dir/-cd DIR or hydra.searchpath=[...], as an
    override for the compose API (which composes the built-in configs only otherwise)."""
    paths = [a.split("=", 1)[1] for a in args if a.startswith("hydra.searchpath=")]
    for i, flag in enumerate(flags):
        if flag in ("--config-dir", "-cd") and i + 1 < len(flags):
            paths.append(f"[file://{Path(flags[i + 1]).resolve()}]")
        elif flag.startswith("--config-dir="):
            paths.append(f"[file://{Path(flag.split('=', 1)[1]).resolve()}]")
    entries = [e.strip() for p in paths for e in p.strip("[]").split(",") if e.strip()]
    return [f"hydra.searchpath=[{','.join(entries)}]"] if entries else []


def typed(composed, choices=None) -> object:
    """The dataclass of a composed config; `eval=paper` of `moex evaluate` sets paper_sizes."""
    schema = OmegaConf.get_type(composed)
    if issubclass(schema, Config):  # (the open schema of `register_configs` names its own)
        cfg = typed_config(getattr(schema, "SCHEMA", schema),
                           OmegaConf.to_container(composed, resolve=True))
    else:
        cfg = OmegaConf.to_object(composed)
    if isinstance(cfg, EvaluateConfig) and (choices or {}).get("eval") == "paper":
        cfg.paper_sizes = True
    return cfg


def typed_job_config(sweep_config) -> object:
    """The dataclass of one job of a sweep (its config without the `hydra` node, as the task
    function receives it): what the packed launcher trains before the job runs."""
    task_cfg = copy.deepcopy(sweep_config)
    with open_dict(task_cfg):
        del task_cfg["hydra"]
    return typed(task_cfg, sweep_config.hydra.runtime.choices)


def interrupted_jobs(job_dirs: list[Path], exc: BaseException) -> None:
    """A packed batch stopped by a signal: each job folder says so, and how to continue."""
    for folder in job_dirs:
        folders.write_status(Path(folder), verb="train", status="interrupted", error=str(exc))
    print(f"moex: interrupted ({exc}); every job's trained state is saved: re-run the same -m "
          f"command with hydra.sweep.dir={Path(job_dirs[0]).parent} to continue",
          file=sys.stderr)


class Composed(NamedTuple):
    """What `validate` composed: the (first variant's) config with Hydra's node and the loader
    that composed it, for `run_composed`."""

    config: object
    loader: object


def validate(config_name: str, args: list[str], flags: list[str] = (), multirun: bool = False):
    """Compose the command line (a sweep: every override variant), build its config and load its
    data (or run folder); raise `ConfigError` on the first problem. Returns the (first variant's)
    config and what was composed for it (`Composed`)."""
    register_configs()
    GlobalHydra.instance().clear()
    search = _search_path(args, list(flags))
    try:
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            try:
                configs, first = [], None
                own = [a for a in args if not a.startswith("hydra.searchpath=")]  # in `search`
                variants = _override_variants(own) if multirun else [own]
                for overrides in variants:
                    composed = compose(config_name, overrides=search + overrides,
                                       return_hydra_config=True)
                    first = first or Composed(copy.deepcopy(composed),
                                              GlobalHydra.instance().config_loader())
                    choices = dict(composed.hydra.runtime.choices)
                    _check_launcher(composed.hydra.launcher)
                    with open_dict(composed):
                        del composed["hydra"]
                    configs.append(typed(composed, choices))
                for cfg in configs:
                    VERBS_CHECK[config_name](cfg)
                return configs[0], first
            except (HydraException, OmegaConfBaseException) as exc:
                if isinstance(exc, OverrideParseException):
                    _parse(args)  # names the override that does not parse
                named = {d.name for d in Path(CONF_DIR).iterdir() if d.is_dir()}
                groups = search + [a for a in args if a.split("=", 1)[0].lstrip("+~") in named]
                raise ConfigError(_launcher_hint(exc) or _one_line(exc, config_name, groups)) \
                    from None
    finally:
        GlobalHydra.instance().clear()


def run_composed(config_name: str, composed: Composed, run_dir: str | None, task_function):
    """One run on the config `validate` composed, as `hydra.main` runs it after composing
    (`Hydra.run`): its callbacks, `run_job` (the folder, .hydra/, the log) and the task function;
    `run_dir` (resume=true, out_dir=) sets hydra.run.dir as the override would."""
    cfg = composed.config
    with read_write(cfg.hydra), open_dict(cfg.hydra):
        cfg.hydra.mode = RunMode.RUN
        if run_dir is not None:
            cfg.hydra.run.dir = run_dir
            cfg.hydra.overrides.hydra.append(f"hydra.run.dir={run_dir}")
        cfg.hydra.overrides.hydra.append("hydra.mode=RUN")  # as hydra.main records it
    callbacks = Callbacks(cfg)
    callbacks.on_run_start(config=cfg, config_name=config_name)
    done = run_job(hydra_context=HydraContext(config_loader=composed.loader, callbacks=callbacks),
                   task_function=task_function, config=cfg, job_dir_key="hydra.run.dir",
                   job_subdir_key=None)
    callbacks.on_run_end(config=cfg, config_name=config_name, job_return=done)
    return done.return_value  # raises the task function's error, as Hydra's run does


def _check_launcher(launcher) -> None:
    """The packed launcher's own option (Hydra checks only its type)."""
    if "max_runs" in launcher:
        check(int(launcher.max_runs) >= 0, f"hydra.launcher.max_runs={launcher.max_runs} must "
              f"be >= 0 (the most networks in one batch; 0: no limit)")


def _launcher_hint(exc: BaseException) -> str:
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    for plugin, extra in (("submitit", "slurm"), ("joblib", "parallel")):
        if plugin in first:
            return (f"hydra/launcher: the {plugin} launcher plugin is not installed; "
                    f"pip install -e '.[{extra}]'")
    return ""


_sweeps: set[Path] = set()  # the sweep folders this process ran jobs in (basic launcher)


def _job(run, verb: str):
    """A Hydra task function calling `run(cfg, out_dir, stop)`.

    Bad input exits 2; SIGINT/SIGTERM save a checkpoint and exit 128 + signal; any other error
    is logged with its traceback to the job's log and, in a multirun, does not stop the sweep.
    `moex train` leaves a status.json (done, failed or interrupted) in every job folder.
    """

    def task_function(dict_cfg) -> None:
        hydra_cfg = HydraConfig.get()
        out_dir = Path(hydra_cfg.runtime.output_dir)
        cfg = typed(dict_cfg, hydra_cfg.runtime.choices)
        status = (lambda **kw: folders.write_status(out_dir, verb=verb, **kw)) if verb == "train" \
            else (lambda **kw: None)
        started = time.time()
        if hydra_cfg.mode == RunMode.MULTIRUN:
            _sweeps.add(Path(hydra_cfg.sweep.dir).resolve())
            folders.write_job_index(Path(hydra_cfg.sweep.dir))
        try:
            with logging_redirect_tqdm(), StopRequest() as stop, provenance.recorded(
                    out_dir, verb, getattr(cfg, "backend", None), getattr(cfg, "device", None),
                    getattr(cfg, "precision", None)):
                run(cfg, out_dir, stop)
        except ConfigError as exc:
            log.error("%s", exc)
            status(status="failed", error=str(exc))
            folders.discard_if_empty(out_dir, verb)
            print(f"moex: error: {exc}", file=sys.stderr)
            sys.exit(2)
        except Interrupted as exc:
            log.warning("%s (%s)", exc, "trained state saved in " + str(out_dir)
                        if verb == "train" else "nothing written")
            status(status="interrupted", error=str(exc))
            if verb == "train" and hydra_cfg.mode == RunMode.MULTIRUN:
                print(f"moex: interrupted ({exc}); re-run the same -m command with "
                      f"hydra.sweep.dir={hydra_cfg.sweep.dir} to continue (finished jobs are "
                      f"kept)", file=sys.stderr)
            elif verb == "train":
                print(f"moex: interrupted ({exc}); re-run the same command with "
                      f"hydra.run.dir={out_dir} (or resume=true) to continue", file=sys.stderr)
            else:
                folders.discard_if_empty(out_dir, verb)
                print(f"moex: interrupted ({exc}); nothing was written", file=sys.stderr)
            sys.exit(128 + (stop.signum or signal.SIGINT))
        except Exception as exc:
            log.exception("job failed")
            status(status="failed", error=f"{type(exc).__name__}: {exc}")
            if hydra_cfg.mode == RunMode.MULTIRUN:
                return  # the sweep goes on; moex report lists failed jobs
            where = "" if folders.discard_if_empty(out_dir, verb) else f" (traceback in {out_dir})"
            print(f"moex: error: {type(exc).__name__}: {exc}{where}", file=sys.stderr)
            sys.exit(1)
        status(status="done",  # a packed job adds its share of the batch's training
               seconds=round(time.time() - started + packing.shared_seconds(out_dir), 1))
        print(f"moex: run folder {out_dir}")

    return task_function


# the verbs Hydra composes a config for; the others (report) read their own arguments (`main`)
VERBS = {name: (module.CONFIG, _job(module.run, name)) for name, module in verbs.VERBS.items()
         if module.CONFIG is not None}
VERBS_CHECK = {module.CONFIG: module.check for module in verbs.VERBS.values()
               if module.CONFIG is not None}


def _latest_run(task: str) -> Path:
    """The folder `resume=true` continues: the newest outputs/<task>/<date> folder holding a
    checkpoint whose training is unfinished (interrupted, or killed before its status.json
    said done), else the newest finished one (which is then not redone)."""
    runs = [p.parent for p in sorted(Path("outputs", task).glob("*/checkpoint.pt"))]
    if not runs:
        raise ConfigError(f"resume=true but outputs/{task}/ holds no run with a checkpoint; "
                          f"name the folder with hydra.run.dir=")
    unfinished = [run for run in runs if folders.read_status(run) != "done"]
    return (unfinished or runs)[-1]


def _tell_interrupted(task: str, overrides: list[str]) -> None:
    """Before a new single run starts: an unfinished folder of the same command (the same
    overrides) is named, with how to continue it, rather than silently left behind."""
    import yaml

    wanted = sorted(o for o in overrides if not o.startswith("hydra."))
    for run in sorted(Path("outputs", task).glob("*/checkpoint.pt"), reverse=True):
        folder = run.parent
        given = folder / ".hydra" / "overrides.yaml"
        if folders.read_status(folder) == "done" or not given.exists():
            continue
        try:
            same = sorted(o for o in yaml.safe_load(given.read_text()) or []
                          if not o.startswith("hydra.")) == wanted
        except (OSError, yaml.YAMLError, TypeError):
            continue
        if same:
            print(f"moex: {folder} holds an unfinished run of this command; this one starts "
                  f"a new folder (add resume=true, or hydra.run.dir={folder}, to continue "
                  f"that one)", file=sys.stderr)
            return


_VALUED_FLAGS = {"--config-dir", "-cd", "--config-path", "-cp", "--config-name", "-cn",
                 "--cfg", "-c", "--package", "-p", "--experimental-rerun"}


def _split_flags(args: list[str]) -> tuple[list[str], list[str]]:
    """Hydra's flags (with the value of those that take one) and the overrides."""
    flags, overrides, i = [], [], 0
    while i < len(args):
        if args[i].startswith("-"):
            flags.append(args[i])
            if args[i] in _VALUED_FLAGS and i + 1 < len(args):
                flags.append(args[i + 1])
                i += 1
        else:
            overrides.append(args[i])
        i += 1
    return flags, overrides


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return
    verb, args = argv[0], argv[1:]
    if verb in ("--version", "-V"):
        print(f"moex {metadata.version('moex')}")
        return
    if verb in ("--shell-completion", "-sc"):
        _shell_completion(args)
        return
    if verb in verbs.VERBS and verb not in VERBS:  # folders in, tables out: argparse, no Hydra
        verbs.VERBS[verb].main(args)
        return
    if verb not in VERBS:
        print(f"moex: error: unknown verb {verb!r}; choose one of {', '.join(verbs.VERBS)}",
              file=sys.stderr)
        sys.exit(2)
    config_name, task_function = VERBS[verb]
    hydra_flags, overrides = _split_flags(args)
    shown = SHOWS_CONFIG & set(hydra_flags)
    if shown and {"-m", "--multirun"} & set(hydra_flags):  # Hydra's answer is a traceback
        print(f"moex: error: {sorted(shown)[0]} shows the config of one run: drop -m and give "
              f"one value per key", file=sys.stderr)
        sys.exit(2)
    multirun = bool({"-m", "--multirun"} & set(hydra_flags))
    claimed = composed = run_dir = None
    if not ({"--help", "-h", "--hydra-help"} | SHOWS_CONFIG) & set(hydra_flags):
        try:
            cfg, composed = validate(config_name, overrides, hydra_flags, multirun)
            if verb == "train" and not multirun \
                    and not any(a.startswith("hydra.run.dir=") for a in args):
                if cfg.resume:
                    run_dir = str(_latest_run(cfg.task.name))
                else:
                    _tell_interrupted(cfg.task.name, overrides)
            if verb != "train" and cfg.out_dir:
                run_dir = cfg.out_dir
            if run_dir is not None:
                args = args + [f"hydra.run.dir={run_dir}"]
            claimed = folders.claim(args, multirun, verb, cfg)
        except ConfigError as exc:
            print(f"moex: error: {exc}", file=sys.stderr)
            sys.exit(2)
    sys.argv = [f"moex {verb}"] + args
    flag_names = {f.split("=", 1)[0] for f in hydra_flags if f.startswith("-")}
    once = composed is not None and not multirun and flag_names <= {"--config-dir", "-cd"}
    try:
        if once:  # the config validate composed, not composed again
            run_and_report(lambda: run_composed(config_name, composed, run_dir, task_function))
        else:
            register_configs()
            hydra.main(version_base="1.3", config_path=CONF_DIR,
                       config_name=config_name)(task_function)()
    finally:
        if claimed is not None:
            folders.release(claimed, args, multirun)
    sweep = folders.named_folder(args, "hydra.sweep.dir")
    if multirun and sweep is not None and sweep.is_dir():
        _sweeps.add(sweep.resolve())
    _summarise_sweeps(verb)


def _summarise_sweeps(verb: str) -> None:
    """A line per sweep folder this command ran jobs in; exit 1 when any of their jobs failed
    (the sweep went on past them, so that only the exit status can tell a script)."""
    failed = 0
    for folder in sorted(_sweeps):
        line, n = folders.sweep_summary(folder, verb)
        print(line)
        failed += n
    if failed:
        print(f"moex: {failed} job(s) failed (status.json in each job folder says which; the "
              f"traceback is in its {verb}.log)", file=sys.stderr)
        sys.exit(1)


COMPLETION = ("install=bash", "install=zsh", "install=fish", "uninstall=bash", "uninstall=zsh",
              "uninstall=fish")


def _shell_completion(args: list[str]) -> None:
    """`moex -sc install=bash` prints Hydra's tab completion for the config keys of every verb
    (`eval "$(moex -sc install=bash)"`); the shell then asks `moex -sc query=bash` with the line
    typed so far, from which the verb is taken out before Hydra sees it."""
    if len(args) == 1 and args[0].startswith("query="):
        words = os.environ.get("COMP_LINE", "").split(" ")
        verb = words[1] if len(words) > 1 and words[1] in VERBS else "train"
        if len(words) > 1 and words[1] in VERBS:  # "moex train ta" -> "moex ta"
            cut = len(words[1]) + 1
            os.environ["COMP_LINE"] = " ".join(words[:1] + words[2:])
            os.environ["COMP_POINT"] = str(max(int(os.environ.get("COMP_POINT", 0)) - cut, 0))
    elif len(args) == 1 and args[0] in COMPLETION:
        verb = "train"
    else:
        print(f"moex: error: --shell-completion takes one of {', '.join(COMPLETION)}; e.g. "
              f'eval "$(moex -sc install=bash)"', file=sys.stderr)
        sys.exit(2)
    register_configs()
    sys.argv = ["moex", "-sc", args[0]]
    hydra.main(version_base="1.3", config_path=CONF_DIR,
               config_name=VERBS[verb][0])(VERBS[verb][1])()
