"""The reproduction's studies: the scripts that turn run folders (and the authors' C tools' runs)
into the tables, figures and verdicts of REPRODUCTION.md and docs/. Run one from the repository's
root as a module, `python -m studies.<name> [...]` (each says its commands at its top); they read
and write docs/, where the pages link their CSVs and figures. They import each other and moex
only by their public names."""
