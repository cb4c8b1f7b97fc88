"""Tab completion that answers at once: `moex -sc query=bash` (what the script of `moex -sc
install=bash` asks on every Tab) is answered here from `completion_keys.json`, without importing
Hydra or PyTorch (3-5 s each). Verbs first; then a verb's config groups (`task=`), a group's
options (`task=reber`) and its keys one level at a time (`eval.` -> `eval.noise_var=`); after
`report`, folders. `python -m moex.completion` writes the key file from the configs (a test
checks it is current)."""

import dataclasses
import json
import os
import sys
from pathlib import Path

VERBS = ("train", "evaluate", "generate", "import", "segment", "report")
KEYS = Path(__file__).with_name("completion_keys.json")
CONFIGS = {"train": "config", "evaluate": "evaluate", "generate": "generate", "import": "import",
           "segment": "segment"}


def candidates(line: str) -> list[str]:
    """The completions of the last word of `line` (the command line up to the cursor)."""
    words = line.split(" ")
    word = words[-1]
    if len(words) <= 2:  # the verb itself
        return [v for v in VERBS if v.startswith(word)]
    verb = words[1]
    if verb == "report":
        return _folders(word)
    if verb not in CONFIGS:
        return []
    table = json.loads(KEYS.read_text())[verb]
    if "=" in word:  # a group's options
        group = word.split("=", 1)[0]
        return [f"{group}={o}" for o in table["groups"].get(group, [])
                if f"{group}={o}".startswith(word)]
    found = {f"{g}=" for g in table["groups"] if g.startswith(word)}
    for key in table["keys"]:
        if key.startswith(word):  # one level beyond what is typed
            rest = key[len(word):]
            cut = rest.find(".", 1 if rest.startswith(".") else 0)
            found.add(word + (rest[:cut + 1] if cut >= 0 else rest + "="))
    return sorted(found)


def _folders(word: str) -> list[str]:
    """Folders whose path starts with `word` (a run or sweep folder for `moex report`)."""
    head, _, _ = word.rpartition("/")
    base = Path(head or ".")
    if not base.is_dir():
        return []
    prefix = f"{head}/" if head else ""
    return sorted(f"{prefix}{p.name}/" for p in base.iterdir()
                  if p.is_dir() and f"{prefix}{p.name}".startswith(word))


def answer() -> None:
    """Print the completions of $COMP_LINE up to $COMP_POINT, one per line."""
    line = os.environ.get("COMP_LINE", "")
    line = line[:int(os.environ.get("COMP_POINT", len(line)))]
    print("\n".join(candidates(line)))


def table() -> dict:
    """Every verb's groups (with their options) and dotted keys, from the composed configs."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    from moex.cli import dotted_keys, register_configs
    from moex.config import CONF_DIR
    from moex.tasks import TASKS

    register_configs()
    GlobalHydra.instance().clear()
    out = {}
    for verb, name in CONFIGS.items():
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            root = compose(name)
        keys = {k for k in dotted_keys(OmegaConf.to_container(root, resolve=False))
                if not k.startswith(("hydra", "task."))}
        if verb in ("train", "import"):  # a `Config`'s task: every task's own keys
            keys |= {f"task.{f.name}" for task in TASKS.values()
                     for f in dataclasses.fields(task.config)}
        else:
            keys |= {k for k in dotted_keys(OmegaConf.to_container(root, resolve=False))
                     if k.startswith("task.")}
        defaults = OmegaConf.load(Path(CONF_DIR) / f"{name}.yaml").get("defaults", [])
        named = {next(iter(d)) for d in defaults if OmegaConf.is_dict(d)}
        groups = {g.name: sorted(p.stem for p in g.glob("*.yaml"))
                  for g in sorted(Path(CONF_DIR).iterdir())
                  if g.is_dir() and g.name != "hydra" and (verb == "train" or g.name in named)}
        if verb == "train":
            groups["hydra/launcher"] = sorted(
                ["basic", "packed", *(p.stem for p in (Path(CONF_DIR) / "hydra" / "launcher")
                                      .glob("*.yaml"))])
        out[verb] = {"groups": groups, "keys": sorted(keys)}
    return out


if __name__ == "__main__":
    KEYS.write_text(json.dumps(table(), indent=1, sort_keys=True) + "\n")
    print(f"wrote {KEYS}", file=sys.stderr)
