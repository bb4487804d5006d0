#!/usr/bin/env bash
# Set up a fresh virtualenv in .venv-test, install glaciar[test] into it, run pytest.
# pytest exit code 5 ("no tests collected") is a failure here.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
"$PY" -m venv .venv-test
.venv-test/bin/python -m pip install --quiet --upgrade pip
.venv-test/bin/python -m pip install --quiet -e ".[test]"
set +e
# Two test processes (pytest-xdist; GLACIAR_TEST_PROCESSES overrides, 0 = in this process):
# the suite is mostly single-threaded, so on the 2-core CI machine this halves its wall time.
# By file: a module's fixtures are built once; the session's run fixtures are built once for
# both processes (tests/conftest.py: _built_once).
.venv-test/bin/python -m pytest -q -n "${GLACIAR_TEST_PROCESSES:-2}" --dist loadfile "$@"
rc=$?
set -e
if [ "$rc" -eq 5 ]; then echo "no tests collected: failing" >&2; exit 1; fi
exit "$rc"
