"""The import graph of the `moex` package has no circle: every `import` statement counts, those
inside functions too (a circle closed by a function-level import still ties its modules together
and breaks as soon as someone moves the import up)."""

import ast
from pathlib import Path

import moex

ROOT = Path(moex.__file__).parent


def _modules() -> dict[str, Path]:
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = ("moex",) + path.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the moex modules it imports. `from package import submodule` is an edge to the
    submodule; `from module import name` to the module."""
    def known(name):
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name

    graph = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                edges |= {known(a.name) for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[:len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                subs = {f"{base}.{a.name}" for a in node.names} & modules.keys()
                edges |= subs | ({known(base)} if len(subs) < len(node.names) else set())
        graph[name] = edges - {"", name}
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while not component or component[-1] != v:
                component.append(stack.pop())
                on_stack.discard(component[-1])
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_package_has_no_import_circle():
    modules = _modules()
    assert "moex.kernels.cpu.phases" in modules and len(modules) > 40
    assert _circles(_graph(modules)) == []


def test_the_circle_finder_finds_a_circle():
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set()}) == []


# what the compute kernels may build on: the model's definitions and its mathematics (the
# objectives, the Lyapunov and symbol formulas the reference backend spells out), the errors, the
# draws and the compile stamp; nothing of training, evaluation, the CLI or the verbs
KERNEL_FLOOR = {"moex", "moex.model", "moex.objectives", "moex.metrics",
                "moex.metrics.lyapunov", "moex.metrics.symbols", "moex.errors", "moex.draws",
                "moex.compile_helper"}


def test_the_kernels_import_nothing_from_the_layers_above_them():
    graph = _graph(_modules())
    upward = {(name, dep) for name, deps in graph.items() if name.startswith("moex.kernels")
              for dep in deps if not dep.startswith("moex.kernels") and dep not in KERNEL_FLOOR}
    assert upward == set()
    assert {dep for name, deps in graph.items() if name.startswith("moex.kernels")
            for dep in deps} >= {"moex.model", "moex.errors"}  # the test sees their imports


def test_the_python_api_imports_no_hydra():
    """`import moex` and every public name (fit, load, evaluate, ...) run without Hydra: only
    the command line (moex.cli) composes configs with it."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", "import sys, moex\n"
                           "for name in moex.__all__: getattr(moex, name)\n"
                           "print(sorted({m.split('.')[0] for m in sys.modules} & "
                           "{'hydra', 'moex'}))"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["['moex']"]


def test_no_module_imports_another_modules_private_names():
    """A name with a leading underscore is its module's own: none is imported by another."""
    private = []
    for name, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("moex"):
                private += [(name, node.module, a.name) for a in node.names
                            if a.name.startswith("_") and not a.name.startswith("__")]
    assert private == []


COMPILED = {"njit", "device", "triton.jit", "intrinsic"}  # numba and Triton: positional ABIs


def test_functions_of_more_than_five_parameters_take_the_rest_by_keyword():
    """A call of six or more arguments names them (`f(a, b, c, d, e, *, rest)`), except the
    compiled kernels (numba, Triton), whose compilers take positions only."""
    wide = []
    for name, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            decorators = {ast.unparse(d.func if isinstance(d, ast.Call) else d)
                          for d in node.decorator_list}
            positional = node.args.posonlyargs + node.args.args
            if positional and positional[0].arg in ("self", "cls"):
                positional = positional[1:]
            if len(positional) > 5 and not decorators & COMPILED:
                wide.append(f"{name}.{node.name}")
    assert wide == []


# what the config dataclasses may build on: errors, the block KL's formulas (EvalConfig.block_kl),
# the common task config and the default task's (Config's default); no registry (backends,
# tasks), nothing that trains or evaluates
CONFIG_FLOOR = {"moex.errors", "moex.metrics.symbols", "moex.tasks.base", "moex.tasks.lissajous"}


def test_the_configs_sit_at_the_bottom_and_import_no_registry():
    graph = _graph(_modules())
    configs = {name for name in graph if name == "moex.config" or name.startswith("moex.config.")}
    assert configs >= {"moex.config", "moex.config.model", "moex.config.train",
                       "moex.config.evaluation", "moex.config.plot"}
    upward = {(name, dep) for name in configs for dep in graph[name]
              if dep not in configs and dep not in CONFIG_FLOOR}
    assert upward == set()
    for task in ("moex.tasks.base", "moex.tasks.lissajous"):  # not the registry either
        assert "moex.tasks" not in graph[task] and "moex.kernels" not in graph[task]
