"""moex.provenance: what produced a folder, appended once per command, timed by parts, and the
fields two folders must share for their numbers to be compared bit for bit."""

import json

import pytest

from moex import provenance


def test_a_command_appends_one_record_with_its_parts_timed(tmp_path):
    with provenance.recorded(tmp_path, "evaluate", "cpu", "cpu", "float64"):
        with provenance.part("lyapunov"):
            sum(range(1000))
        provenance.note(backend="reference")
    with provenance.recorded(tmp_path, "generate", "cpu", "cpu", "float64"):
        assert [r["verb"] for r in provenance.records(tmp_path)] == ["evaluate", "generate"]
    first, second = provenance.read(tmp_path)
    assert (first["verb"], first["backend"], second["verb"]) == ("evaluate", "reference",
                                                                 "generate")
    assert set(first["seconds"]) == {"lyapunov"}
    assert first["seconds"]["lyapunov"]["wall"] >= 0 and first["seconds"]["lyapunov"]["cpu"] >= 0
    assert {"versions", "cpu", "cpu_flags", "threads", "git", "command"} <= set(first)
    assert first["versions"]["moex"] is not None and first["versions"]["torch"] is not None


@pytest.mark.parametrize("verb, kept", [("train", True), ("evaluate", False)])
def test_a_failed_command_leaves_a_record_only_for_train(tmp_path, verb, kept):
    with pytest.raises(RuntimeError), provenance.recorded(tmp_path, verb, "cpu", "cpu",
                                                          "float64"):
        raise RuntimeError("boom")
    assert len(provenance.read(tmp_path)) == int(kept)


def test_parts_and_notes_outside_a_command_record_nothing(tmp_path):
    with provenance.part("nothing"):
        provenance.note(backend="cpu")
    assert provenance.records(tmp_path) == [] and not (tmp_path / provenance.NAME).exists()


def test_a_kept_record_is_written_by_save(tmp_path):
    with provenance.kept("fit", "cpu", "cpu", "float32") as record:
        with provenance.part("phase 1"):
            pass
    provenance.save(tmp_path / "new", record)
    [read] = provenance.read(tmp_path / "new")
    assert read["verb"] == "fit" and "phase 1" in read["seconds"]


def test_unreadable_files_read_as_no_record(tmp_path):
    (tmp_path / provenance.NAME).write_text("{not json")
    assert provenance.read(tmp_path) == []
    (tmp_path / provenance.NAME).write_text(json.dumps({"a": 1}))
    assert provenance.read(tmp_path) == []
    assert provenance.exactness_key([]) == ""
    assert provenance.summary_line([]).startswith("Provenance: not recorded")


def test_the_exactness_key_tells_folders_apart_by_its_fields_alone():
    base = {"versions": {"torch": "2"}, "cpu": "X", "cpu_flags": ["avx2"], "gpu": None,
            "backend": "cpu", "precision": "float64", "host": "a", "started": "then"}
    same = {**base, "host": "b", "started": "now"}  # not an exactness field
    other = {**base, "precision": "float32"}
    assert provenance.exactness_key([base]) == provenance.exactness_key([other, same])
    assert provenance.exactness_key([base]) != provenance.exactness_key([other])
    line = provenance.summary_line([base])
    assert "1 command(s)" in line and "backend cpu, float64" in line
