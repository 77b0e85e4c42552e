#!/usr/bin/env bash
# The ROS wheels' exported CMake files name the include folders of the machine that built them
# (/opt/python/cp311-cp311/...): point them at venv $1's Python and numpy headers, else CMake
# stops with "includes non-existent path". Used by build_interfaces.sh and ros_cli_env.sh.
set -euo pipefail
VENV=$1
PY="$VENV/bin/python"
py_include=$("$PY" -c "import sysconfig; print(sysconfig.get_paths()['include'])")
np_include=$("$PY" -c "import numpy; print(numpy.get_include())")
built_py=/opt/python/cp311-cp311/include/python3.11
grep -rlF /opt/python/ "$VENV/share" 2>/dev/null | while read -r f; do
    sed -i -e "s#/opt/python/[^;\"]*/numpy/_core/include#$np_include#g" \
        -e "s#$built_py#$py_include#g" "$f"
done
