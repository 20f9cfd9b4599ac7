#!/usr/bin/env bash
# Write the Industrial Edge package: what the Industrial Edge Publisher (or iectl) imports.
#
#   docker/edge/package.sh [--no-build] [--output DIR]
#
# Builds the image offline (docker/build-images.sh; skipped with --no-build, which needs the
# image present), then writes DIR (default docker/build/package/lifecycle-manager-<VERSION>):
#   docker-compose.yml            the app (compose 2.4) to "Import YAML" in the Publisher
#   docker-compose.demo.yml       optional simulated robot, for trying the app
#   nginx.json                    reverse-proxy entry of the web service (/lifecycle/)
#   cfg-data/param.json           example app configuration (template-file way)
#   cfg-data-template/param.json  JSON-Forms template (dataschema + uischema) for the IEM form
#   images/*.tar                  `docker save` of the image, to `docker load` next to the Publisher
#   README.md                     Publisher and iectl steps
#   SHA256SUMS
# and DIR.tar.gz of it all.
set -euo pipefail

EDGE="$(cd "$(dirname "$0")" && pwd)"
DOCKER="$(dirname "$EDGE")"
VERSION="$(tr -d ' \n' < "$DOCKER/VERSION")"
IMAGE_NAME="${IMAGE_NAME:-lifecycle-manager}"
IMAGE="$IMAGE_NAME:$VERSION"
OUT="$DOCKER/build/package/$IMAGE_NAME-$VERSION"
BUILD=1
while [ $# -gt 0 ]; do
    case "$1" in
        --no-build) BUILD=0 ;;
        --output) OUT="$2"; shift ;;
        *) echo "usage: $0 [--no-build] [--output DIR]" >&2; exit 2 ;;
    esac
    shift
done

# The files handed to the Publisher must name exactly this version (never latest, no build key).
for file in docker-compose.yml docker-compose.demo.yml; do
    if grep -E '^\s*image:' "$EDGE/$file" | grep -vq "image: $IMAGE\$"; then
        echo "package: $file uses an image other than $IMAGE; update it (docker/VERSION says $VERSION)" >&2
        exit 1
    fi
    if grep -Eq '^\s*build:' "$EDGE/$file"; then
        echo "package: $file has a build key; the Publisher does not build" >&2
        exit 1
    fi
done
docker-compose -f "$EDGE/docker-compose.yml" -f "$EDGE/docker-compose.demo.yml" config -q

if [ "$BUILD" = 1 ]; then
    "$DOCKER/build-images.sh" >/dev/null
fi
docker image inspect "$IMAGE" >/dev/null 2>&1 || { echo "package: image $IMAGE is missing (run docker/build-images.sh)" >&2; exit 1; }

rm -rf "$OUT"
mkdir -p "$OUT/images" "$OUT/cfg-data" "$OUT/cfg-data-template"
cp "$EDGE/docker-compose.yml" "$EDGE/docker-compose.demo.yml" "$EDGE/nginx.json" "$OUT/"
cp "$EDGE/cfg-data/param.json" "$OUT/cfg-data/"
cp "$EDGE/cfg-data-template/param.json" "$OUT/cfg-data-template/"
tarball="images/${IMAGE_NAME}_${VERSION}.tar"
docker save -o "$OUT/$tarball" "$IMAGE"
chmod 0644 "$OUT/$tarball"

size_mb="$(( $(docker image inspect -f '{{.Size}}' "$IMAGE") / 1000000 ))"
# The memory limits of the app's services, e.g. "144 + 96 + 192 + 64 = 496 MB".
memory="$(sed -n 's/^ *mem_limit: *\([0-9]*\)mb *$/\1/p' "$EDGE/docker-compose.yml" |
          awk '{ s += $1; t = t (NR > 1 ? " + " : "") $1 } END { print t " = " s " MB" }')"
cat > "$OUT/README.md" <<EOF
# ROS 2 lifecycle manager $VERSION: Industrial Edge app package

Web app that shows and drives the ROS 2 lifecycle nodes of the robots in the plant, with an
audit log of every state change. Four services, one image (\`$IMAGE\`, $size_mb MB):
\`web\` (the site, behind the device's reverse proxy at \`https://<device>/lifecycle/\`),
\`ingest\` (stores what gateways report), \`gateway\` (the gateway \`local\`: ROS 2 / DDS),
\`redis\`. Memory limits: $memory.

## 1. Load the image next to the Publisher

    docker load -i $tarball

## 2a. Industrial Edge Publisher (GUI)

1. Connect the Publisher to that Docker engine.
2. Create an application (e.g. "ROS 2 Lifecycle Manager", repository \`lifecycle-manager\`),
   add version \`$VERSION\`, and **Import YAML**: \`docker-compose.yml\`.
3. Service \`web\` -> Network -> reverse proxy ("Redirect" via the device's HTTPS proxy):
   name \`lifecycle\`, protocol HTTP, port \`8000\`, rewrite target \`/\`, **secure redirection on**
   (the device's login is required first), headers as in \`nginx.json\`:
   \`Upgrade \$http_upgrade\`, \`Connection upgrade\` (WebSockets: live updates),
   \`X-Forwarded-Proto https\`. Set the app's redirect URL to \`lifecycle\`.
4. Configurations -> add a configuration "Lifecycle manager", host path \`./cfg-data/\`,
   type **JSON schema**, file \`cfg-data-template/param.json\` (the form the operator fills in
   at installation: admin password, robots, allowed host names, ROS discovery). Instead of the
   form you may add \`cfg-data/param.json\` as a template file.
5. Check the version's details (no warnings expected), then **Start Upload** to the IEM.

## 2b. The same with iectl (Industrial Edge CLI; check \`iectl publisher --help\` of your version)

    iectl config add publisher --name pub --dockerurl http://127.0.0.1:2375 --workspace ./workspace
    (cd workspace && iectl publisher workspace init)
    iectl publisher standaloneapp create --reponame lifecycle-manager --appname lifecycle-manager \\
        --appdescription "ROS 2 lifecycle node manager" --iconpath ./icon.png
    iectl publisher standaloneapp createversion --appname lifecycle-manager --versionnumber $VERSION \\
        --yamlpath ./docker-compose.yml --changelogs "$VERSION" \\
        -n "\$(cat nginx.json)" -s web -t FromBoxReverseProxy -u lifecycle -r /
    iectl config add iem --name iem --url https://<iem>:9443 --user <user> --password <password>
    iectl publisher edgemanagement application uploadtocatalog --appname lifecycle-manager -w $VERSION

Add the configuration of step 2a.4 in the Publisher, or upload it with the IEM's
configuration page (Applications -> My Projects -> the app -> Configurations).

## 3. Install on a device (IEM)

Install the app on the device and fill in the configuration form:

- **Administrator**: user name and password (at least 12 characters). Changing the password
  in the configuration resets it at the next start. No password: one is generated into the
  data volume (not readable from the IEM, so set one).
- **Robots**: name (e.g. \`agv-1\`), ROS domain id, optional namespace: robots the app's own
  gateway (\`local\`) watches. More robots can be added later in the app's admin pages.
- **Web access**: the device's host names/IPs (\`allowedHosts\`; they are also the accepted
  WebSocket origins; empty accepts any), URL prefix \`/lifecycle\` (must match nginx.json).
- **ROS 2**: DDS discovery range (\`SUBNET\` for robots in containers on the app's \`ros\` network),
  static peers for robots elsewhere (see the project's docker/README.md: the gateway may need
  the device's host network to reach robots on the plant network).

Open \`https://<device>/lifecycle/\` and log in. Data (database, generated secret key)
lives in the volume \`lifecycle-data\`; it survives restarts and app updates.

## Try it with a simulated robot

\`docker-compose.demo.yml\` adds a robot container (ROS domain 21, nodes joy_to_vel, joystick,
lidar_driver, camera_driver, planner) on the app's \`ros\` network. Register it in the
configuration: \`"robots": [{"name": "agv-1", "domainId": 21}]\`.
EOF

(cd "$OUT" && find . -type f ! -name SHA256SUMS -print0 | sort -z | xargs -0 sha256sum > SHA256SUMS)
tar -C "$(dirname "$OUT")" -cf - "$(basename "$OUT")" | gzip -1 > "$OUT.tar.gz"
echo "package: $OUT ($(du -sh "$OUT" | cut -f1); archive $(du -sh "$OUT.tar.gz" | cut -f1))" >&2
echo "$OUT"
