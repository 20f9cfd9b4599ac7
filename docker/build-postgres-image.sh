#!/usr/bin/env bash
# Build the image lifecycle-postgres:<docker/VERSION> (Debian's PostgreSQL server, for
# docker-compose.postgres.yml) offline, like build-images.sh builds lifecycle-manager:
#   1. the base image (local/debian:bookworm: debootstrap, only when it is absent)
#   2. the Debian packages of postgresql as .deb files, downloaded once in a throw-away
#      container of the base image (apt works there) and cached per base image in
#      $LIFECYCLE_BUILD_CACHE (default ~/.cache/lifecycle-manager)
#   3. `docker build --network none`: nothing is downloaded while the image is built
#
#   docker/build-postgres-image.sh                      # prints lifecycle-postgres:0.1.0
#   BASE_IMAGE=debian:bookworm-slim docker/build-postgres-image.sh   # where a registry is reachable
set -euo pipefail

HERE="$(cd "$(dirname "$0")" && pwd)"
VERSION="$(tr -d ' \n' < "$HERE/VERSION")"
IMAGE="${POSTGRES_IMAGE_NAME:-lifecycle-postgres}:$VERSION"
BASE_IMAGE="${BASE_IMAGE:-local/debian:bookworm}"
PACKAGES="postgresql"
CACHE="${LIFECYCLE_BUILD_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/lifecycle-manager}"
CONTEXT="$HERE/build/postgres-context"
step() { echo "== $*" >&2; }

step "base image $BASE_IMAGE"
if [ "$BASE_IMAGE" = "local/debian:bookworm" ]; then
    LOCAL_BASE_IMAGE="$BASE_IMAGE" "$HERE/build-base-image.sh" >&2
elif ! docker image inspect "$BASE_IMAGE" >/dev/null 2>&1; then
    docker pull "$BASE_IMAGE" >&2
fi

step "Debian packages ($PACKAGES)"
id="$(docker image inspect -f '{{.Id}}' "$BASE_IMAGE" | sed 's/^sha256://' | cut -c1-16)"
key="$(printf '%s\n' "$id" "$PACKAGES" "postgres-v1" | sha256sum | cut -c1-16)"
DEBS="$CACHE/debs/$key"
if [ ! -f "$DEBS/.complete" ]; then
    rm -rf "$DEBS"
    mkdir -p "$DEBS"
    docker run --rm -e DEBIAN_FRONTEND=noninteractive -e "PACKAGES=$PACKAGES" -v "$DEBS:/out" "$BASE_IMAGE" sh -ec '
        apt-get update -qq
        mkdir -p /tmp/debs/partial
        apt-get install -y -qq --no-install-recommends --download-only -o Dir::Cache::archives=/tmp/debs $PACKAGES >/dev/null
        cp /tmp/debs/*.deb /out/
        chmod -R a+rX /out
    ' >&2
    touch "$DEBS/.complete"
fi
echo "$(ls "$DEBS"/*.deb | wc -l) packages in $DEBS" >&2

step "build context $CONTEXT"
rm -rf "$CONTEXT"
mkdir -p "$CONTEXT"
cp -al "$DEBS" "$CONTEXT/debs" 2>/dev/null || cp -a "$DEBS" "$CONTEXT/debs"
rm -f "$CONTEXT/debs/.complete"
cp "$HERE/postgres/Dockerfile" "$HERE/postgres/entrypoint.sh" "$CONTEXT/"

step "docker build $IMAGE (offline, from $BASE_IMAGE)"
docker build --network none --pull=false --build-arg "BASE_IMAGE=$BASE_IMAGE" -t "$IMAGE" "$CONTEXT" >&2
size="$(docker image inspect -f '{{.Size}}' "$IMAGE")"
echo "built $IMAGE ($((size / 1000000)) MB)" >&2
echo "$IMAGE"
