#!/usr/bin/env bash
# The GPU check of issue #15, in one run of at most 8 minutes on a machine with CUDA:
#   1. records the machine (Python, torch, CUDA, GPU) and what differs from our pins;
#   2. installs the packages that are missing, from wheels in $WHEELS (default shared/wheels;
#      no network needed), keeping the machine's own torch;
#   3. checks that MuJoCo renders (EGL, else OSMesa);
#   4. runs the CUDA tests (tests/test_device_cuda.py) and the CPU device tests;
#   5. runs `benchmarks/bench_train.py --device cuda`: CPU, CUDA float32 and CUDA bf16 in one run.
# Everything it writes goes to $OUT (the device machine's return folder) or, without $OUT,
# to benchmarks/results/: gpu_env.json, gpu_tests.log, gpu_tests.xml, bench_train.log,
# train-cuda.json. Copy train-cuda.json to benchmarks/results/ and commit it; say in
# docs/performance.md which figures came from which device.
#
# Usage (repository root, on the GPU machine):  bash scripts/gpu_check.sh
#
# Wheels for packages the machine lacks are prepared on a machine with network access, for
# the GPU machine's Python (gpu_env.json of a first run names it; torch is never downloaded):
#   pip download -d shared/wheels --only-binary=:all: --python-version 3.X \
#       --platform manylinux2014_x86_64 --platform manylinux_2_28_x86_64 \
#       torchrl==0.14.1 tensordict==0.14.3 pyvers hoptorch cloudpickle packaging importlib_metadata orjson \
#       mujoco==3.17.0 labmaze absl-py glfw websockets pyopengl scipy pillow tqdm omegaconf pyyaml pytest pluggy iniconfig \
#       --no-deps
#   pip wheel -w shared/wheels --no-deps antlr4-python3-runtime==4.9.3   # omegaconf's, published as source only
# dm_control is left out: none of this check uses it (only the dm_control face, envs/dmc*.py,
# does), and its 56 MB wheel alone is near what a device machine can be sent.
set -uo pipefail
cd "$(dirname "$0")/.."
START=$(date +%s)
BUDGET_S=470                                  # 8 minutes, less a margin for the copy back
RESULTS="${OUT:-benchmarks/results}"
WHEELS="${WHEELS:-shared/wheels}"
mkdir -p "$RESULTS"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"   # the repository itself, no install needed
export PYTHONUNBUFFERED=1
log() { echo "[gpu_check +$(( $(date +%s) - START ))s] $*"; }
left() { echo $(( BUDGET_S - ($(date +%s) - START) )); }
limit() { local want=$1 rest; rest=$(( $(left) - 5 )); [ "$rest" -lt "$want" ] && want=$rest; [ "$want" -lt 1 ] && want=1; echo "$want"; }
status=0

# 1. the machine, and what differs from the pins (pyproject.toml: Python 3.11, torch 2.13.0)
PY_ENV=$(cat <<'EOF'
import importlib.metadata as md, json, platform, sys
info = {"python": platform.python_version(), "pins": {"python": "3.11", "torch": "2.13.0", "torchrl": "0.14.*", "tensordict": "0.14.*"}}
try:
    import torch
    info.update(torch=torch.__version__, cuda=torch.version.cuda, cuda_available=torch.cuda.is_available(),
                gpu=torch.cuda.get_device_name(0) if torch.cuda.is_available() else None, cudnn=torch.backends.cudnn.version())
except Exception as err:  # noqa: BLE001
    info["torch_error"] = repr(err)
packages = {}
for name in ("torchrl", "tensordict", "mujoco", "dm-control", "labmaze", "omegaconf", "numpy", "scipy", "pillow", "tqdm", "pytest", "matplotlib"):
    try:
        packages[name] = md.version(name)
    except md.PackageNotFoundError:
        packages[name] = None
info["packages"] = packages
info["differs_from_pins"] = [k for k, v in (("python", info["python"].startswith("3.11.")), ("torch", str(info.get("torch", "")).startswith("2.13.0"))) if not v]
print(json.dumps(info, indent=2))
EOF
)
python -c "$PY_ENV" > "$RESULTS/gpu_env.json"
log "machine: $(python -c 'import json,sys; d=json.load(open(sys.argv[1])); print(d["python"], "torch", d.get("torch"), "cuda", d.get("cuda"), d.get("gpu"))' "$RESULTS/gpu_env.json")"

# 2. missing packages, from wheels (the machine's torch stays: it is pinned by a constraint)
MISSING=$(python - <<'EOF'
import importlib.util
need = {"torchrl": "torchrl==0.14.*", "tensordict": "tensordict==0.14.*", "mujoco": "mujoco==3.17.*",
        "labmaze": "labmaze", "omegaconf": "omegaconf", "numpy": "numpy",
        "scipy": "scipy", "PIL": "pillow", "tqdm": "tqdm", "pytest": "pytest"}
print(" ".join(spec for module, spec in need.items() if importlib.util.find_spec(module) is None))
EOF
)
if [ -n "$MISSING" ]; then
  log "missing: $MISSING"
  python -c "import torch; print(f'torch=={torch.__version__}')" > /tmp/gpu_check_constraints.txt 2>/dev/null || true
  if [ -d "$WHEELS" ]; then
    timeout "$(limit 120)" python -m pip install --quiet --disable-pip-version-check --no-index --find-links "$WHEELS" \
      -c /tmp/gpu_check_constraints.txt $MISSING || log "install from $WHEELS failed"
  else
    timeout "$(limit 120)" python -m pip install --quiet --disable-pip-version-check -c /tmp/gpu_check_constraints.txt $MISSING \
      || log "no $WHEELS and no index: prepare wheels (see the header of this script)"
  fi
  python -c "$PY_ENV" > "$RESULTS/gpu_env.json"
fi
if ! python -c "import torch, torchrl, tensordict, mujoco, omegaconf, pytest; assert torch.cuda.is_available(), 'no CUDA'"; then
  log "FAILED: the packages or CUDA are missing (see $RESULTS/gpu_env.json)"
  exit 3
fi

# 3. rendering: EGL, else OSMesa (the envs render on the CPU either way)
render_ok() { timeout "$(limit 60)" python -c "import envs; from envs.nav_env import PathFollowEnv; PathFollowEnv(num_houses=1, image_size=32).reset()" >/dev/null 2>&1; }
export MUJOCO_GL="${MUJOCO_GL:-egl}"
if ! render_ok; then
  log "MUJOCO_GL=$MUJOCO_GL does not render; trying osmesa"
  export MUJOCO_GL=osmesa
  render_ok || log "osmesa does not render either: the tests that render will fail"
fi
log "MUJOCO_GL=$MUJOCO_GL"

# 4. the CUDA tests, and the CPU device tests (meta device) with them
log "tests (limit $(limit 200)s)"
timeout "$(limit 200)" python -m pytest tests/test_device_cuda.py tests/test_device.py -q -rs -p no:cacheprovider \
  --junitxml="$RESULTS/gpu_tests.xml" > "$RESULTS/gpu_tests.log" 2>&1 || status=$?
tail -n 15 "$RESULTS/gpu_tests.log"

# 5. the benchmark: CPU and CUDA measured in this one run
log "bench_train --device cuda (limit $(limit 230)s)"
timeout "$(limit 230)" python benchmarks/bench_train.py --device cuda --data-dir /tmp/bench-train \
  --out "$RESULTS/train-cuda.json" > "$RESULTS/bench_train.log" 2>&1 || status=$?
grep -v "it/s\]" "$RESULTS/bench_train.log" | tail -n 25

log "done (exit $status); files in $RESULTS"
exit "$status"
