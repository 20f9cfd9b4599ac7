#!/usr/bin/env bash
# Build the base image `local/debian:bookworm` without any registry: debootstrap a minimal
# Debian bookworm root file system from Debian's package mirror and `docker import` it.
# Only needed where no registry is reachable; elsewhere pass an official image as
# BASE_IMAGE to build-images.sh (e.g. python:3.11-slim-bookworm or debian:bookworm-slim).
#
#   docker/build-base-image.sh            # builds it when it is absent
#   docker/build-base-image.sh --force    # rebuilds it
set -euo pipefail

IMAGE="${LOCAL_BASE_IMAGE:-local/debian:bookworm}"
MIRROR="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
HERE="$(cd "$(dirname "$0")" && pwd)"
BUILD="$HERE/build"

if [ "${1:-}" != "--force" ] && docker image inspect "$IMAGE" >/dev/null 2>&1; then
    echo "base image $IMAGE is present"
    exit 0
fi
command -v debootstrap >/dev/null || { echo "debootstrap is missing: apt-get install debootstrap" >&2; exit 1; }
[ "$(id -u)" = 0 ] || { echo "debootstrap needs root" >&2; exit 1; }

mkdir -p "$BUILD"
rootfs="$(mktemp -d "$BUILD/rootfs.XXXXXX")"
trap 'rm -rf "$rootfs"' EXIT
echo "debootstrap bookworm (minbase) into $rootfs ..."
debootstrap --variant=minbase bookworm "$rootfs" "$MIRROR" >"$BUILD/debootstrap.log" 2>&1 \
    || { tail -20 "$BUILD/debootstrap.log" >&2; exit 1; }
# Keep the image small: no apt lists, caches, man pages or locales beyond what minbase has.
rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/var/cache/apt/*.bin "$rootfs"/var/cache/apt/archives/*.deb \
       "$rootfs"/usr/share/doc/* "$rootfs"/usr/share/man/* "$rootfs"/usr/share/info/*
tar -C "$rootfs" -c . | docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'CMD ["bash"]' \
    - "$IMAGE" >/dev/null
echo "built base image $IMAGE ($(docker image inspect -f '{{.Size}}' "$IMAGE" | awk '{printf "%.0f MB", $1/1e6}'))"
