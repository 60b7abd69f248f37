# shellcheck shell=bash
# Sourced by .ci/run: a Dask scheduler and two single-thread workers on loopback
# for the whole test run. Exports LODSERVER_TEST_DASK_SCHEDULER (read by
# tests/services/dask.py) and registers its stop in STOPS. The workers run
# under nannies (a worker the tests kill -9 is restarted) and import lodserver
# from this checkout: PYTHONPATH puts it first, whatever is installed.
dask_dir=$(mktemp -d "${TMPDIR:-/tmp}/lodserver-dask.XXXXXX")
dask_env=(env "PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}")
"${dask_env[@]}" python -m distributed.cli.dask_scheduler --host 127.0.0.1 --port 0 \
    --no-dashboard --scheduler-file "$dask_dir/scheduler.json" >"$dask_dir/scheduler.log" 2>&1 &
dask_pids=($!)
# Workers first, while the scheduler can still hear them leave (then they exit in
# a second or two), the scheduler last; whatever is still up after 20 s is killed.
dask_stop() {
    local pid
    for pid in "${dask_pids[@]}"; do
        kill "$pid" 2>/dev/null || continue
        for _ in $(seq 200); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
        kill -9 "$pid" 2>/dev/null || true
    done
    rm -rf "$dask_dir"
}
STOPS+=(dask_stop)
for _ in $(seq 600); do
    [ -s "$dask_dir/scheduler.json" ] && break
    sleep 0.1
done
if [ ! -s "$dask_dir/scheduler.json" ]; then
    cat "$dask_dir/scheduler.log" >&2
    echo "dask.sh: the Dask scheduler did not start within 60 s" >&2
    return 1
fi
dask_address=$(python -c 'import json, sys; print(json.load(open(sys.argv[1]))["address"])' \
    "$dask_dir/scheduler.json")
for n in 1 2; do
    # workers first in the stop list's kill: their nannies then stop them
    (cd "$dask_dir" && exec "${dask_env[@]}" python -m distributed.cli.dask_worker \
        "$dask_address" --nthreads 1 --host 127.0.0.1 --no-dashboard \
        >"$dask_dir/worker$n.log" 2>&1) &
    dask_pids=($! "${dask_pids[@]}")
done
if ! python - "$dask_address" <<'PY'
import sys
import distributed
with distributed.Client(sys.argv[1], timeout=60) as client:
    client.wait_for_workers(2, timeout=120)
PY
then
    tail -n 20 "$dask_dir"/*.log >&2
    echo "dask.sh: the two Dask workers did not join $dask_address within 120 s" >&2
    return 1
fi
export LODSERVER_TEST_DASK_SCHEDULER="$dask_address"
echo "dask.sh: Dask scheduler at $dask_address with 2 workers (pids ${dask_pids[*]})"
