"""moex.checkpoint: a run's state saved atomically and read back exactly; a file that is not a
usable checkpoint is refused in one line that names it, whatever is wrong with it."""

import dataclasses

import pytest
import torch

from moex import checkpoint
from moex.errors import ConfigError

NET = {name: torch.zeros(2, 3) for name in ("w_in", "w_rec", "w_out", "b_c", "b_o", "tau", "u0")}


def _record(**changes) -> checkpoint.Checkpoint:
    done = checkpoint.Checkpoint(
        {"num_runs": 2}, "done", torch.zeros(3, 10, 2, dtype=torch.float64),
        torch.zeros(3, 10, dtype=torch.int64), experts={**NET, "log_sigma": torch.zeros(2, 2)},
        beta=torch.zeros(2, 3, 10, 2), gating=dict(NET), failed=[False, True],
        data_scale={"offset": torch.ones(2), "factor": torch.ones(2)})
    return dataclasses.replace(done, **changes)


def test_a_checkpoint_reads_back_exactly_from_its_folder_or_file(tmp_path):
    saved = _record()
    saved.save(tmp_path / checkpoint.NAME)
    for where in (tmp_path, tmp_path / checkpoint.NAME):
        loaded = checkpoint.load(where)
        assert loaded.config == saved.config and loaded.failed == [False, True]
        assert torch.equal(loaded.series, saved.series) and torch.equal(loaded.beta, saved.beta)
        assert all(torch.equal(loaded.gating[k], v) for k, v in saved.gating.items())
        assert loaded.scale_arrays()["factor"].tolist() == [1.0, 1.0]
    assert sorted(p.name for p in tmp_path.iterdir()) == [checkpoint.NAME]  # no temporary left


@pytest.mark.parametrize("changes, message", [
    (dict(phase="later"), "phase 'later' is not one of experts, gating, done"),
    (dict(config={}), "its config is missing"),
    (dict(labels=torch.zeros(3, 9)), "labels do not match the series"),
    (dict(gating={k: v for k, v in NET.items() if k != "tau"}), "its gating network lacks tau"),
    (dict(gating={**NET, "u0": torch.zeros(3, 3)}), "gating.u0 is not a tensor with one entry "
                                                    r"per run \(2\)"),
    (dict(failed=None), "it says training is done but holds no trained gating network"),
    (dict(beta=None), "it says training is done but holds no trained experts"),
    (dict(phase="gating", beta=None), "phase 2 is due but phase 1's β is missing"),
])
def test_an_inconsistent_checkpoint_is_refused_naming_what_is_wrong(tmp_path, changes,
                                                                      message):
    _record(**changes).save(tmp_path / checkpoint.NAME)
    with pytest.raises(ConfigError, match=f"{checkpoint.NAME}: {message}; it is not a usable"):
        checkpoint.load(tmp_path)


def test_missing_foreign_and_future_files_are_refused(tmp_path):
    with pytest.raises(ConfigError, match=f"holds no {checkpoint.NAME}"):
        checkpoint.load(tmp_path)
    (tmp_path / checkpoint.NAME).write_bytes(b"not a torch file")
    with pytest.raises(ConfigError, match="it cannot be read"):
        checkpoint.load(tmp_path)
    torch.save({"format_version": 99}, tmp_path / checkpoint.NAME)
    with pytest.raises(ConfigError, match="its format is 99; this moex reads formats 1 and 2"):
        checkpoint.load(tmp_path)
    torch.save({"format_version": 2, "phase": "done"}, tmp_path / checkpoint.NAME)
    with pytest.raises(ConfigError, match="it lacks config, labels, series"):
        checkpoint.load(tmp_path)
