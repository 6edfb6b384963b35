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
# the lock: every third-party package at the version the tests passed with (docs/SOUP.md,
# `scripts/soup --lock` writes it); a change to it or to pyproject.toml installs again
LOCK="$ROOT/constraints.txt"
# the test install is a superset of the plain one, the native one and the console's: the demo or
# the console after the tests installs nothing
if { [ -z "$EXTRAS" ] || [ "$EXTRAS" = console ] || [ "$EXTRAS" = native ]; } \
        && [ -f "$VENV/.occ-installed-test" ] \
        && ! [ "$ROOT/pyproject.toml" -nt "$VENV/.occ-installed-test" ] \
        && ! [ "$LOCK" -nt "$VENV/.occ-installed-test" ]; then
    stamp="$VENV/.occ-installed-test"
fi
if [ ! -f "$stamp" ] || [ "$ROOT/pyproject.toml" -nt "$stamp" ] || [ "$LOCK" -nt "$stamp" ]; then
    echo "[setup] installing the project${EXTRAS:+ with [$EXTRAS]} into $VENV"
    # pip's and the build backend's notices go to a log, shown only when the install fails
    log="$VENV/occ-install.log"
    if ! { "$VENV/bin/python" -m pip install -q --upgrade pip \
            && "$VENV/bin/python" -m pip install -q -c "$LOCK" -e "$ROOT${EXTRAS:+[$EXTRAS]}"; } \
            >"$log" 2>&1; then
        cat "$log" >&2
        echo "[setup] installation failed (log: $log)" >&2
        exit 1
    fi
    touch "$stamp"
fi
# The compiled hot path (occ/_native.py) is opt-in: OCC_NATIVE=1 builds it (mypyc, the native
# extra) when missing or stale. It is not what ships: it saved 10-18 % of a daemon's CPU, under
# the quarter that would pay for a second build (docs/BENCHMARKS.md, "The compiled hot path").
# OCC_REQUIRE_NATIVE=1 makes a failed build an error.
if [ "${OCC_NATIVE:-0}" = 1 ]; then
    "$VENV/bin/python" -m pip install -q -c "$LOCK" -e "$ROOT[native]" \
        >"$VENV/occ-native-install.log" 2>&1 \
        || { cat "$VENV/occ-native-install.log" >&2; exit 1; }
    if ! "$VENV/bin/python" "$ROOT/scripts/build_native.py" --quiet; then
        if [ "${OCC_REQUIRE_NATIVE:-0}" = 1 ]; then
            echo "[setup] the compiled build was asked for and failed (OCC_REQUIRE_NATIVE=1)" >&2
            exit 1
        fi
        echo "[setup] running the pure Python hot path" >&2
    fi
fi
export PATH="$VENV/bin:$PATH"
