#!/usr/bin/env bash
# Build the typed ROS interfaces (interfaces/pair_vpr_ros_interfaces, ament_cmake + rosidl)
# with colcon against the ROS 2 Jazzy wheels of the venv, then install them into the venv
# itself (lib/, lib/python3.X/site-packages/, share/), next to the wheels' own messages: every
# Python of the venv (tests, node processes, console scripts) imports them with no sourcing.
# Idempotent: a stamp in the venv skips the build while the package's files are unchanged.
# On a normal ROS install none of this is needed: colcon builds it in the workspace
# (docs/interfaces.md).
#   VENV=.venv                       the venv (with the `ros` and `interfaces` extras installed)
#   INTERFACES_BUILD=build/interfaces  where colcon builds (git-ignored; `make clean` removes it)
set -euo pipefail
cd "$(dirname "$0")/.."
PKG=pair_vpr_ros_interfaces
SRC=interfaces/$PKG
fail() { echo "setup: error: $*" >&2; exit 1; }
[ -x "${VENV:-.venv}/bin/python" ] || fail "no Python at ${VENV:-.venv}/bin/python: make setup" \
    "creates the venv (or give VENV=the venv with the ros and interfaces extras)"
VENV=$(cd "${VENV:-.venv}" && pwd)
WORK=${INTERFACES_BUILD:-build/interfaces}
PY="$VENV/bin/python"
[ -x "$VENV/bin/colcon" ] || fail "colcon is not installed in $VENV: pip install -e" \
    "'.[ros,interfaces]' (make setup does), or set PAIRVPR_INTERFACES=skip to go without" \
    "loop_closure/typed"
stamp="$VENV/.$PKG-built"
want=$(cat "$SRC/package.xml" "$SRC/CMakeLists.txt" "$SRC"/msg/*.msg scripts/build_interfaces.sh \
    | sha256sum | cut -c1-16)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] \
    && "$PY" -c "import $PKG.msg" 2>/dev/null; then
    exit 0
fi
start=$(date +%s)
echo "setup: building $PKG (colcon, rosidl) into $VENV"

bash scripts/wheel_cmake_paths.sh "$VENV"

rm -rf "$WORK"
mkdir -p "$WORK"
CMAKE_PREFIX_PATH="$VENV" AMENT_PREFIX_PATH="$VENV" PATH="$VENV/bin:$PATH" \
    "$VENV/bin/colcon" --log-base "$WORK/log" build --base-paths "$SRC" \
    --build-base "$WORK/build" --install-base "$WORK/install" \
    --event-handlers console_cohesion- console_direct- status- \
    --cmake-args "-DPython3_EXECUTABLE=$PY" -DBUILD_TESTING=OFF \
    > "$WORK/colcon.log" 2>&1 || {
    tail -n 40 "$WORK/colcon.log" >&2
    fail "building $PKG failed (full log: $WORK/colcon.log). The node runs without it (no" \
        "loop_closure/typed); PAIRVPR_INTERFACES=skip make setup skips it."
}
# A message removed from the package must not stay importable from an earlier build.
site=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
rm -rf "$VENV/share/$PKG" "$VENV/include/$PKG" "${site:?}/$PKG"
cmake --install "$WORK/build/$PKG" --prefix "$VENV" > "$WORK/install.log"
"$PY" -c "import $PKG.msg"
echo "$want" > "$stamp"
echo "setup: $PKG built and installed in $(($(date +%s) - start)) s"
