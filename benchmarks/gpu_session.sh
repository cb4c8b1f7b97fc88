#!/usr/bin/env bash
# Everything the GPU backend is measured by, on one GPU in two calls of at most 8 minutes each
# (a device visit allows 10 minutes a command), or on the CPU at toy sizes (--smoke, Triton's
# interpreter) so that CI runs the same script and it never reaches a GPU untried.
# The first call (the default: sections 0, 2, 4, 5; about 7.5 minutes at most) gives the numbers
# that matter; the second (--only 1,3) the compiled tests and the sweeps:
#   0. pre-flight: imports, versions, the GPU's name, every backend's availability;
#   1. the gpu-parametrised tests compiled on CUDA (law tests, float32, closed loop, symbols,
#      trajectories: every test id that holds "gpu", the CPU-only smoke and AOT tests left out),
#      in half as many pytest-xdist workers as the machine has cores;
#   2. ms per network-epoch of both phases, backend=gpu, 90 networks (a Table 2 batch) and 900,
#      float64 and float32, phase 2 with input noise drawn on the device (90), beside backend=cpu
#      on all cores, with each kernel's registers/spills as compiled (to set beside
#      benchmarks/gpu_aot.py's prediction, BENCHMARKS.md);
#   3. warps per program and lanes per program (MOEX_GPU_WARPS, MOEX_GPU_LANE_BUDGET) swept at
#      90 networks, then the adaptive rate's candidates per call (MOEX_GPU_TRIALS 1, 4, 8);
#   4. the closed loop with one Lyapunov tangent, 90 networks x 50 samples, extrapolated to the
#      paper's 100 000 steps, backend=gpu beside backend=cpu on all cores;
#   5. Table 2 packed (the three P values as one batch of 90 networks) at a tenth of the paper's
#      training (3000 + 1000 steps), full evaluation (wall seconds).
# Usage: bash benchmarks/gpu_session.sh [--smoke] [--only 0,1,2,3,4,5] [--cache FILE.tgz] OUT_DIR
# Writes OUT_DIR/gpu_session.md (the log, line by line: a call cut short keeps what finished) and
# OUT_DIR/sections.csv (section, seconds, exit code); scratch run folders go to a temporary folder
# that is removed at the end. --cache FILE.tgz: Triton's compiled kernels are read from FILE (when
# it exists) and written back to it at the end, so a second call compiles nothing the first did.
set -uo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
smoke=0; only=""; out=""; cache=""
while [ $# -gt 0 ]; do
  case $1 in
    --smoke) smoke=1 ;;
    --only) only=$2; shift ;;
    --cache) cache=$2; shift ;;
    -h|--help) sed -n 2,24p "$0"; exit 0 ;;
    -*) echo "gpu_session.sh: unknown option $1 (--smoke, --only LIST, --cache FILE)" >&2; exit 2 ;;
    *) out=$1 ;;
  esac
  shift
done
[ -n "$out" ] || { echo "usage: bash benchmarks/gpu_session.sh [--smoke] [--only 0,...,5] [--cache FILE.tgz] OUT_DIR" >&2; exit 2; }
[ -n "$only" ] || only=$([ $smoke = 1 ] && echo 0,1,2,3,4,5 || echo 0,2,4,5)
mkdir -p "$out" && out=$(cd "$out" && pwd)
log="$out/gpu_session.md"; csv="$out/sections.csv"
scratch=$(mktemp -d); trap 'rm -rf "$scratch"' EXIT
if [ -n "$cache" ]; then  # Triton's kernel cache, one file (a device call returns few files)
  cache=$(cd "$(dirname "$cache")" && pwd)/$(basename "$cache")
  export TRITON_CACHE_DIR="$scratch/triton_cache"; mkdir -p "$TRITON_CACHE_DIR"
  [ -f "$cache" ] && tar xzf "$cache" -C "$TRITON_CACHE_DIR"
fi
py=${PYTHON:-python3}  # a relative path (PYTHON=.venv/bin/python) as seen from here, not scratch
[[ $py == */* ]] && py=$(cd "$(dirname "$py")" && pwd)/$(basename "$py")
cd "$scratch"  # whatever a tool leaves in its working folder (pytest caches) goes with it
export PYTHONPATH="$here${PYTHONPATH:+:$PYTHONPATH}"
cores=$(nproc)
if [ $smoke = 1 ]; then  # the CPU, Triton's interpreter, toy sizes: every section, in ~1.5 min
  export TRITON_INTERPRET=1
  device=cpu; runs="2"; big=""; f32runs=2; size="--series 2 --length 3 --steps 1 --repeats 1 --base 0"
  lyap="--runs 2 --samples 2 --steps 5 --repeats 1"; lyap_cpu="$lyap"
  sweep_warps="4"; sweep_budget="4096"; sweep_trials="2"
  table2="task.num_series=2 task.length=8 num_runs=2 train.experts.steps=2 train.gating.steps=2 eval=quick eval.num_samples=2 eval.lyapunov_steps=10 eval.transient=2 eval.plot_steps=10 task.switch_prob=0.5"
  tests=(-m "not gpu" -k "gpu and closed_loop_kernel_leaves"); workers=0
else
  device=cuda; runs="90"; big="900"; f32runs=90; size="--steps 20 --repeats 2"
  lyap="--runs 90 --samples 50 --steps 1000 --repeats 2"; lyap_cpu="--runs 90 --samples 50 --steps 200 --repeats 1"
  sweep_warps="2 4 8"; sweep_budget="2048 4096 8192"; sweep_trials="1 4 8"
  table2="train.experts.steps=3000 train.gating.steps=1000"
  tests=(-m "gpu or not slow" -k "gpu and not smoke and not aot")
  workers=$(( cores / 2 ))  # compiles in parallel; each worker holds its own CUDA context
fi
lim() { [ $smoke = 1 ] && echo 900 || echo "$1"; }  # a section's limit (s) on a GPU
wanted() { [[ ",$only," == *",$1,"* ]]; }
echo "section,seconds,exit_code" > "$csv"
section() {  # number, title, timeout (s), command...
  local n=$1 title=$2 limit=$3; shift 3
  wanted "$n" || return 0
  echo "## $n. $title"
  local start=$(date +%s%N)
  timeout "$limit" "$@"; local code=$?
  local ms=$(( ($(date +%s%N) - start) / 1000000 ))
  local took=$(printf '%d.%03d' $((ms / 1000)) $((ms % 1000)))
  [ $code = 124 ] && echo "(timed out after $limit s)"
  printf '%s s, exit %s\n\n' "$took" "$code"
  echo "$n,$took,$code" >> "$csv"
}
epochs() {
  $py "$here/benchmarks/bench_epochs.py" --backends gpu --device $device --threads 1 $size "$@"
}
{
  echo "# GPU session $(date -u +%FT%TZ)$([ $smoke = 1 ] && echo ' (smoke: CPU, Triton interpreter, toy sizes)')"
  section 0 "pre-flight" $(lim 45) $py -c '
import platform, torch, triton, numba, hydra, moex
from moex.kernels import REGISTRY, available
print("python", platform.python_version(), "torch", torch.__version__, "triton",
      triton.__version__, "numba", numba.__version__, "hydra", hydra.__version__)
print("GPU:", torch.cuda.get_device_name() if torch.cuda.is_available() else "none (CPU)")
for name in REGISTRY:
    b, why = available(name)
    print(f"backend {name}:", f"{b.device}, {b.caps}" if b else why)'
  section 1 "gpu tests" $(lim 240) \
      $py -m pytest -q -p no:cacheprovider -o addopts="" -n $workers "${tests[@]}" "$here/tests"
  section 2 "epochs: ms per network-epoch" $(lim 150) bash -c "
      $(declare -f epochs); py=$py; here=$here; device=$device; size='$size'
      epochs --runs $runs $big --kernels
      epochs --runs $f32runs --dtype float32
      epochs --runs $runs --noise 1e-3 --phases 'phase 2'
      $py $here/benchmarks/bench_epochs.py --backends cpu --runs $runs --threads $cores $size"
  section 3 "warps x lanes per program, then candidates per call (float64, $runs networks)" \
      $(lim 220) bash -c "
      $(declare -f epochs); py=$py; here=$here; device=$device; size='$size'
      for w in $sweep_warps; do for b in $sweep_budget; do
        echo \"warps \$w, lane budget \$b:\"
        MOEX_GPU_WARPS=\$w MOEX_GPU_LANE_BUDGET=\$b epochs --runs $runs | tail -3
      done; done
      for k in $sweep_trials; do
        echo \"adaptive-rate candidates per call \$k:\"
        MOEX_GPU_TRIALS=\$k epochs --runs $runs | tail -3
      done"
  section 4 "closed loop with one tangent" $(lim 90) bash -c "
      $py $here/benchmarks/bench_lyapunov.py $lyap --threads 1 --backends gpu --device $device --kernels
      $py $here/benchmarks/bench_lyapunov.py $lyap_cpu --threads $cores --backends cpu"
  section 5 "Table 2 packed: a tenth of the training, full evaluation" $(lim 180) \
      bash -c "cd $scratch && $py -c 'from moex.cli import main; main()' train -m \
      experiment=paper_table2 hydra/launcher=packed backend=gpu device=$device $table2 \
      hydra.sweep.dir=$scratch/table2 > $scratch/table2.log 2>&1; code=\$?
      grep -E \"paper's criterion|chaotic|sweep folder|rror\" $scratch/table2.log
      cp $scratch/table2/jobs.csv $out/table2_jobs.csv
      head -1 \$(ls $scratch/table2/*/metrics.csv | head -1) > $out/table2_metrics.csv
      for m in $scratch/table2/*/metrics.csv; do tail -n +2 \$m; done >> $out/table2_metrics.csv
      exit \$code"
} 2>&1 | tee "$log"
[ -n "$cache" ] && tar czf "$cache" -C "$TRITON_CACHE_DIR" . && echo "kernel cache: $cache"
failed=$(awk -F, 'NR > 1 && $3 != 0' "$csv" | wc -l)
echo "gpu_session.sh: $(($(wc -l < "$csv") - 1)) sections, $failed failed; log $log"
[ "$failed" = 0 ]
