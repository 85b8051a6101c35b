#!/usr/bin/env bash
# GPU check, for a machine with a CUDA GPU (a few minutes; nothing here needs more than one GPU):
#   1. a virtual environment .venv-gpu with a CUDA-enabled torch and the package,
#   2. the `cuda` tests (tests/test_cuda.py: CPU/CUDA plan equality, no host round trip while planning, a short
#      learning run, save on CUDA -> load on CPU and back, bf16 planning),
#   3. benchmarks/speed/planning_speed.py --device cuda (paper-size plans, fp32 and bf16),
# and appends their rows to benchmarks/RESULTS.md (the lines added are printed at the end).
#
#     benchmarks/device_check.sh
#
# torch: the Makefile installs the CPU wheel, which cannot use a GPU, so this script keeps its own environment. It is
# made with --system-site-packages, so a CUDA-enabled torch that $PYTHON already has is reused (nothing downloaded);
# when $PYTHON has none, torch is installed from PyPI, whose Linux x86-64 wheels are built with CUDA (TORCH_SPEC,
# default "torch", and TORCH_INDEX_URL, e.g. https://download.pytorch.org/whl/cu128, pick another build).
# Without internet: PIP_NO_INDEX=1 PIP_FIND_LINKS=/folder/of/wheels benchmarks/device_check.sh
# Environment: PYTHON (default python3), VENV (default .venv-gpu), OUT (if set, the log and RESULTS.md are copied
# there too).
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
VENV=${VENV:-.venv-gpu}
PY="$VENV/bin/python"
LOG=$(mktemp -t device_check.XXXXXX.log)
BEFORE=$(mktemp -t results_before.XXXXXX.md)
TESTS_LOG=$(mktemp -t device_check_pytest.XXXXXX.log)
cp benchmarks/RESULTS.md "$BEFORE"
exec > >(tee "$LOG") 2>&1
export PYTHONUNBUFFERED=1

step() { echo; echo "== [$((SECONDS / 60))m$((SECONDS % 60))s] $*"; }

step "environment ($VENV, from $PYTHON)"
if [ ! -x "$PY" ]; then
    "$PYTHON" -m venv --system-site-packages "$VENV"
fi
if ! "$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)" 2>/dev/null; then
    echo "no CUDA-enabled torch in reach: installing ${TORCH_SPEC:-torch}${TORCH_INDEX_URL:+ from $TORCH_INDEX_URL}"
    "$PY" -m pip install -q ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"} "${TORCH_SPEC:-torch}"
fi
# torch>=2.3 is satisfied by the CUDA build above, so pip keeps it; the cuda tests need pytest only
"$PY" -m pip install -q -e . pytest
"$PY" - <<'EOF'
import sys

import torch

if not torch.cuda.is_available():
    sys.exit(
        f"torch {torch.__version__} sees no CUDA device (built for CUDA {torch.version.cuda}): check nvidia-smi, "
        "or install a CUDA build with TORCH_SPEC / TORCH_INDEX_URL"
    )
print(f"torch {torch.__version__}, CUDA {torch.version.cuda}, {torch.cuda.get_device_name()}")
EOF

step "cuda tests"
set +e
timeout 240 "$PY" -m pytest -m cuda tests/test_cuda.py -p no:cacheprovider -q -rs 2>&1 | tee "$TESTS_LOG"
tests_rc=${PIPESTATUS[0]}
set -e
tests_summary=$(grep -E "^(=+ )?[0-9]+ (passed|failed|skipped|error)" "$TESTS_LOG" | tail -1 | tr -d '=' | xargs)
if grep -q "skipped" <<<"$tests_summary"; then
    echo "some cuda tests were skipped: they did not run on the GPU"
    tests_rc=1
fi

step "planning_speed.py --device cuda (fp32 and bf16)"
set +e
timeout 180 "$PY" benchmarks/speed/planning_speed.py --device cuda --repeats 5
speed_rc=$?
set -e

step "RESULTS.md row of the tests"
"$PY" - "$tests_summary" "$tests_rc" "$SECONDS" <<'EOF'
import datetime
import os
import sys

import torch

sys.path.insert(0, "benchmarks")
from results_file import append_row, describe_machine

summary, rc, seconds = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
append_row(
    "GPU device check (`benchmarks/device_check.sh`)",
    "The `cuda` tests (tests/test_cuda.py) on a machine with a GPU; the planner's speed on it is in the "
    "planning_speed section (rows with `--device cuda`).",
    ["date", "cuda tests", "result", "script time so far", "machine"],
    [
        str(datetime.date.today()),
        summary or "no summary (see the log)",
        "pass" if rc == 0 else f"FAIL (exit {rc})",
        f"{seconds} s",
        describe_machine(torch.get_num_threads(), "cuda"),
    ],
)
EOF

step "rows added to benchmarks/RESULTS.md"
diff "$BEFORE" benchmarks/RESULTS.md | grep '^>' | cut -c3- || true
if [ -n "${OUT:-}" ]; then
    mkdir -p "$OUT"
    cp "$LOG" "$OUT/device_check.log"
    cp benchmarks/RESULTS.md "$OUT/RESULTS.md"
fi
echo
echo "device check: cuda tests exit $tests_rc, planning_speed exit $speed_rc, ${SECONDS} s in all"
[ "$tests_rc" -eq 0 ] && [ "$speed_rc" -eq 0 ]
