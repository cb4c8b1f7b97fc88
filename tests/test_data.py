"""moex.data: the data a config trains on, made once per process."""

import dataclasses

from moex.config import Config
from moex.data import load_task
from moex.tasks import task_config


def test_a_generated_data_set_is_built_once_per_process(monkeypatch, tmp_path):
    """`moex train` checks its config on the data (cli.validate), then trains on it: the same
    settings give the same `Dataset` object, also after other settings (a packed sweep checks
    every job, then trains them), as long as they fit the cache's bound; other settings a new
    one; a task read from files is read again (the files may have changed)."""
    from moex import data

    built = []
    make = data.make_task
    monkeypatch.setattr(data, "make_task", lambda *a, **k: built.append(a) or make(*a, **k))
    cfg = Config()
    cfg.task.num_series, cfg.task.length = 2, 50
    first = load_task(cfg)
    assert load_task(cfg) is first and len(built) == 1
    other = dataclasses.replace(cfg, seed=cfg.seed + 1)
    assert load_task(other) is not first and len(built) == 2
    assert load_task(cfg) is first and len(built) == 2  # a packed sweep: every job's, then each
    monkeypatch.setattr(data, "_BUILT_BYTES", 1)  # over the bound: only the newest is kept
    load_task(dataclasses.replace(cfg, seed=cfg.seed + 2))
    assert len(built) == 3
    assert load_task(cfg) is not first and len(built) == 4
    (tmp_path / "x.csv").write_text("0.1 0.2\n" * 20)
    files = dataclasses.replace(cfg, task=task_config("csv", path=str(tmp_path / "x.csv")))
    load_task(files)
    load_task(files)
    assert len(built) == 6
