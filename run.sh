#!/usr/bin/env bash
# One entry point for people and CI. Creates or refreshes .venv, then runs a job.
#   ./run.sh demo      the daemon driving an emulated 3-segment robot (no hardware needed)
#   ./run.sh test      the whole test suite (what CI runs)
#   ./run.sh bench [NAME…] [OPTIONS]  all benchmarks, or the named ones (on demand; prints figures)
#   ./run.sh ucr …     any ucr command inside the environment
#   ./run.sh setup     only create/refresh .venv; says which optional parts were skipped and why
#   ./run.sh pi-check  install as docs/daemon.md says inside an arm64 Debian rootfs (qemu), run it
set -euo pipefail
cd "$(dirname "$0")"
VENV=${UCR_VENV:-.venv}
PY=${PYTHON:-python3}
ALL_EXTRAS="test emulator gamepad view record ros2 tui"   # with gamepad: the 'dev' extra

# Which optional parts (pyproject extras) to install here. Platform markers leave out what has no
# wheel for this machine (reported by host/extras.py after the install); evdev, an sdist, is only
# attempted where it can be built. UCR_EXTRAS="a b" overrides the choice ("" = runtime only).
plan_extras() {
    SKIPS=()
    if [ -n "${UCR_EXTRAS+set}" ]; then
        EXTRAS=${UCR_EXTRAS//,/ }
        return
    fi
    EXTRAS="test emulator view record ros2 tui"
    local missing=()
    if [ "$(uname -s)" != Linux ]; then
        SKIPS+=("gamepad (evdev): Linux only; ucr teleop --keyboard works everywhere")
        return
    fi
    if "$VENV/bin/python" -m pip show -q evdev >/dev/null 2>&1; then
        EXTRAS="$EXTRAS gamepad"   # installed before: keep it pinned
        return
    fi
    if "$VENV/bin/python" -c "import evdev" >/dev/null 2>&1; then
        SKIPS+=("gamepad (evdev): not installed from PyPI; using the system's evdev (python3-evdev)")
        return
    fi
    command -v cc >/dev/null 2>&1 || missing+=("a C compiler")
    local inc
    inc=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
    [ -f "$inc/Python.h" ] || missing+=("Python.h")
    [ -f /usr/include/linux/input.h ] || missing+=("the kernel headers (linux/input.h)")
    if [ ${#missing[@]} -eq 0 ]; then
        EXTRAS="$EXTRAS gamepad"
    else
        local lacks
        lacks=$(printf '%s, ' "${missing[@]}")
        SKIPS+=("gamepad (evdev==2.0.0, source only): this machine lacks ${lacks%, }; for ucr teleop --device: sudo apt install build-essential python3-dev and rerun ./run.sh setup, or sudo apt install python3-evdev and UCR_VENV_SYSTEM_SITE=1 ./run.sh setup")
    fi
}

ensure_venv() {
    if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
        echo "[setup] error: ucr needs Python >= 3.11; $PY is $("$PY" -V 2>&1)" >&2
        exit 1
    fi
    if [ -x "$VENV/bin/python" ] && ! "$VENV/bin/python" -m pip --version >/dev/null 2>&1; then
        # a venv left half-made (e.g. python3-venv was missing): it has a python but no pip
        echo "[setup] $VENV has no pip (an earlier creation failed): creating it again" >&2
        rm -rf "$VENV"
    fi
    if [ ! -x "$VENV/bin/python" ]; then
        echo "[setup] creating virtual environment in $VENV" >&2
        if ! "$PY" -m venv "$VENV"; then
            rm -rf "$VENV"
            echo "[setup] error: cannot create $VENV; on Debian/Raspberry Pi OS: sudo apt install python3-venv" >&2
            exit 1
        fi
    fi
    if [ "${UCR_VENV_SYSTEM_SITE:-0}" = 1 ]; then
        # see the system's packages (e.g. Debian's python3-evdev) behind the pinned ones
        sed -i 's/^include-system-site-packages = false/include-system-site-packages = true/' \
            "$VENV/pyvenv.cfg"
    fi
    plan_extras
    local spec=.
    if [ "$(xargs -n1 <<<"$EXTRAS" | sort | xargs)" = "$(xargs -n1 <<<"$ALL_EXTRAS" | sort | xargs)" ]; then
        spec=".[dev]"
    elif [ -n "${EXTRAS// /}" ]; then
        spec=".[$(xargs <<<"$EXTRAS" | tr ' ' ',')]"
    fi
    local stamp="$VENV/.ucr-installed" report="$VENV/.ucr-setup-report"
    local want
    want=$( (cat pyproject.toml; echo "$spec"; cat "$VENV/pyvenv.cfg") | sha256sum | cut -c1-16)
    local here=$PWD venv_py=$VENV/bin/python
    [ "${venv_py#/}" != "$venv_py" ] || venv_py=$PWD/$venv_py
    if [ -f "$stamp" ] && ! (cd / && "$venv_py" - "$here" <<'PYEOF'
import importlib.util, os, sys
spec = importlib.util.find_spec("host")
here = os.path.realpath(sys.argv[1]) + os.sep
sys.exit(spec is None or not os.path.realpath(spec.origin or "").startswith(here))
PYEOF
    ) 2>/dev/null; then
        # pip's editable install and the scripts' #! lines name the checkout's absolute path: a
        # moved or copied checkout (or a .venv shared between two) imports the other one's code
        echo "[setup] $VENV was installed for another directory (checkout moved or copied?): reinstalling it for $PWD" >&2
        rm -f "$stamp"
    fi
    if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
        echo "[setup] installing $spec (pinned in pyproject.toml)" >&2
        "$VENV/bin/python" -m pip install -q --upgrade pip >&2
        "$VENV/bin/python" -m pip install -q -e "$spec" >&2
        {
            echo "[setup] installed: runtime${EXTRAS:+ + extras: $EXTRAS} ($spec)"
            for s in ${SKIPS[@]+"${SKIPS[@]}"}; do echo "[setup] skipped $s"; done
            # shellcheck disable=SC2086
            "$VENV/bin/python" -m host.extras $EXTRAS
        } > "$report"
        cat "$report" >&2
        echo "$want" > "$stamp"
        REPORTED=1
    fi
    PATH="$(dirname "$venv_py"):$PATH"
    export PATH
}

# The browser tests drive Debian's chromium (no browser download) and the TLS tests need openssl.
# Where they are missing and this is a Debian machine run as root (CI), install them; otherwise
# those tests skip and say why. UCR_NO_APT=1 never installs anything.
ensure_browser() {
    local need=()
    command -v chromium >/dev/null 2>&1 || need+=(chromium)
    command -v openssl >/dev/null 2>&1 || need+=(openssl)
    [ ${#need[@]} -eq 0 ] && return 0
    if [ "${UCR_NO_APT:-0}" != 1 ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
        echo "[setup] installing ${need[*]} (Debian packages) for the browser and TLS tests" >&2
        if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}"; } >/dev/null 2>&1; then
            echo "[setup] could not install ${need[*]}: those tests will skip and say why" >&2
        fi
    else
        echo "[setup] ${need[*]} missing: the browser/TLS tests will skip (sudo apt install ${need[*]})" >&2
    fi
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
        ensure_browser
        # Two phases (conftest.py): what can share the machine, in UCR_TEST_WORKERS (default 2)
        # pytest-xdist workers a file at a time; then, in one process, the browser files, the
        # documentation's commands and the tests that judge timing or CPU load. UCR_TEST_WORKERS=0
        # (or --collect-only) runs everything in one process. pytest exits 5 when a selection
        # collects no test: not a failure of the suite (a phase may hold none of the tests asked for).
        workers=${UCR_TEST_WORKERS:-2}
        case " $* " in *" --collect-only "*|*" --co "*) workers=0 ;; esac
        set +e
        if [ "$workers" = 0 ]; then
            "$VENV/bin/python" -m pytest "$@"
            rc=$?
            if [ "$rc" -eq 5 ]; then echo "no tests collected" >&2; rc=0; fi
        else
            "$VENV/bin/python" -m pytest -n "$workers" --dist loadfile --ucr-phase=shared "$@"
            rc1=$?
            rc2=5
            case "$rc1" in  # interrupted (2), internal (3) or usage error (4): the second phase too
                0|1|5) "$VENV/bin/python" -m pytest --ucr-phase=alone "$@"; rc2=$? ;;
            esac
            if [ "$rc1" -eq 5 ] && [ "$rc2" -eq 5 ]; then echo "no tests collected" >&2; fi
            [ "$rc1" -eq 5 ] && rc1=0
            [ "$rc2" -eq 5 ] && rc2=0
            rc=$((rc1 != 0 ? rc1 : rc2))
        fi
        set -e
        exit "$rc"
        ;;
    bench)
        # ./run.sh bench                 every benchmark with its defaults (a long run)
        # ./run.sh bench fk chain        the named ones (benchmarks/bench_<name>.py)
        # ./run.sh bench chain --duration 1   options (from the first word starting with -)
        #                                go to each named benchmark
        names=()
        while [ $# -gt 0 ] && [ "${1#-}" = "$1" ]; do names+=("$1"); shift; done
        if [ ${#names[@]} -eq 0 ] && [ $# -gt 0 ]; then
            echo "run.sh bench: options go to named benchmarks, e.g. ./run.sh bench chain $*" >&2
            echo "  (each benchmark has its own; see .venv/bin/python benchmarks/bench_<name>.py --help)" >&2
            exit 2
        fi
        files=()
        if [ ${#names[@]} -eq 0 ]; then
            files=(benchmarks/bench_*.py)
        else
            for n in "${names[@]}"; do
                f="benchmarks/bench_${n#bench_}"; f="${f%.py}.py"
                if [ ! -f "$f" ]; then
                    known=$(cd benchmarks && ls bench_*.py | sed 's/^bench_//; s/\.py$//' | tr '\n' ' ' | sed 's/ $//')
                    echo "run.sh bench: no benchmark '$n' (known: $known)" >&2
                    exit 2
                fi
                files+=("$f")
            done
        fi
        ensure_venv
        failed=()
        set +e
        for b in "${files[@]}"; do
            echo "== $b"
            "$VENV/bin/python" "$b" "$@"
            rc=$?
            if [ "$rc" -eq 130 ]; then  # Ctrl-C ends the whole run, not one benchmark
                echo "run.sh bench: interrupted in $b" >&2
                exit 130
            fi
            [ "$rc" -eq 0 ] || { failed+=("$b (exit $rc)"); echo "== $b failed (exit $rc); going on" >&2; }
        done
        set -e
        if [ ${#failed[@]} -gt 0 ]; then
            echo "run.sh bench: ${#failed[@]} of ${#files[@]} failed: ${failed[*]}" >&2
            exit 1
        fi
        echo "run.sh bench: ${#files[@]} benchmark(s) ran"
        ;;
    ucr)
        ensure_venv
        exec "$VENV/bin/ucr" "$@"
        ;;
    setup)
        ensure_venv
        [ -n "${REPORTED:-}" ] || cat "$VENV/.ucr-setup-report" 2>/dev/null || true
        ;;
    pi-check)
        ensure_venv
        exec "$VENV/bin/python" -m tools.pi_check "$@"
        ;;
    *)
        sed -n '2,8p' "$0"
        exit 2
        ;;
esac
