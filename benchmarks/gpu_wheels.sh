#!/usr/bin/env bash
# The wheels a device machine lacks, for benchmarks/gpu_session.sh there (its Python is 3.12 with
# torch, triton, numba, pandas and matplotlib, and no package index): hydra-core, omegaconf and
# antlr4-python3-runtime at the versions installed here, into .whl/ in the repository's root
# (ignored by git through .git/info/exclude; about 0.4 MB). antlr4-python3-runtime has no wheel on
# the index, so pip builds one from its source.
#   bash benchmarks/gpu_wheels.sh        (PYTHON=... to read the versions from another Python)
set -euo pipefail
cd "$(dirname "$0")/.."
py=${PYTHON:-.venv/bin/python}
version() { "$py" -c "import importlib.metadata as m; print(m.version('$1'))"; }
mkdir -p .whl .git/info
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo /.whl/ >> .git/info/exclude
"$py" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_17_x86_64 -d .whl "hydra-core==$(version hydra-core)" \
  "omegaconf==$(version omegaconf)"
"$py" -m pip wheel -q --no-deps -w .whl "antlr4-python3-runtime==$(version antlr4-python3-runtime)"
ls .whl
