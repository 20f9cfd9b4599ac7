#!/usr/bin/env bash
# Collect the Debian packages the image needs (Python 3.11 when the base image lacks it,
# tini, redis-server) as .deb files into $LIFECYCLE_BUILD_CACHE/debs/<base> (default under
# ~/.cache/lifecycle-manager, kept per machine), so that `docker build`
# itself runs with --network none: the Dockerfile installs them from the build context.
#
# The download runs once in a throw-away container of the base image (apt works there;
# the packages are exactly those missing from that base), and is cached per base-image id.
#
#   docker/build-debs.sh [BASE_IMAGE]     # prints the folder it filled
set -euo pipefail

HERE="$(cd "$(dirname "$0")" && pwd)"
BASE_IMAGE="${1:-${BASE_IMAGE:-local/debian:bookworm}}"
RUNTIME_PACKAGES="tini redis-server"
id="$(docker image inspect -f '{{.Id}}' "$BASE_IMAGE" | sed 's/^sha256://' | cut -c1-16)"
key="$(printf '%s\n' "$id" "$RUNTIME_PACKAGES" "v1" | sha256sum | cut -c1-16)"
CACHE="${LIFECYCLE_BUILD_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/lifecycle-manager}"
OUT="$CACHE/debs/$key"

if [ -f "$OUT/.complete" ]; then
    echo "$OUT"
    exit 0
fi
rm -rf "$OUT"
mkdir -p "$OUT/runtime" "$OUT/build"
# Runtime set: what the final image installs. Build set: what the build stage adds on top
# (python3-venv for Debian's python; nothing for an image that ships its own Python).
docker run --rm -e DEBIAN_FRONTEND=noninteractive -e "RUNTIME_PACKAGES=$RUNTIME_PACKAGES" \
    -v "$OUT:/out" "$BASE_IMAGE" sh -ec '
    runtime="$RUNTIME_PACKAGES"; build=""
    command -v python3.11 >/dev/null 2>&1 || runtime="python3 $runtime"
    python3.11 -m ensurepip --version >/dev/null 2>&1 || build="python3-venv"
    apt-get update -qq
    mkdir -p /tmp/runtime/partial /tmp/build/partial
    apt-get install -y -qq --no-install-recommends --download-only -o Dir::Cache::archives=/tmp/runtime $runtime >/dev/null
    apt-get install -y -qq --no-install-recommends -o Dir::Cache::archives=/tmp/runtime $runtime >/dev/null
    if [ -n "$build" ]; then
        apt-get install -y -qq --no-install-recommends --download-only -o Dir::Cache::archives=/tmp/build $build >/dev/null
    fi
    cp /tmp/runtime/*.deb /out/runtime/
    cp /tmp/build/*.deb /out/build/ 2>/dev/null || true
    chmod -R a+rX /out
' >&2
touch "$OUT/runtime/.keep" "$OUT/build/.keep" "$OUT/.complete"
echo "collected $(ls "$OUT"/runtime/*.deb | wc -l) runtime and $(ls "$OUT"/build/*.deb 2>/dev/null | wc -l) build packages for $BASE_IMAGE" >&2
echo "$OUT"
