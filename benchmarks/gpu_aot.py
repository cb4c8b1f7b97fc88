"""The gpu backend's Triton kernels compiled for an NVIDIA H200 (sm_90a) on a machine without a
GPU: per kernel and size, registers, local memory (spills), shared memory and the warp shuffles
and barriers of its machine code, checked against `BUDGET`.

    python benchmarks/gpu_aot.py [--sizes table2 table2_f32 ...] [--csv OUT.csv]

How: at each size (`SIZES`: the task's own data and model sizes, as users run them) a phase-1
step (fixed and adaptive rate), a phase-2 step and an evaluation (the closed loop with its
Lyapunov tangent, the symbol reader) run on the gpu backend with every Triton launch recorded
instead of run: nothing is computed, the host code sees zeros. Each distinct launch (kernel,
argument types, constexprs, warps) is then compiled by `triton.compile(ASTSource(...),
target=GPUTarget("cuda", 90, 32))`; the ptxas bundled with Triton, run on the PTX with the flags
Triton gives it, reports registers and spills, and nvdisasm reads the cubin's SASS. Shuffles
(SHFL) and barriers (BAR) are counted in the machine code as written: a loop's body once (the
time loop's body is most of each kernel), not per executed step. Exit code 1 when a kernel is
over its budget.
"""

import argparse
import contextlib
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

SIZES = {  # name: (Hydra overrides, what it is)
    "table2": (["task=lissajous2"], "Table 2: 2 experts of M 10, gating NC 15, 10 x 1000 steps"),
    "table2_f32": (["task=lissajous2", "precision=float32"], "Table 2 in float32"),
    "table1_nc20": (["task=reber"], "Table 1: Reber, 7 symbols, NC 20, 4 x 500 steps"),
    "table1_nc50": (["task=reber", "model.gating.context_size=50"], "Table 1 at NC 50"),
    "lissajous9": (["task=lissajous9"], "Figs. 10-13: 24 experts, NC 30, τ 5, 1 x 10 000 steps"),
}
TRAINING = ("rnn_forward", "rnn_backward", "rnn_weight_gradients", "mixture_objective",
            "softmax_objective", "momentum_kernel", "noise_kernel")
# kernels that promise the CPU's bits (the momentum step, the input noise): compiled without
# fused multiply-adds, so their PTX may hold none (`fma` below: fma.rn instructions)
EXACT = ("momentum_kernel", "noise_kernel")
# the most each kernel may use at any size above (registers per thread, SHFL and BAR
# instructions in its machine code); a training kernel may not spill at all (BENCHMARKS.md,
# "Compiled for an H200", states these and the redesign's goals beside them)
BUDGET = {  # the counts at the sizes above on 2026-12-04 (4 warps), rounded up: no worse
    "rnn_forward": {"registers": 96, "shuffles": 0, "barriers": 4},  # by columns (2026-12-04)
    "rnn_backward": {"registers": 255, "shuffles": 32, "barriers": 24},  # by columns too
    "rnn_weight_gradients": {"registers": 255, "shuffles": 330, "barriers": 30},
    "momentum_kernel": {"registers": 96, "shuffles": 8, "barriers": 6},
    "noise_kernel": {"registers": 96, "shuffles": 0, "barriers": 0},  # 2026-12-07: 90
    "mixture_objective": {"registers": 255, "shuffles": 330, "barriers": 30},
    "softmax_objective": {"registers": 112, "shuffles": 330, "barriers": 2},
    "closed_loop_kernel": {"registers": 255, "shuffles": 512, "barriers": 128},  # by columns
    "nearest_kernel": {"registers": 192, "shuffles": 340, "barriers": 24},
}
TYPES = {torch.float64: "*fp64", torch.float32: "*fp32", torch.int64: "*i64",
         torch.int32: "*i32", torch.int16: "*i16", torch.int8: "*i8", torch.bool: "*i1"}


@dataclass
class Launch:
    size: str
    kernel: object  # the JITFunction
    signature: dict
    constexprs: dict
    num_warps: int
    num_stages: int | None = None  # Triton's default where a launch does not say
    options: dict = field(default_factory=dict)  # compile options a launch sets (fp fusion)

    @property
    def name(self) -> str:
        return self.kernel.fn.__name__

    def key(self) -> tuple:
        return (self.name, tuple(sorted(self.signature.items())),
                tuple(sorted((k, repr(v)) for k, v in self.constexprs.items())), self.num_warps,
                self.num_stages, tuple(sorted(self.options.items())))


def signature(kernel, args, kwargs) -> tuple[dict, dict]:
    """The ASTSource signature and constexprs of one launch's arguments (a Python int as i32
    or i64 by its value, the int 1 as the constant 1 unless the kernel says not to specialize
    that argument, a float as fp32, as Triton's launcher types them)."""
    types, constexprs = {}, {}
    for i, param in enumerate(kernel.params):
        value = args[i] if i < len(args) else kwargs.get(param.name, param.default)
        if param.is_constexpr:
            types[param.name], constexprs[param.name] = "constexpr", value
        elif isinstance(value, torch.Tensor):
            types[param.name] = TYPES[value.dtype]
        elif isinstance(value, bool):
            types[param.name] = "i1"
        elif isinstance(value, int) and value == 1 and not param.do_not_specialize:
            types[param.name], constexprs[param.name] = "constexpr", 1
        elif isinstance(value, int):
            types[param.name] = "i32" if -2**31 <= value < 2**31 else "i64"
        elif isinstance(value, float):
            types[param.name] = "fp32"
        else:
            raise TypeError(f"{kernel.fn.__name__}: argument {param.name} is a {type(value)}")
    return types, constexprs


@contextlib.contextmanager
def recording(size: str, into: list[Launch]):
    """Every Triton launch in the block appended to `into` instead of run; the gpu backend
    usable on the CPU meanwhile."""
    from triton.runtime.jit import JITFunction

    from moex.kernels import gpu

    def run(kernel, *args, **kwargs):  # JITFunction.run(*args, grid, warmup, **kwargs)
        types, constexprs = signature(kernel, args, kwargs)
        into.append(Launch(size, kernel, types, constexprs, kwargs.get("num_warps", 4),
                           kwargs.get("num_stages"), {k: kwargs[k] for k in ("enable_fp_fusion",)
                                                      if k in kwargs}))

    saved = JITFunction.run, gpu.available
    JITFunction.run, gpu.available = run, (lambda device: True)
    try:
        yield
    finally:
        JITFunction.run, gpu.available = saved


def config(overrides: list[str]):
    from hydra import compose, initialize_config_dir

    from moex.cli import register_configs, typed
    from moex.config import CONF_DIR

    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return typed(compose("config", overrides=overrides + ["num_runs=2"]))


def record(size: str, evaluation: bool = True) -> list[Launch]:
    """The launches of one phase-1 step at each rate, two phase-2 steps and (`evaluation`) an
    evaluation."""
    from moex.closed_loop import CHUNK, closed_loop_lyapunov, generate, trained_state
    from moex.data import load_task
    from moex.jobs import run_seeds
    from moex.kernels import get_backend
    from moex.model import init_experts, init_gating, random_state
    from moex.train import phase2_targets, train_experts, train_gating

    cfg = config(SIZES[size][0])
    dtype = getattr(torch, cfg.precision)
    data = load_task(cfg)
    series = torch.as_tensor(data.series, dtype=dtype)
    S, _, D = series.shape
    gens = [torch.Generator().manual_seed(s) for s in run_seeds(0, cfg.num_runs)]
    launches = []
    with recording(size, launches):
        backend = get_backend("gpu", "cpu")
        experts, beta = {}, None
        if D > 0:
            experts = init_experts(cfg.model, S, D, gens, dtype)
            for adaptive in (False, True):
                cfg.train.experts.steps, cfg.train.experts.adaptive_lr = 1, adaptive
                experts, beta, _ = train_experts(experts, series, cfg.model, cfg.train.experts,
                                                 cfg.train, backend=backend)
        targets = phase2_targets(beta, data, cfg.num_runs, dtype,
                                 cfg.train.gating.target_temperature)
        gating = init_gating(cfg.model, S, D, gens, dtype)
        # two steps with input noise: its kernel launched at step 0 and step 1 (the int 1 is
        # a constant to Triton's launcher: a kernel must compile with it)
        cfg.train.gating.steps, cfg.train.gating.input_noise_var = 2, 1e-3
        gating, _ = train_gating(gating, targets, series[:, :targets.shape[2]], cfg.model,
                                 cfg.train.gating, rule=cfg.train, backend=backend)
        if not evaluation:
            return launches
        # the evaluation's kernels as `moex.evaluate` calls them (its metrics are not computed:
        # they would read the kernels' unwritten outputs): the closed loop from the trained
        # states, then λ_max with its tangent over a transient and counted chunks, the symbols
        # of every chunk read on the device
        state = trained_state(experts, gating, targets, series, delay=cfg.model.delay)
        generate(experts, gating, state, targets.shape[2], backend=backend)
        start = random_state(experts, gating, 4, num_features=D, delay=cfg.model.delay,
                             generator=gens[0])
        closed_loop_lyapunov(experts, gating, start, CHUNK, cfg.eval.transient, generator=gens[0],
                             on_chunk=lambda run: data.symbolize(run.outputs.numpy(),
                                                                 run.gates.numpy(),
                                                                 backend.nearest_symbols),
                             keep_potentials=10, backend=backend)
    return launches


def resources(compiled, tools: Path, ptxas: str) -> dict:
    """Registers, spilled bytes (stores) and stack frame per thread, as the ptxas Triton used
    reports them (its own flags, `triton.backends.nvidia.compiler.make_cubin`), shared memory per
    program, and the SHFL and BAR instructions of the cubin's machine code (nvdisasm)."""
    with tempfile.TemporaryDirectory() as tmp:
        ptx, cubin = Path(tmp) / "k.ptx", Path(tmp) / "k.cubin"
        ptx.write_text(compiled.asm["ptx"])
        cubin.write_bytes(compiled.asm["cubin"])
        log = subprocess.run([ptxas, "-lineinfo", "-v", "--regAllocOptLevel=2",
                              "--gpu-name=sm_90a", str(ptx), "-o", str(Path(tmp) / "k.o")],
                             capture_output=True, text=True, check=True).stderr
        sass = subprocess.run([str(tools / "nvdisasm"), str(cubin)], capture_output=True,
                              text=True, check=True).stdout
    number = {name: int(re.search(rf"(\d+) {name}", log).group(1))
              for name in ("registers", "bytes spill stores", "bytes stack frame")}
    ops = re.findall(r"^\s+/\*[0-9a-f]+\*/\s+(?:@!?U?P\w+\s+)?([A-Z][A-Z0-9_.]*)", sass, re.M)
    return {"registers": number["registers"], "spill_bytes": number["bytes spill stores"],
            "stack_bytes": number["bytes stack frame"], "shared_bytes": compiled.metadata.shared,
            "shuffles": sum(op.startswith("SHFL") for op in ops),
            "barriers": sum(op.startswith("BAR") for op in ops), "instructions": len(ops),
            "fma": len(re.findall(r"\bfma\.rn\.", compiled.asm["ptx"]))}


def compile_all(launches: list[Launch]) -> list[dict]:
    """Each distinct launch compiled for sm_90a: one row of resources each."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.backends.nvidia.compiler import get_ptxas
    from triton.compiler import ASTSource

    from moex.kernels.gpu.lanes import OPTIONS

    tools = Path(triton.__file__).parent / "backends" / "nvidia" / "bin"
    target = GPUTarget("cuda", 90, 32)
    ptxas = get_ptxas(target.arch).path
    rows, seen = [], {}
    for launch in launches:
        if launch.key() in seen:  # the same compile at another size
            sizes = seen[launch.key()]["sizes"].split()
            seen[launch.key()]["sizes"] = " ".join(dict.fromkeys([*sizes, launch.size]))
            continue
        start = time.perf_counter()
        stages = {} if launch.num_stages is None else {"num_stages": launch.num_stages}
        compiled = triton.compile(ASTSource(launch.kernel, launch.signature, launch.constexprs),
                                  target=target, options={"num_warps": launch.num_warps,
                                                          **stages, **OPTIONS, **launch.options})
        shown = {k: v for k, v in launch.constexprs.items()
                 if k in ("KT", "TANGENT", "COUNT", "KEEP_U", "LEARN_EPS", "ATTRACT", "KEEP_C",
                          "BL", "BN", "HP", "KP")}
        row = {"sizes": launch.size, "kernel": launch.name,
               "dtype": "fp32" if "*fp32" in launch.signature.values() else "fp64",
               "warps": launch.num_warps, "constexprs": " ".join(f"{k}={v}" for k, v in
                                                                 shown.items()),
               **resources(compiled, tools, ptxas),
               "compile_s": round(time.perf_counter() - start, 1)}
        seen[launch.key()] = row
        rows.append(row)
    return rows


def over_budget(row: dict) -> list[str]:
    """What of one compiled kernel exceeds its budget (a training kernel's spill included)."""
    budget = BUDGET[row["kernel"]]
    out = [f"{k} {row[k]} > {budget[k]}" for k in ("registers", "shuffles", "barriers")
           if row[k] > budget[k]]
    if row["kernel"] in TRAINING and row["spill_bytes"] > 0:
        out.append(f"spills {row['spill_bytes']} B")
    if row["kernel"] in EXACT and row["fma"] > 0:
        out.append(f"fma {row['fma']} > 0")
    return out


def main(argv: list[str] | None = None) -> int:
    import pandas as pd

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    parser.add_argument("--training", action="store_true",
                        help="the training kernels only (no evaluation: no closed loop, no "
                             "symbol reader)")
    parser.add_argument("--csv", type=Path, help="write the table here too")
    args = parser.parse_args(argv)
    launches = [launch for size in args.sizes for launch in record(size, not args.training)]
    table = pd.DataFrame(compile_all(launches))
    table["over budget"] = ["; ".join(over_budget(row)) or "-"
                            for row in table.to_dict("records")]
    if args.csv:
        table.to_csv(args.csv, index=False)
    with pd.option_context("display.width", 250, "display.max_columns", 30,
                           "display.max_colwidth", 60):
        print(table.to_string(index=False))
    bad = table[table["over budget"] != "-"]
    for row in bad.to_dict("records"):
        print(f"gpu_aot: {row['kernel']} ({row['sizes']}, {row['dtype']}) is over its budget: "
              f"{row['over budget']}", file=sys.stderr)
    return 1 if len(bad) else 0


if __name__ == "__main__":
    sys.exit(main())
