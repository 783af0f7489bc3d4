#!/usr/bin/env bash
# Install and start what the service tests need on a fresh Debian machine (run as root):
# PostgreSQL (a server, a user and a database for tests/service) and Debian's chromium (browser tests).
#
#   eval "$(.ci/services.sh)"      # exports MAPFREE_TEST_PG (also written to .ci/services.env)
#   make test
#
# Without it, `make test` still passes: the PostgreSQL parametrisation skips ("MAPFREE_TEST_PG is not set")
# and browser tests skip only when /usr/bin/chromium is absent. All progress goes to stderr; stdout carries
# only `export` lines.
set -euo pipefail
cd "$(dirname "$0")/.."
export DEBIAN_FRONTEND=noninteractive
PGUSER_NAME=${MAPFREE_PG_USER:-mapfree}
PGPASS=${MAPFREE_PG_PASSWORD:-mapfree}
PGDB=${MAPFREE_PG_DB:-mapfree_test}
PGPORT=${MAPFREE_PG_PORT:-5432}

need=()
command -v pg_ctlcluster >/dev/null 2>&1 || need+=(postgresql)
[ -x /usr/bin/chromium ] || need+=(chromium)
command -v fc-list >/dev/null 2>&1 || need+=(fonts-dejavu-core)
if [ ${#need[@]} -gt 0 ]; then
  echo "services: apt-get install ${need[*]}" >&2
  apt-get update -qq >&2
  apt-get install -y -qq --no-install-recommends "${need[@]}" >&2
fi

# A cluster (the package usually creates one; containers sometimes skip it), started without systemd.
PGVER=$(ls /usr/lib/postgresql | sort -V | tail -1)
if ! pg_lsclusters -h | awk '{print $1" "$2}' | grep -q "^$PGVER main$"; then
  pg_createcluster --port "$PGPORT" "$PGVER" main >&2
fi
PGPORT=$(pg_lsclusters -h | awk -v v="$PGVER" '$1==v && $2=="main" {print $3}')
if ! pg_lsclusters -h | awk -v v="$PGVER" '$1==v && $2=="main" {print $4}' | grep -q online; then
  pg_ctlcluster "$PGVER" main start >&2
fi
for _ in $(seq 1 60); do
  pg_isready -q -h 127.0.0.1 -p "$PGPORT" && break
  sleep 0.5
done
pg_isready -h 127.0.0.1 -p "$PGPORT" >&2

as_pg() { runuser -u postgres -- psql -p "$PGPORT" -v ON_ERROR_STOP=1 -qtAc "$1"; }
if [ "$(as_pg "SELECT 1 FROM pg_roles WHERE rolname='$PGUSER_NAME'")" != "1" ]; then
  as_pg "CREATE ROLE $PGUSER_NAME LOGIN PASSWORD '$PGPASS' CREATEDB" >&2
fi
if [ "$(as_pg "SELECT 1 FROM pg_database WHERE datname='$PGDB'")" != "1" ]; then
  as_pg "CREATE DATABASE $PGDB OWNER $PGUSER_NAME" >&2
fi

URL="postgresql+psycopg://$PGUSER_NAME:$PGPASS@127.0.0.1:$PGPORT/$PGDB"
{
  echo "export MAPFREE_TEST_PG='$URL'"
} | tee .ci/services.env
echo "services: PostgreSQL $PGVER on 127.0.0.1:$PGPORT (db $PGDB), chromium at $(command -v chromium)" >&2
