#!/usr/bin/env bash
# Everything the GPU backend's issue measures, in one run of about 5 minutes on one GPU (its
# timeouts add up to 5.6 min):
#   1. the `gpu` test suite (Triton kernels compiled, not interpreted, against the CPU backend);
#   2. ms per network-epoch of both phases, backend=gpu, for a Table 2 batch (90 networks) and
#      900 networks, float64 and float32, beside backend=cpu on all of the machine's cores;
#   3. the closed loop with one Lyapunov tangent, 90 networks x 50 samples, extrapolated to the
#      paper's 100 000 steps, backend=gpu beside backend=cpu on all cores;
#   4. Table 2 end to end at a tenth of the paper's training (3 jobs one after another) and the
#      evaluation at full length, so the full run's time is 10x the training part + evaluation.
# Usage: bash benchmarks/gpu_session.sh [OUT_DIR]  (writes gpu_session.md there; default .)
# Needs moex importable (pip install -e ., or PYTHONPATH=. with Hydra installed beside torch).
set -uo pipefail
out=${1:-.}
mkdir -p "$out"
log="$out/gpu_session.md"
py=${PYTHON:-python3}
cores=$(nproc)
{
  echo "# GPU session $(date -u +%FT%TZ)"
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  $py -c 'import torch, triton; print("torch", torch.__version__, "triton", triton.__version__)'
  echo "## 1. gpu tests"
  timeout 60 $py -m pytest -q -o addopts="" -m gpu tests/test_kernels.py 2>&1 | tail -5
  echo "## 2. epochs (best of 2, 20 epochs each)"
  timeout 60 $py benchmarks/bench_epochs.py --backends gpu --device cuda --runs 90 900 \
      --threads 1 --steps 20 --repeats 2
  timeout 25 $py benchmarks/bench_epochs.py --backends gpu --device cuda --runs 90 \
      --threads 1 --steps 20 --repeats 2 --dtype float32
  timeout 45 $py benchmarks/bench_epochs.py --backends cpu --runs 90 --threads "$cores" \
      --steps 5 --repeats 1
  echo "## 3. closed loop with one tangent"
  timeout 25 $py benchmarks/bench_lyapunov.py --runs 90 --samples 50 --steps 1000 \
      --threads 1 --backends gpu --device cuda
  timeout 30 $py benchmarks/bench_lyapunov.py --runs 90 --samples 50 --steps 200 \
      --threads "$cores" --backends cpu
  echo "## 4. Table 2 at 1/10 of the training, full evaluation (wall time)"
  /usr/bin/time -f "%e s wall" timeout 90 $py -c 'from moex.cli import main; main()' train -m experiment=paper_table2 \
      backend=gpu device=cuda train.experts.steps=3000 train.gating.steps=1000 \
      hydra.sweep.dir="$out/table2_tenth" 2>&1 | grep -E "s wall|λ_max positive|Error" || true
} 2>&1 | tee "$log"
