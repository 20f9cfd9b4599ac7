#!/usr/bin/env bash
# Build the image lifecycle-manager:<docker/VERSION> offline.
#
#   docker/build-images.sh                      # base image local/debian:bookworm (built if absent)
#   BASE_IMAGE=python:3.11-slim-bookworm docker/build-images.sh   # where a registry is reachable
#
# Steps, each cached on this machine (Docker's image store and build cache, and
# $LIFECYCLE_BUILD_CACHE, default ~/.cache/lifecycle-manager: it outlives a fresh clone):
#   1. the base image (debootstrap, only for local/debian:bookworm when it is absent)
#   2. the Python wheelhouse on the host (build-wheelhouse.sh; redone when requirements.txt changes)
#   3. the Debian packages the base lacks, as .deb files (build-debs.sh; per base image)
#   4. a clean build context (app sources, wheelhouse, debs, runtime scripts)
#   5. `docker build --network none`: nothing is downloaded while the image is built
# Prints the image reference on its last line.
set -euo pipefail

HERE="$(cd "$(dirname "$0")" && pwd)"
ROOT="$(dirname "$HERE")"
VERSION="$(tr -d ' \n' < "$HERE/VERSION")"
IMAGE_NAME="${IMAGE_NAME:-lifecycle-manager}"
IMAGE="$IMAGE_NAME:$VERSION"
BASE_IMAGE="${BASE_IMAGE:-local/debian:bookworm}"
CONTEXT="$HERE/build/context"
CACHE="${LIFECYCLE_BUILD_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/lifecycle-manager}"

[[ "$VERSION" =~ ^[0-9]+\.[0-9]+\.[0-9]+([.+-][0-9A-Za-z.-]+)?$ ]] || { echo "docker/VERSION must hold a version such as 1.2.3" >&2; exit 1; }
step() { echo "== $*" >&2; }

step "base image $BASE_IMAGE"
if [ "$BASE_IMAGE" = "local/debian:bookworm" ]; then
    LOCAL_BASE_IMAGE="$BASE_IMAGE" "$HERE/build-base-image.sh" >&2
elif ! docker image inspect "$BASE_IMAGE" >/dev/null 2>&1; then
    docker pull "$BASE_IMAGE" >&2
fi

step "Python wheelhouse"
"$HERE/build-wheelhouse.sh" >&2

step "Debian packages"
DEBS="$("$HERE/build-debs.sh" "$BASE_IMAGE")"

step "build context $CONTEXT"
rm -rf "$CONTEXT"
mkdir -p "$CONTEXT/app"
# Hard links where the cache is on the same file system (no copying of the ~90 MB wheelhouse).
cp -al "$CACHE/wheelhouse" "$CONTEXT/wheelhouse" 2>/dev/null || cp -a "$CACHE/wheelhouse" "$CONTEXT/wheelhouse"
cp -al "$DEBS" "$CONTEXT/debs" 2>/dev/null || cp -a "$DEBS" "$CONTEXT/debs"
cp -a "$HERE/runtime" "$CONTEXT/runtime"
cp "$HERE/VERSION" "$CONTEXT/VERSION"
# The application: only what runs (no tests, venv, local data, caches).
tar -C "$ROOT" --exclude='__pycache__' --exclude='*.pyc' --exclude='.DS_Store' \
    -cf - manage.py lifecycle_site ros_gateway templates static locale | tar -C "$CONTEXT/app" -xf -

step "docker build $IMAGE (offline, from $BASE_IMAGE)"
docker build --network none --pull=false \
    --build-arg "BASE_IMAGE=$BASE_IMAGE" --build-arg "VERSION=$VERSION" \
    -f "$HERE/Dockerfile" -t "$IMAGE" "$CONTEXT" >&2
size="$(docker image inspect -f '{{.Size}}' "$IMAGE")"
echo "built $IMAGE ($((size / 1000000)) MB)" >&2
echo "$IMAGE"
