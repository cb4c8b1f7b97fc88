"""moex.folders: a folder's lock against a second process, the job's status, a sweep's index
and summary, and the removal of what a failed evaluate or generate left empty."""

import json
import os
import subprocess
import sys

import pytest

from moex import folders
from moex.errors import ConfigError


def test_status_is_written_atomically_and_read_back(tmp_path):
    assert folders.read_status(tmp_path) == ""
    folders.write_status(tmp_path, verb="train", status="done", seconds=3.0)
    assert folders.read_status(tmp_path) == "done"
    assert json.loads((tmp_path / folders.STATUS).read_text())["seconds"] == 3.0
    (tmp_path / folders.STATUS).write_text("[1, 2]")  # not a mapping
    assert folders.read_status(tmp_path) == ""


def test_a_sweeps_index_and_summary_count_its_jobs(tmp_path):
    for job, overrides, status in (("0", ["seed=0"], "done"), ("1", ["seed=1"], "failed"),
                                   ("10", ["seed=10"], "done")):
        (tmp_path / job / ".hydra").mkdir(parents=True)
        (tmp_path / job / ".hydra" / "overrides.yaml").write_text(
            "".join(f"- {o}\n" for o in overrides))
        folders.write_status(tmp_path / job, status=status, seconds=60.0)
    folders.write_job_index(tmp_path)
    index = (tmp_path / folders.JOBS_INDEX).read_text().splitlines()
    assert index == ["folder,overrides", "0,seed=0", "1,seed=1", "10,seed=10"]  # 10 after 1
    line, failed = folders.sweep_summary(tmp_path, "train")
    assert failed == 1 and "3 jobs (2 done, 1 failed, 3.0 min)" in line
    assert f"moex report {tmp_path}" in line


def test_only_an_empty_folder_of_a_failed_evaluate_is_removed(tmp_path):
    out = tmp_path / "run" / "evaluate" / "today"
    out.mkdir(parents=True)
    (out / "evaluate.log").write_text("log")
    assert folders.discard_if_empty(out, "evaluate")
    assert not (tmp_path / "run" / "evaluate").exists() and (tmp_path / "run").is_dir()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "metrics.csv").write_text("x")
    assert not folders.discard_if_empty(kept, "evaluate") and kept.is_dir()
    assert not folders.discard_if_empty(tmp_path / "run", "train")  # a run folder, never


def test_the_last_named_folder_wins():
    args = ["hydra.run.dir=a", "seed=1", "hydra.run.dir=b"]
    assert str(folders.named_folder(args, "hydra.run.dir")) == "b"
    assert folders.named_folder(args, "hydra.sweep.dir") is None


def test_a_claimed_folder_is_refused_to_a_second_process_and_released_without_a_trace(
        tmp_path):
    args = [f"hydra.run.dir={tmp_path / 'run'}"]
    assert folders.claim(["seed=1"], False, "train", None) is None  # a new dated folder
    fd = folders.claim(args, False, "evaluate", None)
    assert (tmp_path / "run" / folders.LOCK).read_text() == str(os.getpid())
    other = subprocess.run(
        [sys.executable, "-c", "import sys; from moex import folders\n"
         "try:\n folders.claim(sys.argv[1:], False, 'evaluate', None)\n"
         "except Exception as e: print(e)", *args], capture_output=True, text=True, timeout=120)
    assert f"is being written by another moex process (pid {os.getpid()})" in other.stdout
    folders.release(fd, args, False)
    assert not (tmp_path / "run" / folders.LOCK).exists()
    folders.release(folders.claim(args, False, "evaluate", None), args, False)  # free again


def test_a_file_where_a_folder_is_named_is_refused(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigError, match="out_dir=.* is a file, not a folder"):
        folders.claim([f"hydra.run.dir={tmp_path / 'file'}"], False, "generate", None)
