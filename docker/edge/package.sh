#!/usr/bin/env bash
# Write an Industrial Edge package: what the Industrial Edge Publisher (or iectl) imports.
#
#   docker/edge/package.sh [--app edge|edge-cell] [--no-build] [--output DIR]
#
# --app edge (default): the whole app (docker/edge/): site, ingest, gateway "local", Redis.
# --app edge-cell: a gateway only, for a cell's device (docker/edge-cell/), no web UI.
# Builds the image offline (docker/build-images.sh; skipped with --no-build, which needs the
# image present), then writes DIR (default docker/build/package/<package>-<VERSION>, package
# lifecycle-manager or lifecycle-gateway):
#   docker-compose.yml            the app (compose 2.4) to "Import YAML" in the Publisher
#   docker-compose.no-layer2.yml  (edge) the app for a device without layer-2 access
#   docker-compose.demo.yml       (edge) optional simulated robot, for trying the app
#   nginx.json                    (edge) reverse-proxy entry of the web service (/lifecycle/)
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
APP=edge
OUT=""
BUILD=1
while [ $# -gt 0 ]; do
    case "$1" in
        --app) APP="$2"; shift ;;
        --no-build) BUILD=0 ;;
        --output) OUT="$2"; shift ;;
        *) echo "usage: $0 [--app edge|edge-cell] [--no-build] [--output DIR]" >&2; exit 2 ;;
    esac
    shift
done
case "$APP" in
    edge)
        APP_DIR="$DOCKER/edge"; PACKAGE="lifecycle-manager"
        FILES=(docker-compose.yml docker-compose.no-layer2.yml docker-compose.demo.yml nginx.json) ;;
    edge-cell)
        APP_DIR="$DOCKER/edge-cell"; PACKAGE="lifecycle-gateway"
        FILES=(docker-compose.yml) ;;
    *) echo "package: --app must be edge or edge-cell" >&2; exit 2 ;;
esac
OUT="${OUT:-$DOCKER/build/package/$PACKAGE-$VERSION}"

# The files handed to the Publisher must name exactly this version (never latest, no build key).
for file in "${FILES[@]}"; do
    case "$file" in *.yml) ;; *) continue ;; esac
    if grep -E '^\s*image:' "$APP_DIR/$file" | grep -vq "image: $IMAGE\$"; then
        echo "package: $file uses an image other than $IMAGE; update it (docker/VERSION says $VERSION)" >&2
        exit 1
    fi
    if grep -Eq '^\s*build:' "$APP_DIR/$file"; then
        echo "package: $file has a build key; the Publisher does not build" >&2
        exit 1
    fi
done
if [ "$APP" = edge ]; then
    docker-compose -f "$APP_DIR/docker-compose.yml" -f "$APP_DIR/docker-compose.demo.yml" config -q
    docker-compose -f "$APP_DIR/docker-compose.no-layer2.yml" -f "$APP_DIR/docker-compose.demo.yml" config -q
else
    docker-compose -f "$APP_DIR/docker-compose.yml" config -q
fi

if [ "$BUILD" = 1 ]; then
    "$DOCKER/build-images.sh" >/dev/null
fi
docker image inspect "$IMAGE" >/dev/null 2>&1 || { echo "package: image $IMAGE is missing (run docker/build-images.sh)" >&2; exit 1; }

rm -rf "$OUT"
mkdir -p "$OUT/images" "$OUT/cfg-data" "$OUT/cfg-data-template"
for file in "${FILES[@]}"; do cp "$APP_DIR/$file" "$OUT/"; done
cp "$APP_DIR/cfg-data/param.json" "$OUT/cfg-data/"
cp "$APP_DIR/cfg-data-template/param.json" "$OUT/cfg-data-template/"
tarball="images/${IMAGE_NAME}_${VERSION}.tar"
docker save -o "$OUT/$tarball" "$IMAGE"
chmod 0644 "$OUT/$tarball"

size_mb="$(( $(docker image inspect -f '{{.Size}}' "$IMAGE") / 1000000 ))"
# The memory limits of the app's services, e.g. "144 + 96 + 192 + 64 = 496 MB".
memory="$(sed -n 's/^ *mem_limit: *\([0-9]*\)mb *$/\1/p' "$APP_DIR/docker-compose.yml" |
          awk '{ s += $1; t = t (NR > 1 ? " + " : "") $1 } END { print (NR > 1 ? t " = " : "") s " MB" }')"

readme_edge() {
cat <<EOF
# ROS 2 lifecycle manager $VERSION: Industrial Edge app package

Web app that shows and drives the ROS 2 lifecycle nodes of the robots in the plant, with an
audit log of every state change. Four services, one image (\`$IMAGE\`, $size_mb MB):
\`web\` (the site, behind the device's reverse proxy at \`https://<device>/lifecycle/\`),
\`ingest\` (stores what gateways report), \`gateway\` (the gateway \`local\`: ROS 2 / DDS),
\`redis\`. Memory limits: $memory.

**Before installing, the device needs layer-2 access for the plant network.** The gateway
talks DDS with the robots over the device's layer-2 network \`zzz_layer2_net1\` (the app's
container becomes a host of the plant LAN with an address of its own). The device creates
that network when its operator enables layer-2 access for an interface (with an address
range for apps) in the device's network settings; without it the app does not start
(\`Network zzz_layer2_net1 declared as external, but could not be found\`).
\`docker-compose.no-layer2.yml\` is the same app without it: import it instead where no
layer-2 access is possible (its gateway then reaches only robot containers of the app).

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
- **ROS 2**: DDS discovery range (\`SUBNET\`: multicast discovery on the plant LAN through the
  layer-2 network), static peers (robots where multicast does not reach), a Fast DDS discovery
  server (\`ADDRESS:PORT\`, the gateway as super client). Robots in other routed networks: a
  gateway of their own (the package \`lifecycle-gateway\`, \`package.sh --app edge-cell\`).

Open \`https://<device>/lifecycle/\` and log in. Data (database, generated secret key)
lives in the volume \`lifecycle-data\`; it survives restarts and app updates.

## Try it with a simulated robot

\`docker-compose.demo.yml\` adds a robot container (ROS domain 21, nodes joy_to_vel, joystick,
lidar_driver, camera_driver, planner) on a network \`ros\` it shares with the gateway.
Register it in the configuration: \`"robots": [{"name": "agv-1", "domainId": 21}]\`.
EOF
}

readme_edge_cell() {
cat <<EOF
# ROS 2 lifecycle gateway $VERSION: Industrial Edge app package (a cell's gateway)

The gateway of the ROS 2 lifecycle manager for the robots of one cell, on an Industrial Edge
device of that cell. It speaks DDS with the robots over the device's layer-2 network and
dials out to the central site's Redis; the site (web UI, database) runs elsewhere. One
service, \`gateway\`, one image (\`$IMAGE\`, $size_mb MB). Memory limit: $memory.
No web UI: no nginx.json, no reverse proxy, no host port, no volume.

## 0. On the site

Publish the site's Redis to the plant network (docker/README.md, "A gateway for a remote
cell"), then register this gateway; it prints what the device needs:

    python manage.py add_gateway cell-a --redis-url redis://site.plant.local:6379/0
    LIFECYCLE_GATEWAY_NAME=cell-a
    REDIS_URL=redis://gw-cell-a:<password>@site.plant.local:6379/0
    LIFECYCLE_CHANNEL_PREFIX=lifecycle

and add the cell's robots to it: \`manage.py add_robot agv-7 --domain 31 --gateway cell-a\`.

## 1. Load the image next to the Publisher

    docker load -i $tarball

## 2. Publisher or iectl

As for the lifecycle-manager app, but **without a reverse proxy**: Import YAML
\`docker-compose.yml\`, leave the service's network redirect empty (no UI: the device shows
the app's tile without a link; if your Publisher version insists on a redirect URL, the
app has none to offer), add the configuration "Lifecycle gateway" with host path
\`./cfg-data/\`, type **JSON schema**, file \`cfg-data-template/param.json\`. With iectl:

    iectl publisher standaloneapp create --reponame lifecycle-gateway --appname lifecycle-gateway \\
        --appdescription "ROS 2 lifecycle gateway for a cell" --iconpath ./icon.png
    iectl publisher standaloneapp createversion --appname lifecycle-gateway --versionnumber $VERSION \\
        --yamlpath ./docker-compose.yml --changelogs "$VERSION"

(no \`-n\`/\`-s\`/\`-t\`/\`-u\`/\`-r\`: those describe a UI). Check the options of your iectl version.

## 3. Install on a device (IEM)

Enable **layer-2 access** for the interface on the cell's plant network in the device's
network settings first (the device then has the network \`zzz_layer2_net1\`; without it the
app does not start). Then install and fill in the form:

- **Gateway**: the name from step 0 (\`LIFECYCLE_GATEWAY_NAME\`), key prefix (\`lifecycle\`).
- **Central site**: the Redis URL (paste the whole \`REDIS_URL\` of step 0, or the URL without
  credentials and the user \`gw-NAME\` and password separately), and for \`rediss://\` with a
  private CA its certificate (PEM). The password is a secret: it lives only in the device's
  app configuration, never in the compose file or the image. Rotate it by running
  add_gateway again and updating the configuration.
- **ROS 2**: \`SUBNET\` finds robots on the plant LAN by multicast; static peers or a Fast DDS
  discovery server where multicast does not reach.

Within seconds the gateway appears online on the site (\`/api/v1/gateways\`, the fleet page).
A wrong setting stops the container with the reason in its log (exit code 78).
EOF
}

case "$APP" in
    edge) readme_edge > "$OUT/README.md" ;;
    edge-cell) readme_edge_cell > "$OUT/README.md" ;;
esac

(cd "$OUT" && find . -type f ! -name SHA256SUMS -print0 | sort -z | xargs -0 sha256sum > SHA256SUMS)
tar -C "$(dirname "$OUT")" -cf - "$(basename "$OUT")" | gzip -1 > "$OUT.tar.gz"
echo "package: $OUT ($(du -sh "$OUT" | cut -f1); archive $(du -sh "$OUT.tar.gz" | cut -f1))" >&2
echo "$OUT"
