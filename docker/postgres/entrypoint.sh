#!/bin/sh
# First start: a cluster in $PGDATA with the user and database "lifecycle", its password from
# POSTGRES_PASSWORD (password login, scram-sha-256, from any address of the compose networks).
# Every start: the server in the foreground (STOPSIGNAL SIGINT: a fast, clean shutdown).
set -eu

if [ ! -s "$PGDATA/PG_VERSION" ]; then
    if [ -z "${POSTGRES_PASSWORD:-}" ]; then
        echo "POSTGRES_PASSWORD is empty: set it in docker/.env (e.g. openssl rand -hex 24), then start again." >&2
        exit 1
    fi
    pwfile="$(mktemp)"
    printf '%s\n' "$POSTGRES_PASSWORD" > "$pwfile"
    initdb -D "$PGDATA" -U lifecycle --pwfile="$pwfile" --auth-local=scram-sha-256 --auth-host=scram-sha-256 \
        --encoding=UTF8 --locale=C.UTF-8 >/dev/null
    rm -f "$pwfile"
    printf 'host all all all scram-sha-256\n' >> "$PGDATA/pg_hba.conf"
    echo "CREATE DATABASE lifecycle OWNER lifecycle;" | postgres --single -D "$PGDATA" -j postgres >/dev/null
    echo "created the cluster in $PGDATA (user and database lifecycle)"
fi
exec postgres -D "$PGDATA" -c listen_addresses='*' -c "max_connections=${POSTGRES_MAX_CONNECTIONS:-150}"
