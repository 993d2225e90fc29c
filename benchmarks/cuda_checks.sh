#!/usr/bin/env bash
# The GPU checks of one short device session, in one script (the code's only CUDA runs: CI has no GPU).
#
#   bash benchmarks/cuda_checks.sh OUTDIR [SECONDS] [STEPS...]
#
# Run from the repository root on a machine with CUDA and the project's dependencies importable
# (torchblur itself from this checkout: PYTHONPATH gets $PWD). Each step's printout goes to
# OUTDIR/<step>.txt and to stdout; every step runs under `timeout`, and the whole stays inside
# SECONDS (default 540): a step that would start with under 20 s left is skipped and says so.
# Steps (default all, in this order):
#   tests     the tests parametrised over CUDA (tests/test_dm_kernel.py, tests/test_camera.py)
#   bench     benchmarks/bench_cuda.py: renderer, gradients, kernel render, sinusoid fits (Gaussian
#             and kernel PSF), the ladder spot fit, bench_dm.py's three mirrors, each against the CPU
#   quick     benchmarks/bench_dm_hcipy.py --quick --case aligned on CUDA (the figures to set beside
#             the CPU run's; the run kept as OUTDIR/quick_aligned.pkl)
#   full      the same with the full plan (16 frequencies x 2 repeats, 4096 frames): issue 23's
#             done-when grid (OUTDIR/full_aligned.pkl)
#   misreg    the full plan on the misregistered mirror (OUTDIR/full_misregistered.pkl)
set -u
out=${1:?usage: bash benchmarks/cuda_checks.sh OUTDIR [SECONDS] [STEPS...]}
budget=${2:-540}
shift $(($# >= 2 ? 2 : 1))
steps=${*:-tests bench quick full misreg}
end=$((SECONDS + budget))
mkdir -p "$out"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
jobs=$(nproc)
dev=${DEVICE:-cuda}  # DEVICE=cpu: the same steps on the CPU (a check of this script)

run() {  # run STEP SECONDS_AT_MOST CMD...: under timeout, within what is left of the budget
  local step=$1 most=$2; shift 2
  local left=$((end - SECONDS - 5))
  local t=$((most < left ? most : left))
  if ((t < 20)); then echo "== $step: skipped, ${left} s left of the budget" | tee "$out/$step.txt"; return; fi
  echo "== $step (at most $t s): $*"
  local t0=$SECONDS
  timeout "$t" "$@" 2>&1 | tee "$out/$step.txt"
  echo "== $step: rc ${PIPESTATUS[0]}, $((SECONDS - t0)) s" | tee -a "$out/$step.txt"
}

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null
python3 -c "import torch, kornia, omegaconf, control, scipy, numpy; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.is_available() and torch.cuda.get_device_name(0), '| kornia', kornia.__version__, '| control', control.__version__, '| numpy', numpy.__version__, '| scipy', scipy.__version__)"
for s in $steps; do
  case $s in
    tests) run tests 120 python3 -m pytest -q -o addopts= -p no:cacheprovider tests/test_dm_kernel.py tests/test_camera.py -k cuda ;;
    bench) run bench 240 python3 benchmarks/bench_cuda.py --device "$dev" --fit-sizes 1000 20000 --kernel-fit-sizes 100 5000 ;;
    quick) BENCH_DM_HCIPY_SAVE=$out/quick run quick 200 python3 benchmarks/bench_dm_hcipy.py --quick --case aligned --no-checks --device "$dev" --jobs "$jobs" ;;
    full) BENCH_DM_HCIPY_SAVE=$out/full run full 600 python3 benchmarks/bench_dm_hcipy.py --case aligned --no-checks --device "$dev" --jobs "$jobs" --progress ;;
    misreg) BENCH_DM_HCIPY_SAVE=$out/full run misreg 600 python3 benchmarks/bench_dm_hcipy.py --case misregistered --no-checks --device "$dev" --jobs "$jobs" --progress ;;
    *) echo "unknown step $s (tests bench quick full misreg)"; exit 2 ;;
  esac
done
for f in "$out"/*.pkl; do  # the saved runs, compressed (a full run's is ~16 MB)
  [ -e "$f" ] && xz -T0 -6 "$f" && ls -la "$f.xz"
done
echo "== total $SECONDS s"
