#!/usr/bin/env bash
# Set up everything `make test` and `make demo` need on a fresh Debian/Ubuntu machine:
# the system library libzbar0 (for pyzbar) and a local .venv with the project installed.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${VENV:-.venv}"
PYTHON="${PYTHON:-python3}"

have_zbar() {
    ldconfig -p 2>/dev/null | grep -q 'libzbar\.so\.0' && return 0
    # ldconfig may be absent from PATH for non-root users; look in the usual places too.
    compgen -G '/usr/lib/*/libzbar.so.0' >/dev/null || compgen -G '/usr/lib/libzbar.so.0' >/dev/null
}

if ! have_zbar; then
    if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        echo "bootstrap: installing libzbar0 with apt-get"
        DEBIAN_FRONTEND=noninteractive apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libzbar0 >/dev/null
    else
        echo "bootstrap: the system library libzbar0 is missing. Install it with:" >&2
        echo "    sudo apt-get update && sudo apt-get install -y libzbar0" >&2
        exit 1
    fi
fi

"$PYTHON" - <<'PY'
import sys
if sys.version_info < (3, 11):
    sys.exit(f"bootstrap: Python >= 3.11 is needed, {sys.executable} is {sys.version.split()[0]}")
PY

stamp="$VENV/.cellvision-installed"
if [ ! -x "$VENV/bin/python" ]; then
    "$PYTHON" -m venv "$VENV"
fi
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    log="$VENV/bootstrap.log"
    echo "bootstrap: installing cellvision and its dependencies into $VENV (log: $log)"
    if ! { "$VENV/bin/python" -m pip install --upgrade pip &&
           "$VENV/bin/python" -m pip install -e ".[dev]"; } >"$log" 2>&1; then
        tail -n 40 "$log" >&2
        echo "bootstrap: pip install failed; the whole log is in $log" >&2
        exit 1
    fi
    touch "$stamp"
fi

# The Aravis camera source and its tests (issue 29): Debian's Aravis (the library, its
# introspection data and the tools with the GigE Vision emulator) and PyGObject, which builds
# against gobject-introspection and cairo. Installed as root with apt-get; elsewhere the
# Aravis tests skip and say what to install. CELLVISION_NO_ARAVIS=1 leaves it out.
aravis_stamp="$VENV/.cellvision-aravis"
aravis_debs="aravis-tools aravis-tools-cli gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config"
if [ -z "${CELLVISION_NO_ARAVIS:-}" ] && { [ ! -f "$aravis_stamp" ] || [ pyproject.toml -nt "$aravis_stamp" ]; }; then
    missing=""
    for deb in $aravis_debs; do
        dpkg -s "$deb" >/dev/null 2>&1 || missing="$missing $deb"
    done
    if [ -n "$missing" ] && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        echo "bootstrap: installing$missing with apt-get (the Aravis camera source)"
        DEBIAN_FRONTEND=noninteractive apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $missing >/dev/null
        missing=""
    fi
    if [ -n "$missing" ]; then
        echo "bootstrap: the Aravis source's tests will skip: missing Debian packages:$missing" >&2
    elif "$VENV/bin/python" -m pip install -e ".[dev,aravis]" >"$VENV/bootstrap-aravis.log" 2>&1; then
        touch "$aravis_stamp"
    else
        tail -n 20 "$VENV/bootstrap-aravis.log" >&2
        echo "bootstrap: PyGObject did not install (log: $VENV/bootstrap-aravis.log);" \
            "the Aravis source's tests will skip" >&2
    fi
fi
