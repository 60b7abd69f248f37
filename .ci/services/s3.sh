# Sourced by .ci/run: moto's S3 server on loopback for the whole test run.
# Exports LODSERVER_TEST_S3_ENDPOINT (read by tests/services/s3.py) and registers
# its stop in STOPS. A server that does not answer within 60 s fails the run.
s3_port=$(python -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
python -m moto.server -H 127.0.0.1 -p "$s3_port" >/dev/null 2>&1 &
s3_pid=$!
STOPS+=("kill $s3_pid")
export LODSERVER_TEST_S3_ENDPOINT="http://127.0.0.1:$s3_port"
if ! python - "$LODSERVER_TEST_S3_ENDPOINT" <<'PY'
import sys, time
sys.path.insert(0, ".")
from tests.services.s3 import answers
deadline = time.monotonic() + 60
while not answers(sys.argv[1]):
    if time.monotonic() > deadline:
        sys.exit(f"moto_server did not answer at {sys.argv[1]} within 60 s")
    time.sleep(0.2)
PY
then
    echo "s3.sh: the S3 server (moto) did not start" >&2
    exit 1
fi
echo "s3.sh: moto S3 server at $LODSERVER_TEST_S3_ENDPOINT (pid $s3_pid)"
