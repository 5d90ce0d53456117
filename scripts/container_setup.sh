#!/usr/bin/env bash
# Set up rootful podman for the container test (tests/test_container.py) and build the base
# image it gives the Dockerfile as BASE_IMAGE, without pulling from any registry:
#   1. install podman, runc and debootstrap with apt-get when they are missing (root only);
#   2. debootstrap a minimal Debian (python3, python3-venv, python3-pip) from the suite and
#      mirror this machine's apt uses, add this machine's CA certificates (pip inside the build
#      goes through the same TLS interception as the host), and import it into podman's image
#      store as localhost/cellvision-base:SUITE-KEY;
#   3. run a container from it once, to be sure podman can run containers here.
# Idempotent and cached: the image is kept, and built again only when its inputs (suite,
# mirror, packages, CA certificates, this recipe) change. Concurrent callers wait on a lock.
#
# stdout: the base image's name. Exit status: 0 ready; 77 cannot run here (the reason, one
# line, on stderr); anything else, a failure.
# Overrides: CELLVISION_BASE_SUITE, CELLVISION_BASE_MIRROR.
set -euo pipefail

# The flags podman needs on these machines: crun refuses the host's mixed cgroups, and the
# default rlimits are above what the sandbox lets a container set. The test uses the same.
PODMAN_FLAGS=(--runtime runc)
ULIMITS=(--ulimit nofile=20000:20000 --ulimit nproc=4096:4096)
PACKAGES=python3,python3-venv,python3-pip,ca-certificates
RECIPE=1   # bump when the steps below change what the image holds

skip() {
    echo "container-setup: cannot run here: $*" >&2
    exit 77
}
say() { echo "container-setup: $*" >&2; }

[ "$(uname -s)" = Linux ] || skip "containers need Linux, this is $(uname -s)"
[ "$(id -u)" = 0 ] || skip "rootful podman and debootstrap need root (running as uid $(id -u))"

# One installer at a time: parallel test workers (pytest-xdist) may all find it missing at once.
exec 8>/tmp/cellvision-apt.lock
flock 8
missing=()
for tool in podman runc debootstrap; do
    command -v "$tool" >/dev/null 2>&1 || missing+=("$tool")
done
if [ "${#missing[@]}" -gt 0 ]; then
    command -v apt-get >/dev/null 2>&1 || skip "${missing[*]} missing and no apt-get to install them"
    say "installing ${missing[*]} with apt-get"
    log=$(mktemp)
    if ! { DEBIAN_FRONTEND=noninteractive apt-get update -qq &&
           DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}"; } >"$log" 2>&1
    then
        reason=$(tail -n 1 "$log")
        rm -f "$log"
        skip "apt-get could not install ${missing[*]}: $reason"
    fi
    rm -f "$log"
fi
exec 8>&-

# One setup at a time: parallel test runs share podman's image store.
exec 9>/var/lock/cellvision-container-setup.lock
flock 9

# The suite and mirror of this machine's apt (deb822 or one-line sources alike).
suite="${CELLVISION_BASE_SUITE:-}"
if [ -z "$suite" ] && [ -r /etc/os-release ]; then
    suite=$(. /etc/os-release && echo "${VERSION_CODENAME:-}")
fi
[ -n "$suite" ] || skip "cannot tell this machine's Debian suite (no VERSION_CODENAME in /etc/os-release)"
mirror="${CELLVISION_BASE_MIRROR:-}"
if [ -z "$mirror" ]; then
    mirror=$(apt-get indextargets --format '$(REPO_URI) $(RELEASE) $(TARGET_OF)' 2>/dev/null |
        awk -v s="$suite" '$2 == s && $3 == "deb" { print $1; exit }')
fi
[ -n "$mirror" ] || skip "no apt source for the suite $suite (apt-get indextargets lists none)"

ca_dir=/usr/local/share/ca-certificates
ca_sum=$({ find "$ca_dir" -type f -name '*.crt' -print0 2>/dev/null || true; } | sort -z |
    xargs -0 -r cat | sha256sum | cut -c1-12)
key=$(printf '%s\n' "$RECIPE" "$suite" "$mirror" "$PACKAGES" "$ca_sum" | sha256sum | cut -c1-12)
image="localhost/cellvision-base:$suite-$key"

if ! podman image exists "$image"; then
    work=$(mktemp -d /var/tmp/cellvision-base.XXXXXX)
    trap 'rm -rf "$work"' EXIT
    rootfs="$work/rootfs"
    say "debootstrap $suite from $mirror into $rootfs (about a minute)"
    if ! debootstrap --variant=minbase --include="$PACKAGES" "$suite" "$rootfs" "$mirror" \
        >"$work/debootstrap.log" 2>&1; then
        skip "debootstrap $suite from $mirror failed: $(tail -n 1 "$work/debootstrap.log")"
    fi
    chroot "$rootfs" python3 -c 'import sys; sys.exit(sys.version_info < (3, 11))' ||
        skip "the suite $suite ships python3 older than 3.11, which cellvision needs"
    # This machine's extra CA certificates, for apt and pip inside the build.
    if [ -d "$ca_dir" ]; then
        cp -r "$ca_dir"/. "$rootfs/usr/local/share/ca-certificates/"
        chroot "$rootfs" update-ca-certificates >/dev/null 2>&1
    fi
    printf '[global]\ncert = /etc/ssl/certs/ca-certificates.crt\n' >"$rootfs/etc/pip.conf"
    rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
    say "importing $image"
    tar -C "$rootfs" -c . | podman import --quiet \
        --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'ENV LANG=C.UTF-8' \
        --change 'CMD ["/bin/bash"]' \
        - "$image" >/dev/null
    # Older base images of this recipe are no longer needed (one still in use stays).
    podman images --format '{{.Repository}}:{{.Tag}}' localhost/cellvision-base |
        grep -vx "$image" | xargs -r podman rmi >/dev/null 2>&1 || true
fi

if ! out=$(podman run --rm "${PODMAN_FLAGS[@]}" "${ULIMITS[@]}" --network none "$image" \
    true 2>&1); then
    skip "podman cannot run a container here: $(printf '%s' "$out" | tail -n 1)"
fi
echo "$image"
