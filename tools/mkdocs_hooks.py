"""The site's pages are the repository's own Markdown at their repository paths (README.md the
home page, guide/, docs/, REPRODUCTION.md, BENCHMARKS.md) with the figures they show, so that
every relative link means on the site what it means in the repository, and `mkdocs build
--strict` checks each one. mkdocs reads only `docs_dir` (guide/); this hook replaces what it
found there by that set (the theme's own files stay)."""

import subprocess
from pathlib import Path

from mkdocs.structure.files import File, Files

KINDS = ("*.md", "*.png")


def on_files(files: Files, config) -> Files:
    root = Path(config.config_file_path).parent
    docs_dir = Path(config.docs_dir).resolve()
    listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard",
                             *KINDS], cwd=root, capture_output=True, text=True,
                            check=True).stdout.split()
    site = Files([f for f in files
                  if f.abs_src_path is None or docs_dir not in Path(f.abs_src_path).parents])
    for path in listed:
        if (root / path).is_file() and not path.startswith((".", "tests/")):
            site.append(File.generated(config, path, abs_src_path=str(root / path)))
    return site
