"""What the dead-code check cannot see used, and where each is used: `vulture moex hydra_plugins
benchmarks tools/vulture_whitelist.py --min-confidence 60` (run by .ci/run) reports everything
else that nothing uses. A name belongs here only with a user outside those folders."""

_ = object()

# Python and Hydra call these by name
__getattr__  # moex/__init__.py: the package's lazy names (PEP 562)
__dir__  # moex/__init__.py: the same, for dir(moex)
_.SLP_VECTORIZE  # moex/kernels/cpu/simd.py: a numba setting numba reads
_.align  # moex/kernels/cpu/simd.py: the alignment of an llvmlite alloca, which llvmlite prints
_.get_source_stamp  # moex/kernels/cpu/cache.py: numba's cache locator interface, numba calls it
_width, _typed, _tanh  # moex/kernels/cpu/simd.py: numba overloads, registered by @overload
TerminalFormatter  # conf/hydra/job_logging/moex.yaml names the log formatter
BarOrLines  # conf/hydra/job_logging/moex.yaml names the console filter
PackedLauncher  # conf: hydra/launcher=packed (Hydra instantiates it by its _target_)
_.setup  # Hydra's Launcher interface
_.launch  # Hydra's Launcher interface
_.num  # hydra.job.num of a sweep job, read by Hydra

# the Python API (README: "Python API"; guide/mregn.md: "The authors' C tools beside moex"), tested
lyapunov_exponents  # moex.lyapunov_exponents (moex/__init__.py names it in a string)
export_run  # moex.importer.export_run: a moex run in the C tools' files
read_targets  # moex.mregn_format.read_targets: their target files, the reader of write_targets
accepts  # moex.tasks.reber.accepts: the grammar's acceptor, which the Reber generator obeys
is_known  # moex.metrics.table.is_known: whether a column is in the one table of metrics

# the backend seam's declarations, which the tests size themselves from (tests/helpers.py)
REGISTRY  # moex.kernels.REGISTRY: every backend, for the `backend` fixture
_.caps  # Backend.caps
_.float32  # Capabilities.float32
_.interpreted  # Capabilities.interpreted
