#!/usr/bin/env bash
# One entry point for people and CI. Creates or refreshes .venv, then runs a job.
#   ./run.sh demo   the daemon driving an emulated 3-segment robot (no hardware needed)
#   ./run.sh test   the whole test suite (what CI runs)
#   ./run.sh bench  all benchmarks (on demand; prints figures)
#   ./run.sh ucr …  any ucr command inside the environment
set -euo pipefail
cd "$(dirname "$0")"
VENV=${UCR_VENV:-.venv}
PY=${PYTHON:-python3}

ensure_venv() {
    if [ ! -x "$VENV/bin/python" ]; then
        echo "[setup] creating virtual environment in $VENV" >&2
        "$PY" -m venv "$VENV"
    fi
    local stamp="$VENV/.ucr-installed"
    local want
    want=$(cat pyproject.toml | sha256sum | cut -c1-16)
    if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
        echo "[setup] installing dependencies (pinned in pyproject.toml)" >&2
        "$VENV/bin/python" -m pip install -q --upgrade pip >&2
        "$VENV/bin/python" -m pip install -q -e ".[dev]" >&2
        echo "$want" > "$stamp"
    fi
    export PATH="$PWD/$VENV/bin:$PATH"
}

job=${1:-help}
shift || true
case "$job" in
    demo)
        ensure_venv
        exec "$VENV/bin/ucr" demo "$@"
        ;;
    test)
        ensure_venv
        set +e
        "$VENV/bin/python" -m pytest "$@"
        rc=$?
        set -e
        # pytest exits 5 when a selection collects no test: that is not a failure of the suite.
        if [ "$rc" -eq 5 ]; then echo "no tests collected" >&2; exit 0; fi
        exit "$rc"
        ;;
    bench)
        ensure_venv
        for b in benchmarks/bench_*.py; do
            echo "== $b"
            "$VENV/bin/python" "$b" "$@"
        done
        ;;
    ucr)
        ensure_venv
        exec "$VENV/bin/ucr" "$@"
        ;;
    setup)
        ensure_venv
        ;;
    *)
        sed -n '2,7p' "$0"
        exit 2
        ;;
esac
