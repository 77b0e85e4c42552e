#!/usr/bin/env bash
# Run every test file alone, one after another (`pytest -x -q -m "not slow" <file>`), and list the
# files that fail alone. A file that passes inside `make test` but fails alone uses something
# only another file sets up (a fixture imported by a neighbour, a module-level side effect).
# Usage: scripts/each_test_file.sh [python] [files...]   (default: .venv/bin/python, test/**/test_*.py)
# Slow (one interpreter a file): CI checks the cheap part instead (test/core/test_test_files.py).
set -u
PY=${1:-.venv/bin/python}
shift || true
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST MPLBACKEND=Agg
if [ $# -gt 0 ]; then files=("$@"); else mapfile -t files < <(ls test/*/test_*.py | sort); fi
failed=()
for f in "${files[@]}"; do
    start=$(date +%s)
    "$PY" -m pytest -x -q -m "not slow" "$f" >/tmp/each_test_file.$$ 2>&1
    rc=$?
    # 5: every test in the file is marked slow (nothing collected) -- not a failure.
    if [ $rc -ne 0 ] && [ $rc -ne 5 ]; then
        failed+=("$f")
        echo "FAIL ($rc, $(( $(date +%s) - start )) s) $f"
        tail -n 15 /tmp/each_test_file.$$ | sed 's/^/    /'
    else
        echo "ok   ($rc, $(( $(date +%s) - start )) s) $f"
    fi
done
rm -f /tmp/each_test_file.$$
echo "${#failed[@]} of ${#files[@]} files fail alone: ${failed[*]:-none}"
[ ${#failed[@]} -eq 0 ]
