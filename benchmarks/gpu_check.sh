#!/usr/bin/env bash
# The GPU run, prepared for a machine lent with an accelerator (one NVIDIA
# GPU, its own Python with torch and Triton, no package registry): builds
# torchrot from this tree in place against that torch, runs the tests of the
# accelerator path (tests/test_devices.py: Triton kernels against the scalar
# CPU kernel, backward, out=, errors, a compiled caller), then the device
# benchmark (python -m torchrot bench --device cuda). About 5 to 10 minutes on
# an H100 machine with 16 cores.
# Usage: benchmarks/gpu_check.sh [OUTPUT_DIR]   (default: $OUT, else ./gpu-results)
# Writes versions.txt, build.log, tests.log, bench.log, device.json and device.md there.
# Env: PYTHON (default python3), BENCH_DEVICE (default cuda; cpu for a dry run), DEVICE_N (the benchmark's --device-n, default its own),
#      SKIP_TESTS=1, SKIP_BENCH=1.
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-${OUT:-gpu-results}}"
python="${PYTHON:-python3}"
mkdir -p "$out"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
"$python" - <<'PY' | tee "$out/versions.txt"
import platform, torch, triton
print(f"python {platform.python_version()}, torch {torch.__version__}, triton {triton.__version__}")
print(f"device: {torch.cuda.get_device_name() if torch.cuda.is_available() else 'no CUDA device'}")
PY
start=$SECONDS
"$python" setup.py -q build_ext --inplace > "$out/build.log" 2>&1 || { tail -30 "$out/build.log"; exit 1; }
echo "built torchrot in place in $((SECONDS - start)) s"
status=0
if [[ "${SKIP_TESTS:-0}" != 1 ]]; then
  start=$SECONDS
  "$python" -m pytest -q -p no:cacheprovider tests/test_devices.py 2>&1 | tee "$out/tests.log" || status=1
  echo "tests: $((SECONDS - start)) s"
fi
if [[ "${SKIP_BENCH:-0}" != 1 ]]; then
  start=$SECONDS
  # shellcheck disable=SC2086
  "$python" -m torchrot bench --device "${BENCH_DEVICE:-cuda}" ${DEVICE_N:+--device-n $DEVICE_N} --output "$out" 2>&1 \
    | tee "$out/bench.log" || status=1
  echo "benchmark: $((SECONDS - start)) s"
fi
exit $status
