# shellcheck shell=bash
# PostgreSQL for the shared-catalogue tests: a throwaway cluster from the
# machine's Debian packages on a free loopback port. Sourced by .ci/run, which
# runs every command appended to STOPS on exit.
#
# Exports LODSERVER_TEST_POSTGRES_URL (tests/services/postgres.py reads it; each
# test module then makes a database of its own on this server).

pg_bin=$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -n 1)
if [ -z "$pg_bin" ] || [ ! -x "$pg_bin/initdb" ]; then
    echo "postgres.sh: no PostgreSQL under /usr/lib/postgresql (apt-get install postgresql)" >&2
    return 1
fi
pg_dir=$(mktemp -d "${TMPDIR:-/tmp}/lodserver-pg.XXXXXX")
# initdb refuses to run as root: the cluster belongs to the postgres user then
pg_as=()
if [ "$(id -u)" = 0 ]; then
    chown postgres "$pg_dir"
    pg_as=(runuser -u postgres --)
fi
pg_port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
"${pg_as[@]}" "$pg_bin/initdb" -D "$pg_dir/data" -U postgres -A trust --no-sync \
    >"$pg_dir/initdb.log" 2>&1 || { cat "$pg_dir/initdb.log" >&2; return 1; }
# The socket goes to the cluster's own folder (/var/run/postgresql may not exist);
# fsync off: the data is thrown away with the folder.
"${pg_as[@]}" "$pg_bin/pg_ctl" -D "$pg_dir/data" -l "$pg_dir/server.log" -w -t 60 \
    -o "-c listen_addresses=127.0.0.1 -p $pg_port -k $pg_dir -c fsync=off -c max_connections=200" \
    start >/dev/null || { cat "$pg_dir/server.log" >&2; return 1; }
STOPS+=("${pg_as[*]} $pg_bin/pg_ctl -D $pg_dir/data -m fast -w stop >/dev/null; rm -rf $pg_dir")
export LODSERVER_TEST_POSTGRES_URL="postgresql://postgres@127.0.0.1:$pg_port/postgres"
echo "PostgreSQL on 127.0.0.1:$pg_port (stopped on exit)"
