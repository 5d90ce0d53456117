#!/usr/bin/env bash
# Make sure the browser tests have a headless Chromium and its WebDriver (Debian's `chromium` and
# `chromium-driver`), as bootstrap.sh does libzbar0: installed with apt-get when we are root and
# they are missing; quick when they are present.
#
# Prints two lines on success:
#     chromium=/usr/bin/chromium
#     chromedriver=/usr/bin/chromedriver
# Exits 77 (the "skipped" code of automake and of tests/helpers/browser.py) with a one-line reason
# on stderr where it cannot install them: not root, or no apt-get.
set -euo pipefail

find_chromium() {
    local candidate
    for candidate in chromium chromium-browser; do
        if command -v "$candidate" >/dev/null 2>&1; then
            command -v "$candidate"
            return 0
        fi
    done
    return 1
}

find_driver() {
    if command -v chromedriver >/dev/null 2>&1; then
        command -v chromedriver
        return 0
    fi
    # Debian ships the driver under /usr/lib/chromium as well as the /usr/bin link.
    if [ -x /usr/lib/chromium/chromedriver ]; then
        echo /usr/lib/chromium/chromedriver
        return 0
    fi
    return 1
}

# One installer at a time: parallel test workers (pytest-xdist) may all find it missing at once.
exec 8>/tmp/cellvision-apt.lock
flock 8
if ! find_chromium >/dev/null || ! find_driver >/dev/null; then
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "browser_setup: chromium or chromium-driver is missing and there is no apt-get to install them" >&2
        exit 77
    fi
    if [ "$(id -u)" != "0" ]; then
        echo "browser_setup: chromium or chromium-driver is missing; install them as root: apt-get install chromium chromium-driver" >&2
        exit 77
    fi
    echo "browser_setup: installing chromium and chromium-driver with apt-get" >&2
    if ! { DEBIAN_FRONTEND=noninteractive apt-get update -qq -o DPkg::Lock::Timeout=300 &&
           DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -o DPkg::Lock::Timeout=300 --no-install-recommends \
               chromium chromium-driver; } >/tmp/browser_setup.$$.log 2>&1; then
        echo "browser_setup: apt-get install chromium chromium-driver failed: $(tail -n 1 /tmp/browser_setup.$$.log)" >&2
        rm -f /tmp/browser_setup.$$.log
        exit 77
    fi
    rm -f /tmp/browser_setup.$$.log
fi
exec 8>&-

chromium_path="$(find_chromium)" || { echo "browser_setup: chromium not found after installing it" >&2; exit 77; }
driver_path="$(find_driver)" || { echo "browser_setup: chromedriver not found after installing it" >&2; exit 77; }
echo "chromium=$chromium_path"
echo "chromedriver=$driver_path"
