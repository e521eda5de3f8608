# Shared by the measuring scripts: start_server DATA [PREFIX...] starts `roam-server serve`
# on an ephemeral loopback port (PREFIX, e.g. `taskset -c 0`, runs before it), waits until
# it says how to connect, and sets $server (its pid), $state (a temporary directory removed
# on exit), $addr, $token and $fingerprint. The binary is taken from $BIN_DIR (default
# target/release); $SERVE_ARGS, if set, adds flags to `serve`. stop_server stops it.
start_server() {
    local data=$1
    shift
    state=$(mktemp -d)
    local log="$state/server.log"
    "$@" "${BIN_DIR:-target/release}/roam-server" serve "$data" --listen 127.0.0.1:0 --state-dir "$state" \
        ${SERVE_ARGS:-} >"$log" 2>&1 &
    server=$!
    trap 'stop_server; rm -rf "$state"' EXIT
    for _ in $(seq 1 1200); do
        grep -qs '^connect with:' "$log" && break
        kill -0 $server 2>/dev/null || { cat "$log" >&2; exit 1; }
        sleep 0.1
    done
    read -r addr token fingerprint < <(sed -n 's/^connect with: roam-client --connect \([^ ]*\) --token \([^ ]*\) --fingerprint \([^ ]*\).*/\1 \2 \3/p' "$log")
    [[ -n "${fingerprint:-}" ]] || { echo "error: the server did not say how to connect" >&2; cat "$log" >&2; exit 1; }
}

stop_server() {
    kill -INT "$server" 2>/dev/null || true
    wait "$server" 2>/dev/null || true
}
