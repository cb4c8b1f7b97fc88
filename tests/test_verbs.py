"""moex.verbs: the command line's verbs, a module each."""


def test_every_verb_is_one_module_with_its_config_a_check_and_a_run():
    """The CLI's verbs are `moex.verbs.VERBS`: each module names its verb and its Hydra config
    (a YAML in conf/) and has `check(cfg)` and `run(cfg, out_dir, stop)`."""
    import inspect

    from moex import cli, config, verbs

    assert list(cli.VERBS) == list(verbs.VERBS) == ["train", "evaluate", "generate", "import",
                                                     "segment"]
    for name, module in verbs.VERBS.items():
        assert module.NAME == name and cli.VERBS[name][0] == module.CONFIG
        assert (config.CONF_DIR / f"{module.CONFIG}.yaml").exists()
        assert cli.VERBS_CHECK[module.CONFIG] is module.check
        assert list(inspect.signature(module.run).parameters)[1:] == ["out_dir", "stop"]
