#!/usr/bin/env bash
# Make sure the MQTT publisher's tests have an MQTT broker to start (Debian's `mosquitto` and
# its `mosquitto_passwd`), as postgres_setup.sh does PostgreSQL: installed with apt-get when we
# are root and it is missing; quick when it is present. The tests start a private broker of
# their own (tests/helpers/mosquitto.py: its own configuration in a temporary directory, a free
# port of 127.0.0.1); nothing here starts, configures or enables the system's broker.
#
# Prints one line on success:
#     mosquitto=/usr/sbin/mosquitto passwd=/usr/bin/mosquitto_passwd
# Exits 77 (the "skipped" code, as browser_setup.sh) with a one-line reason on stderr where it
# cannot install it: not root, or no apt-get.
set -euo pipefail

find_programs() {
    local broker passwd
    broker="$(command -v mosquitto || true)"
    [ -n "$broker" ] || { [ -x /usr/sbin/mosquitto ] && broker=/usr/sbin/mosquitto; } || true
    passwd="$(command -v mosquitto_passwd || true)"
    [ -n "$broker" ] && [ -n "$passwd" ] || return 1
    echo "mosquitto=$broker passwd=$passwd"
}

# One installer at a time: parallel test workers (pytest-xdist) may all find it missing at once.
exec 8>/tmp/cellvision-apt.lock
flock 8
if ! find_programs >/dev/null; then
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "mosquitto_setup: mosquitto is missing and there is no apt-get to install it" >&2
        exit 77
    fi
    if [ "$(id -u)" != "0" ]; then
        echo "mosquitto_setup: mosquitto is missing; install it as root: apt-get install mosquitto" >&2
        exit 77
    fi
    echo "mosquitto_setup: installing mosquitto with apt-get" >&2
    log="/tmp/mosquitto_setup.$$.log"
    if ! { DEBIAN_FRONTEND=noninteractive apt-get update -qq -o DPkg::Lock::Timeout=300 &&
           DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -o DPkg::Lock::Timeout=300 \
               --no-install-recommends mosquitto; } >"$log" 2>&1; then
        echo "mosquitto_setup: apt-get install mosquitto failed: $(tail -n 1 "$log")" >&2
        rm -f "$log"
        exit 77
    fi
    rm -f "$log"
fi
exec 8>&-

find_programs || { echo "mosquitto_setup: mosquitto not found after installing it" >&2; exit 77; }
