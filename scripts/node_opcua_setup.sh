#!/usr/bin/env bash
# Make sure the OPC UA front-end's independent-stack tests have node-opcua (an OPC UA stack in
# JavaScript, from npm) for the client in tests/opcua_client/: Debian's `nodejs` and `npm` are
# installed with apt-get when we are root and they are missing (as bootstrap.sh does libzbar0),
# then the client's pinned packages (tests/opcua_client/package-lock.json, `npm ci`) go into a
# cache folder outside the checkout, once: quick when they are there. Only that first install
# needs the npm registry; the tests themselves need no network.
#
# The cache folder's name carries the lockfile's hash, so a changed lockfile installs anew. It is
# installed into a temporary folder beside it and renamed into place when complete, under a lock:
# parallel test workers (pytest-xdist) and an interrupted install never see half a tree.
#
# Prints one line on success:
#     node_path=/root/.cache/cellvision/node-opcua-2.186.4-0123456789ab/node_modules
# Exits 77 (the "skipped" code, as browser_setup.sh) with a one-line reason on stderr where it
# cannot: not root and no node, no apt-get, node older than 18, or npm could not install.
set -euo pipefail

NODE_MIN_MAJOR=18
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
client_dir="$(cd "$here/../tests/opcua_client" && pwd)"

skip() {
    echo "node_opcua_setup: $*" >&2
    exit 77
}

have_node() {
    command -v node >/dev/null 2>&1 && command -v npm >/dev/null 2>&1
}

# One apt-get at a time, shared with the other setup scripts.
exec 8>/tmp/cellvision-apt.lock
flock 8
if ! have_node; then
    command -v apt-get >/dev/null 2>&1 || skip "node or npm is missing and there is no apt-get to install them"
    [ "$(id -u)" = "0" ] || skip "node or npm is missing; install them as root: apt-get install nodejs npm"
    echo "node_opcua_setup: installing nodejs and npm with apt-get" >&2
    log="/tmp/node_opcua_setup.$$.log"
    if ! { DEBIAN_FRONTEND=noninteractive apt-get update -qq -o DPkg::Lock::Timeout=300 &&
           DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -o DPkg::Lock::Timeout=300 \
               --no-install-recommends nodejs npm; } >"$log" 2>&1; then
        reason="$(tail -n 1 "$log")"
        rm -f "$log"
        skip "apt-get install nodejs npm failed: $reason"
    fi
    rm -f "$log"
fi
exec 8>&-
have_node || skip "node or npm not found after installing nodejs and npm"

major="$(node -p 'process.versions.node.split(".")[0]' 2>/dev/null || echo 0)"
[ "$major" -ge "$NODE_MIN_MAJOR" ] 2>/dev/null ||
    skip "node $(node --version 2>/dev/null || echo '?') is older than $NODE_MIN_MAJOR"

lockfile="$client_dir/package-lock.json"
[ -f "$lockfile" ] || skip "no $lockfile"
version="$(node -p 'require(process.argv[1]).dependencies["node-opcua-client"]' "$client_dir/package.json")"
digest="$(sha256sum "$lockfile" "$client_dir/package.json" | sha256sum | cut -c1-12)"
cache_root="${XDG_CACHE_HOME:-${HOME:-/tmp}/.cache}/cellvision"
dest="$cache_root/node-opcua-$version-$digest"
marker="$dest/.complete"

if [ ! -f "$marker" ]; then
    mkdir -p "$cache_root" || skip "cannot create $cache_root"
    exec 9>"$cache_root/.node-opcua.lock"
    flock 9
    if [ ! -f "$marker" ]; then  # another worker may have installed it while we waited
        # What an interrupted install left (only ever touched under this lock).
        rm -rf "$cache_root"/.install-node-opcua.* "$dest"
        tmp="$(mktemp -d "$cache_root/.install-node-opcua.XXXXXX")"
        cp "$client_dir/package.json" "$lockfile" "$tmp/"
        echo "node_opcua_setup: installing node-opcua-client $version with npm ci (first use)" >&2
        log="$tmp/npm.log"
        # --ignore-scripts: nothing from the registry runs at install time; the packages need none.
        if ! (cd "$tmp" && npm ci --ignore-scripts --no-audit --no-fund --loglevel=error) >"$log" 2>&1; then
            reason="$(grep -m 1 -E 'ERR!|error' "$log" || tail -n 1 "$log")"
            rm -rf "$tmp"
            skip "npm ci of node-opcua-client $version failed: $reason"
        fi
        rm -f "$log"
        touch "$tmp/.complete"
        mv -T "$tmp" "$dest"
    fi
    exec 9>&-
fi
echo "node_path=$dest/node_modules"
