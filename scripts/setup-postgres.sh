#!/usr/bin/env bash
# PostgreSQL for the queue tests (issue 11): installs Debian's `postgresql` if missing,
# starts its cluster with `pg_ctlcluster`, and makes the role and database that
# LIGHTMAPD_TEST_POSTGRES names (default
# postgres://lightmapd:lightmapd@127.0.0.1:5432/lightmapd). Each test then makes its own
# schema inside that database, so tests run in parallel.
# Idempotent: installs only what is missing, starts only a stopped cluster, creates only
# a missing role or database. Runs as root or through sudo. Called from scripts/setup.sh.
set -euo pipefail

SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"

if ! dpkg-query -W -f='${Status}' postgresql 2>/dev/null | grep -q "install ok installed"; then
    echo "setup-postgres: installing postgresql" >&2
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends postgresql >/dev/null
fi

# The newest installed major version's `main` cluster (Debian creates it on install).
ver=$(ls /usr/lib/postgresql | sort -n | tail -1)
if ! pg_lsclusters -h | awk -v v="$ver" '$1 == v && $2 == "main"' | grep -q .; then
    $SUDO pg_createcluster "$ver" main >/dev/null
fi
if ! pg_lsclusters -h | awk -v v="$ver" '$1 == v && $2 == "main" && $4 == "online"' | grep -q .; then
    echo "setup-postgres: starting cluster $ver/main" >&2
    $SUDO pg_ctlcluster "$ver" main start
fi

# The tests expect port 5432. Debian gives a new cluster the next free port when 5432 is
# taken (e.g. by a cluster that was still shutting down during a reinstall): move it back.
port=$(pg_lsclusters -h | awk -v v="$ver" '$1 == v && $2 == "main" {print $3}')
if [ "$port" != 5432 ]; then
    echo "setup-postgres: cluster $ver/main listens on $port; moving it to 5432" >&2
    $SUDO pg_conftool "$ver" main set port 5432
    $SUDO pg_ctlcluster "$ver" main restart
fi

# TLS (issue 24: the queue connects with rustls and honours sslmode; tests/service/hardening.rs
# checks it): Debian turns ssl on with the ssl-cert package's self-signed "snakeoil"
# certificate. Where ssl is off, make a self-signed certificate for the cluster and turn
# it on. The certificate is world-readable (the test verifies against it); the key is the
# postgres user's only.
ssl=$(pg_conftool -s "$ver" main show ssl 2>/dev/null || echo off)
if [ "$ssl" != "on" ] && [ "$ssl" != "true" ]; then
    echo "setup-postgres: turning on TLS with a self-signed certificate" >&2
    if ! command -v openssl >/dev/null; then
        $SUDO apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends openssl >/dev/null
    fi
    conf="/etc/postgresql/$ver/main"
    # Not a CA certificate (rustls refuses a CA certificate as a server's own), like
    # Debian's snakeoil one.
    ext=$(mktemp)
    printf '[req]\ndistinguished_name = dn\nx509_extensions = ext\n[dn]\n[ext]\nbasicConstraints = critical, CA:FALSE\nsubjectAltName = DNS:localhost, IP:127.0.0.1\n' > "$ext"
    $SUDO openssl req -x509 -newkey rsa:2048 -nodes -days 3650 -subj "/CN=localhost" -config "$ext" \
        -keyout "$conf/lightmapd-test.key" -out "$conf/lightmapd-test.crt" 2>/dev/null
    rm -f "$ext"
    $SUDO chown postgres:postgres "$conf/lightmapd-test.key" "$conf/lightmapd-test.crt"
    $SUDO chmod 0600 "$conf/lightmapd-test.key"
    $SUDO chmod 0644 "$conf/lightmapd-test.crt"
    $SUDO pg_conftool "$ver" main set ssl_cert_file "$conf/lightmapd-test.crt"
    $SUDO pg_conftool "$ver" main set ssl_key_file "$conf/lightmapd-test.key"
    $SUDO pg_conftool "$ver" main set ssl on
    $SUDO pg_ctlcluster "$ver" main restart
fi

# Wait for it to accept connections (a fresh start takes a moment); fail loudly if not.
ready=""
for _ in $(seq 1 100); do
    if pg_isready -q -h 127.0.0.1 -p 5432; then ready=1; break; fi
    sleep 0.2
done
if [ -z "$ready" ]; then
    echo "setup-postgres: nothing accepts connections on 127.0.0.1:5432 after 20 s (pg_lsclusters: $(pg_lsclusters -h | tr '\n' ' '))" >&2
    exit 1
fi

# psql as the cluster's superuser (peer authentication over the local socket).
psql_su() {
    if [ "$(id -u)" -eq 0 ]; then
        runuser -u postgres -- psql -X -q -v ON_ERROR_STOP=1 "$@"
    else
        sudo -u postgres psql -X -q -v ON_ERROR_STOP=1 "$@"
    fi
}
if [ "$(psql_su -tAc "SELECT 1 FROM pg_roles WHERE rolname = 'lightmapd'")" != "1" ]; then
    psql_su -c "CREATE ROLE lightmapd LOGIN PASSWORD 'lightmapd'"
fi
if [ "$(psql_su -tAc "SELECT 1 FROM pg_database WHERE datname = 'lightmapd'")" != "1" ]; then
    psql_su -c "CREATE DATABASE lightmapd OWNER lightmapd"
fi
echo "setup-postgres: ready at postgres://lightmapd:lightmapd@127.0.0.1:5432/lightmapd" >&2
