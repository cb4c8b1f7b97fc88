"""The command line's verbs, one module each (`moex <verb> key=value ...`). A verb module names
itself (`NAME`) and its Hydra config (`CONFIG`, a YAML in conf/) and has two functions:

- `check(cfg)`: everything the verb refuses, run before its folder is made (a `ConfigError`
  names the bad key; the CLI exits 2 and writes nothing);
- `run(cfg, out_dir, stop)`: the work, into the folder `out_dir`; `stop` (`moex.stop`) says
  when a signal asked it to stop.

A verb whose arguments are not a config (`report`: folders; `CONFIG` None) reads them itself in
`main(argv)`. A new verb is a module here, its entry in `VERBS` and its config under conf/.
"""

from moex.verbs import evaluate, generate, importing, report, segment, train

VERBS = {module.NAME: module
         for module in (train, evaluate, generate, importing, segment, report)}
