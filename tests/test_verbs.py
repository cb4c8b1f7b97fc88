"""moex.verbs: the command line's verbs, a module each."""

import subprocess
import sys


def test_every_verb_is_one_module_with_its_config_a_check_and_a_run():
    """The CLI's verbs are `moex.verbs.VERBS`: each module names its verb and its Hydra config
    (a YAML in conf/; None for `report`, which reads its arguments in `main`) and has
    `check(cfg)` and `run(cfg, out_dir, stop)`."""
    import inspect

    from moex import cli, config, verbs

    assert list(verbs.VERBS) == ["train", "evaluate", "generate", "import", "segment", "report"]
    assert list(cli.VERBS) == [name for name in verbs.VERBS if name != "report"]
    for name, module in verbs.VERBS.items():
        assert module.NAME == name
        assert list(inspect.signature(module.run).parameters)[1:] == ["out_dir", "stop"]
        assert callable(module.check)
        if module.CONFIG is None:
            assert callable(module.main) and name not in cli.VERBS
            continue
        assert cli.VERBS[name][0] == module.CONFIG
        assert (config.CONF_DIR / f"{module.CONFIG}.yaml").exists()
        assert cli.VERBS_CHECK[module.CONFIG] is module.check


def test_report_refuses_a_missing_folder_and_one_without_jobs_in_one_line(tmp_path):
    for folder, message in ((tmp_path / "nope", f"{tmp_path / 'nope'} is not a folder"),
                            (tmp_path, f"{tmp_path} holds no job folder (.hydra/config.yaml)")):
        done = subprocess.run([sys.executable, "-c", "from moex.launch import main; main()",
                               "report", str(folder)], capture_output=True, text=True,
                              timeout=300)
        assert done.returncode == 2
        assert done.stderr.strip().splitlines() == [f"moex: error: {message}"], done.stderr
