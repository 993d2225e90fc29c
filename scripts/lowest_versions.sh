#!/usr/bin/env bash
# Check the dependency floors of pyproject.toml: build a fresh venv holding the LOWEST version
# each `name>=X` allows (name==X), and run, with torchblur imported from this tree,
# a representative subset of the tests (spot finding with kornia, FRF/CSV/MAT/JSON with numpy
# and scipy, transfer-function fits and python-control interop, figures with matplotlib, the
# config (omegaconf), the serial protocol (pyserial), recordings (tifffile), the consistency loss).
#
# Usage (from anywhere; about 1 minute to install, a few minutes of tests on 2 cores):
#   scripts/lowest_versions.sh [VENV_DIR]            # default VENV_DIR=/tmp/torchblur-lowest
#   PIN_OVERRIDES="numpy==1.23.5 scipy==1.9.3" scripts/lowest_versions.sh   # try lower candidates
#   TESTS="tests/test_spots.py" scripts/lowest_versions.sh                     # other tests
#
# torch is not taken down to its floor: it comes from constraints-cpu.txt (torch==2.13.0, the
# CPU wheel; set CONSTRAINTS=... to use another file). Its floor, torch>=2.5.1, is kornia 0.9's
# own requirement. Floors were checked on CPython 3.11; older numpy/scipy/matplotlib releases
# than these floors lack wheels for 3.11 or were not tried.
#
# Runs on 2026-11-24 (CPython 3.11.7, torch 2.13.0+cpu), every selected test passing:
#   1. the old floors (kornia 0.9.0 instead of 0.8, numpy 1.24.0, scipy 1.10.0, matplotlib 3.7.0,
#      control 0.10.1, omegaconf 2.3.0, tqdm 4.60.0, tifffile 2023.1.23, pyserial 3.5);
#   2. numpy 1.23.2, scipy 1.9.3, matplotlib 3.6.2, omegaconf 2.2.3, tqdm 4.50.0, tifffile 2022.8.12;
#   3. numpy 1.23.2, scipy 1.9.2, matplotlib 3.6.1, omegaconf 2.1.0, tqdm 4.40.0,
#      tifffile 2021.11.2, pyserial 3.4, kornia 0.9.0, control 0.10.1; then matplotlib 3.6.0
#      (tests/test_plots.py, tests/test_control_interop.py);
#   4. this script as it stands, pins from pyproject: 270 tests passed.
# numpy 1.23.2, scipy 1.9.2 and matplotlib 3.6.0 are the oldest releases with CPython 3.11
# wheels (matplotlib 3.5 has none; the code needs >= 3.5 anyway: Figure(layout=...),
# matplotlib.colormaps). Older omegaconf/tqdm/tifffile/pyserial were not tried.
# omegaconf's antlr4 runtime (4.8/4.9) comes as an sdist: do not set PIP_ONLY_BINARY.
# Found on the way: kornia 0.8.0-0.8.3 lack kornia.contrib.connected_components_union_find
# (spot finding), and python-control 0.10.0's frd() takes no smooth= (FrequencyResponse.to_control).
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
VENV=${1:-/tmp/torchblur-lowest}
CONSTRAINTS=${CONSTRAINTS:-$ROOT/constraints-cpu.txt}
PYTHON=${PYTHON:-python3}

# name>=X in [project] dependencies -> name==X (torch left to the constraints file)
PINS=$("$PYTHON" - "$ROOT/pyproject.toml" <<'EOF'
import re, sys
text = open(sys.argv[1]).read()
deps = re.search(r"^dependencies\s*=\s*\[(.*?)\]", text, re.S | re.M).group(1)
pins = []
for name, low in re.findall(r'"([A-Za-z0-9_.-]+)\s*>=\s*([^",;\s]+)', deps):
    if name.lower() != "torch":
        pins.append(f"{name}=={low}")
print(" ".join(pins))
EOF
)
# PIN_OVERRIDES replaces the pin of the packages it names
for o in ${PIN_OVERRIDES:-}; do
    name=${o%%[=<>]*}
    PINS=$(echo "$PINS" | tr ' ' '\n' | grep -vi "^${name}==" | tr '\n' ' ')
    PINS="$PINS $o"
done
echo "lowest pins: $PINS"

"$PYTHON" -m venv "$VENV"
# shellcheck disable=SC1091
. "$VENV/bin/activate"
pip install -q -c "$CONSTRAINTS" torch $PINS pytest hypothesis
pip list 2>/dev/null | grep -iE '^(torch|kornia|numpy|scipy|matplotlib|control|omegaconf|tqdm|tifffile|pyserial) '

cd "$ROOT"   # torchblur itself from this tree (PYTHONPATH), so nothing can move the pins
TESTS=${TESTS:-"tests/test_preprocess.py tests/test_spots.py
    tests/test_frequency_response.py tests/test_model_fit.py tests/test_control_interop.py tests/test_mimo.py
    tests/test_plots.py tests/test_config_cli.py tests/test_hardware_protocol.py tests/test_hardware_units.py
    tests/test_consistency.py tests/test_consistency_module.py"}
# shellcheck disable=SC2086
PYTHONPATH="$ROOT" MPLBACKEND=Agg python -m pytest -p no:cacheprovider $TESTS   # -q comes from pyproject
