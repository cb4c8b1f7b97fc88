"""numba's cache, made to see the kernels' imports: numba keys a cached function on the source of
the file that defines it, not on the files whose functions it inlines, so an edit to `simd.py`
alone (exp, tanh, the stack arrays) would leave the cached kernels of `rnn.py` and `phases.py` in
use, and a rerun compiled afresh would then differ from one loaded from the cache. Here a kernel
file's cache entries are keyed on every source of this package instead (the same folders and
files; only the key changes), so any edit here recompiles every kernel once. Installed by the
package before any kernel module is imported (numba picks a function's cache locator when the
function is decorated). Other code's numba caches are left alone."""

from pathlib import Path

from numba.core import caching

from moex.compile_helper import KERNELS, kernel_sources


def _keyed_on_the_package(base: type) -> type:
    """`base` (one of numba's source-file cache locators) for this package's files only, with the
    digest of all its sources (`kernel_sources`) as the source stamp."""

    class Locator(base):
        folder = KERNELS

        @classmethod
        def from_function(cls, py_func, py_file):
            if Path(py_file).resolve().parent != cls.folder:
                return None
            return super().from_function(py_func, py_file)

        def get_source_stamp(self):
            return kernel_sources()

    Locator.__name__ = f"Package{base.__name__}"
    return Locator


def install() -> None:
    """Put the package's locators first in numba's list (once)."""
    classes = caching.CacheImpl._locator_classes
    if not any(c.__name__.startswith("Package") for c in classes):
        classes[:0] = [_keyed_on_the_package(b) for b in (
            caching.UserProvidedCacheLocator, caching.InTreeCacheLocator,
            caching.UserWideCacheLocator)]
