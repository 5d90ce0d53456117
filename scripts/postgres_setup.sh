#!/usr/bin/env bash
# Make sure the PostgreSQL result log's tests have a PostgreSQL server to start (Debian's
# `postgresql`: initdb, pg_ctl, postgres), as bootstrap.sh does libzbar0: installed with apt-get
# when we are root and it is missing; quick when it is present. The tests start a private
# cluster of their own in a temporary directory (tests/helpers/postgres.py); nothing here
# starts, configures or enables the system's cluster.
#
# Prints one line on success:
#     bindir=/usr/lib/postgresql/15/bin
# Exits 77 (the "skipped" code, as browser_setup.sh) with a one-line reason on stderr where it
# cannot install it: not root, or no apt-get.
set -euo pipefail

find_bindir() {
    local dir
    # Debian keeps each major version's programs in /usr/lib/postgresql/N/bin; take the newest.
    for dir in $(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V -r); do
        if [ -x "$dir/initdb" ] && [ -x "$dir/pg_ctl" ] && [ -x "$dir/postgres" ]; then
            echo "$dir"
            return 0
        fi
    done
    if command -v initdb >/dev/null 2>&1 && command -v pg_ctl >/dev/null 2>&1; then
        dirname "$(command -v pg_ctl)"
        return 0
    fi
    return 1
}

# One installer at a time: parallel test workers (pytest-xdist) may all find it missing at once.
exec 8>/tmp/cellvision-apt.lock
flock 8
if ! find_bindir >/dev/null; then
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "postgres_setup: PostgreSQL is missing and there is no apt-get to install it" >&2
        exit 77
    fi
    if [ "$(id -u)" != "0" ]; then
        echo "postgres_setup: PostgreSQL is missing; install it as root: apt-get install postgresql" >&2
        exit 77
    fi
    echo "postgres_setup: installing postgresql with apt-get" >&2
    log="/tmp/postgres_setup.$$.log"
    if ! { DEBIAN_FRONTEND=noninteractive apt-get update -qq -o DPkg::Lock::Timeout=300 &&
           DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -o DPkg::Lock::Timeout=300 \
               --no-install-recommends postgresql; } >"$log" 2>&1; then
        echo "postgres_setup: apt-get install postgresql failed: $(tail -n 1 "$log")" >&2
        rm -f "$log"
        exit 77
    fi
    rm -f "$log"
fi
exec 8>&-

bindir="$(find_bindir)" || { echo "postgres_setup: initdb not found after installing postgresql" >&2; exit 77; }
echo "bindir=$bindir"
