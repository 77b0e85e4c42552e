#!/usr/bin/env bash
# Create (or update) the project's virtual environment: CPU torch first, then the package with
# its ROS, interfaces, training, test, SLAM, OpenVINO, docs and Milvus extras; then build the typed
# messages (scripts/build_interfaces.sh) into it. Idempotent: re-running only reinstalls when
# setup.py changed, and only rebuilds the messages when their files changed.
#   VENV=.venv          where to create it
#   PYTHON=python3.11   interpreter (the pip ROS Jazzy wheels are cp311)
#   TORCH_SPEC=...      torch requirement; default is the CPU build used in CI. On a CUDA machine
#                       install your CUDA torch into the venv first, then run this script.
#   PAIRVPR_INTERFACES=skip  do not build pair_vpr_ros_interfaces (the node then runs without
#                       loop_closure/typed and the tests of that topic are skipped)
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3.11}
command -v "$PYTHON" >/dev/null 2>&1 || PYTHON=python3
TORCH_SPEC=${TORCH_SPEC:-torch==2.13.0}

if [ ! -x "$VENV/bin/python" ]; then
    echo "setup: creating $VENV with $($PYTHON --version)"
    "$PYTHON" -m venv "$VENV"
fi
PIP=("$VENV/bin/python" -m pip --disable-pip-version-check -q)
stamp="$VENV/.pair_vpr_ros-installed"
want=$(cat setup.py setup.cfg | sha256sum | cut -c1-16)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    "${PIP[@]}" install --upgrade pip 'setuptools<80' wheel
    # torch before the package: a bare "torch" requirement on a machine without torch pulls the
    # multi-GB CUDA build.
    "$VENV/bin/python" -c "import torch" 2>/dev/null || "${PIP[@]}" install "$TORCH_SPEC"
    "${PIP[@]}" install -e '.[ros,interfaces,train,test,slam,openvino,docs,milvus]'
    echo "$want" > "$stamp"
    echo "setup: $VENV ready ($("$VENV/bin/python" -c 'import torch; print("torch", torch.__version__)'))"
fi
if [ "${PAIRVPR_INTERFACES:-}" = skip ]; then
    echo "setup: PAIRVPR_INTERFACES=skip: pair_vpr_ros_interfaces not built"
else
    VENV="$VENV" bash scripts/build_interfaces.sh
fi
