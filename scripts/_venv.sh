# Sourced by scripts/test and scripts/demo: create or refresh the project's virtual environment.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${OCC_VENV:-$ROOT/.venv}"
PY="${PYTHON:-python3}"
EXTRAS="${OCC_EXTRAS:-}"
if [ ! -x "$VENV/bin/python" ]; then
    echo "[setup] creating virtual environment $VENV"
    "$PY" -m venv "$VENV"
fi
stamp="$VENV/.occ-installed${EXTRAS:+-$EXTRAS}"
# the test install is a superset of the plain one, the native one and the console's: the demo or
# the console after the tests installs nothing
if { [ -z "$EXTRAS" ] || [ "$EXTRAS" = console ] || [ "$EXTRAS" = native ]; } \
        && [ -f "$VENV/.occ-installed-test" ] \
        && ! [ "$ROOT/pyproject.toml" -nt "$VENV/.occ-installed-test" ]; then
    stamp="$VENV/.occ-installed-test"
fi
if [ ! -f "$stamp" ] || [ "$ROOT/pyproject.toml" -nt "$stamp" ]; then
    echo "[setup] installing the project${EXTRAS:+ with [$EXTRAS]} into $VENV"
    # pip's and the build backend's notices go to a log, shown only when the install fails
    log="$VENV/occ-install.log"
    if ! { "$VENV/bin/python" -m pip install -q --upgrade pip \
            && "$VENV/bin/python" -m pip install -q -e "$ROOT${EXTRAS:+[$EXTRAS]}"; } >"$log" 2>&1; then
        cat "$log" >&2
        echo "[setup] installation failed (log: $log)" >&2
        exit 1
    fi
    touch "$stamp"
fi
# The compiled hot path (occ/_native.py): built when missing or stale, where mypyc is installed
# (the native and test extras). Where it cannot be built the pure sources run, and we say so;
# OCC_REQUIRE_NATIVE=1 (CI) makes that an error, OCC_NATIVE=0 skips the build.
if [ "${OCC_NATIVE:-1}" != 0 ] && "$VENV/bin/python" -c "import mypyc" 2>/dev/null; then
    if ! "$VENV/bin/python" "$ROOT/scripts/build_native.py" --quiet; then
        if [ "${OCC_REQUIRE_NATIVE:-0}" = 1 ]; then
            echo "[setup] the compiled build is required (OCC_REQUIRE_NATIVE=1)" >&2
            exit 1
        fi
        echo "[setup] running the pure Python hot path (slower: docs/BENCHMARKS.md)" >&2
    fi
fi
export PATH="$VENV/bin:$PATH"
