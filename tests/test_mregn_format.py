"""moex.mregn_format: the authors' C tools' save files (tests/data/mregn, written by jnamika/mregn
6a92a19's mre-learn, gn-learn and rnn-learn) read and written back byte for byte, and their target
files carrying moex's data exactly."""

from pathlib import Path

import numpy as np
import pytest

from moex.mregn_format import read_save, read_targets, write_save, write_targets

DATA = Path(__file__).parent / "data" / "mregn"


@pytest.mark.parametrize("name", ["mixture/mre.dat", "mixture/gn.dat", "gating/rnn.dat"])
def test_save_files_read_and_write_back_byte_for_byte(tmp_path, name):
    path = DATA / name
    written = write_save(tmp_path / path.name, read_save(path), path.name)
    assert written.read_bytes() == path.read_bytes()


def test_a_truncated_save_file_is_refused(tmp_path):
    (tmp_path / "mre.dat").write_bytes((DATA / "mixture/mre.dat").read_bytes()[:-100])
    with pytest.raises(ValueError, match="ends early"):
        read_save(tmp_path / "mre.dat")


def test_target_files_carry_moex_data_exactly(tmp_path):
    series = np.random.default_rng(0).uniform(-1, 1, (3, 7, 2))
    back = read_targets(write_targets(tmp_path / "t.txt", series, "header\nline two"))
    assert len(back) == 3 and all(np.array_equal(b, s) for b, s in zip(back, series, strict=True))
