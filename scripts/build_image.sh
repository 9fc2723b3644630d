#!/usr/bin/env bash
# Build catalign's image with Docker (where a daemon answers) or Podman, from a wheelhouse made
# here on the host, so that the build itself needs no network. Where the base image cannot be
# pulled (no registry reachable), a Debian bookworm base is built with mmdebstrap from Debian's
# packages and kept locally under its tag, so that later builds reuse it.
#
#   scripts/build_image.sh [--tag catalign:latest] [--base python:3.11-slim] [--no-cache]
set -euo pipefail
cd "$(dirname "$0")/.."

DEFAULT_BASE=python:3.11-slim
TAG="${CATALIGN_IMAGE:-catalign:latest}"
BASE="${CATALIGN_BASE:-}"
LOCAL_BASE="${CATALIGN_LOCAL_BASE:-catalign-base:bookworm}"
DEBIAN_MIRROR="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
DEBIAN_SECURITY="${DEBIAN_SECURITY:-http://deb.debian.org/debian-security}"
PYTHON="${PYTHON:-python3.11}"
NO_CACHE=()
# The Debian base: Python 3.11 and the shared libraries open3d links against (GL, EGL, X11,
# udev, usb, idn2); passwd for the image's user. python3-venv brings pip into the venv.
BASE_PACKAGES=python3,python3-venv,ca-certificates,passwd,libusb-1.0-0,libgl1,libegl1,libx11-6,libudev1,libidn2-0

usage() {
    cat <<EOF
usage: scripts/build_image.sh [--tag IMAGE] [--base IMAGE] [--no-cache]
  --tag IMAGE   the image's tag (env CATALIGN_IMAGE; default catalign:latest)
  --base IMAGE  the base image (env CATALIGN_BASE; default $DEFAULT_BASE, and where that cannot
                be pulled, $LOCAL_BASE built here with mmdebstrap; give
                --base $LOCAL_BASE to use that one directly)
  --no-cache    rebuild every layer of the image (the base is still reused)
Other variables: PYTHON (the host's Python 3.11, for the wheelhouse), DEBIAN_MIRROR,
DEBIAN_SECURITY (where mmdebstrap takes Debian's packages), CATALIGN_LOCAL_BASE.
EOF
}

fail() {
    echo "build_image.sh: $*" >&2
    exit 1
}

while [ $# -gt 0 ]; do
    case "$1" in
        -t | --tag) TAG="${2:?--tag needs a value}"; shift 2 ;;
        --base) BASE="${2:?--base needs a value}"; shift 2 ;;
        --no-cache) NO_CACHE=(--no-cache); shift ;;
        -h | --help) usage; exit 0 ;;
        *) echo "build_image.sh: unknown option $1 (see --help)." >&2; exit 2 ;;
    esac
done

# Docker only where its daemon answers (a bare client is common); otherwise Podman, which needs
# chroot isolation, runc and explicit open-file limits in containers such as CI's, and the
# docker image format to keep the HEALTHCHECK.
if command -v docker >/dev/null 2>&1 && docker info >/dev/null 2>&1; then
    TOOL=docker
    BUILD_FLAGS=()
elif command -v podman >/dev/null 2>&1; then
    command -v runc >/dev/null 2>&1 || fail "podman needs the runc runtime here; install it (apt-get install runc)."
    TOOL=podman
    BUILD_FLAGS=(--isolation chroot --runtime runc --ulimit nofile=20000:20000 --format docker)
else
    fail "neither a Docker daemon (docker info) nor podman is available; install podman and runc (apt-get install podman runc) or start Docker."
fi

WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT

has_image() { "$TOOL" image inspect "$1" >/dev/null 2>&1; }

build_debian_base() {
    command -v mmdebstrap >/dev/null 2>&1 \
        || fail "$DEFAULT_BASE cannot be pulled and mmdebstrap is missing to build a Debian base; install it (apt-get install mmdebstrap) or give --base IMAGE."
    echo "build_image.sh: building the Debian bookworm base $LOCAL_BASE with mmdebstrap"
    # Like Debian's slim images: no manuals, translations or documentation but the licences.
    mmdebstrap --quiet --variant=minbase --include="$BASE_PACKAGES" \
        --dpkgopt='path-exclude=/usr/share/man/*' --dpkgopt='path-exclude=/usr/share/locale/*' \
        --dpkgopt='path-exclude=/usr/share/doc/*' --dpkgopt='path-include=/usr/share/doc/*/copyright' \
        bookworm "$WORK/base.tar" \
        "deb $DEBIAN_MIRROR bookworm main" \
        "deb $DEBIAN_MIRROR bookworm-updates main" \
        "deb $DEBIAN_SECURITY bookworm-security main"
    "$TOOL" import --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        "$WORK/base.tar" "$LOCAL_BASE" >/dev/null
}

if [ -z "$BASE" ]; then
    BASE="$DEFAULT_BASE"
    if ! has_image "$BASE" && ! timeout 300 "$TOOL" pull -q "$BASE" >/dev/null 2>&1; then
        echo "build_image.sh: cannot pull $BASE; using the local Debian base $LOCAL_BASE"
        BASE="$LOCAL_BASE"
    fi
fi
if ! has_image "$BASE"; then
    if [ "$BASE" = "$LOCAL_BASE" ]; then
        build_debian_base
    else
        timeout 300 "$TOOL" pull -q "$BASE" >/dev/null || fail "cannot pull the base image $BASE."
    fi
fi

# The wheelhouse: torch (the local CPU wheel) and every dependency of the served package, the
# SDK and their builds, as wheels for the image's Python 3.11, so the image installs offline.
"$PYTHON" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null \
    || fail "the wheelhouse needs Python 3.11 on the host (the image's Python); set PYTHON."
rm -rf wheelhouse
mkdir wheelhouse
"$PYTHON" - >"$WORK/requirements.txt" <<'EOF'
import tomllib

for path, extras in (("pyproject.toml", ["serve"]), ("client/pyproject.toml", [])):
    with open(path, "rb") as file:
        project = tomllib.load(file)
    print(*project["build-system"]["requires"], sep="\n")
    print(*project["project"]["dependencies"], sep="\n")
    for extra in extras:
        print(*project["project"]["optional-dependencies"][extra], sep="\n")
EOF
echo "build_image.sh: making the wheelhouse"
"$PYTHON" -m pip wheel --quiet --disable-pip-version-check --wheel-dir wheelhouse \
    torch==2.13.0 -r "$WORK/requirements.txt"

echo "build_image.sh: building $TAG from $BASE with $TOOL"
"$TOOL" build "${BUILD_FLAGS[@]}" "${NO_CACHE[@]}" --build-arg BASE="$BASE" --tag "$TAG" .
bytes="$("$TOOL" image inspect --format '{{.Size}}' "$TAG")"
echo "build_image.sh: built $TAG ($((bytes / 1000000)) MB)"
