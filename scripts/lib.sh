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

# One world served by edges over NATS (issue 23; `scripts/cluster.sh`, `EDGE=1
# scripts/capacity.sh`). Each start_* waits for its process's ready line (bounded: 20 s
# for nats-server, 120 s for the others, which may build their data set's cache) and
# needs $state (start_server's, or `state=$(mktemp -d)`); each process's log is in
# $state. The binaries are taken from $BIN_DIR as above.
#
# start_nats [PREFIX...]: nats-server on a loopback port it picks; sets $nats (its pid)
#   and $nats_url.
# start_world DATA [PREFIX...]: `roam-server world DATA` on $nats_url (world $WORLD,
#   default `bench`; $WORLD_ARGS adds flags); sets $world (its pid).
# start_edge DATA [PREFIX...]: `roam-server edge DATA --listen 127.0.0.1:0` of that world
#   ($SERVE_ARGS adds flags, as to `serve`); sets $edge (its pid), $addr, $token and
#   $fingerprint, as start_server does. Its log is $state/edge.log.
# start_cluster DATA [PREFIX...]: all three, nats-server and the world each run after
#   $CLUSTER_PREFIX (e.g. `taskset -c 1`), the edge after PREFIX; then $server is the
#   edge's pid (what a script measuring `serve` measures) and $state/server.log its log;
#   without an EXIT trap of the caller's, one that stops the three and removes $state.
# stop_pid PID...: SIGINT, up to 10 s to exit, then SIGKILL. stop_cluster stops the three.

# wait_line LOG PATTERN PID SECONDS WHAT: waits until LOG has a line matching PATTERN;
# fails, showing LOG, if PID exits first or SECONDS pass.
wait_line() {
    local log=$1 pattern=$2 pid=$3 seconds=$4 what=$5 i
    for ((i = 0; i < seconds * 10; i++)); do
        grep -qs -- "$pattern" "$log" && return 0
        kill -0 "$pid" 2>/dev/null || { echo "error: $what exited:" >&2; cat "$log" >&2; exit 1; }
        sleep 0.1
    done
    echo "error: $what did not say '$pattern' in $seconds s:" >&2
    cat "$log" >&2
    exit 1
}

start_nats() {
    local log="$state/nats.log"
    "$@" nats-server -a 127.0.0.1 -p -1 >"$log" 2>&1 &
    nats=$!
    wait_line "$log" 'Server is ready' "$nats" 20 nats-server
    nats_url="nats://$(sed -n 's/.*Listening for client connections on \([^ ]*\).*/\1/p' "$log" | head -n 1)"
    [[ "$nats_url" == nats://?*:?* ]] || { echo "error: where nats-server listens?" >&2; cat "$log" >&2; exit 1; }
}

# bus_args: the flags that give the world, an edge or bus-load the cluster's secret
#   ($state/bus.key, made once), or `--insecure-bus` when INSECURE_BUS=1.
bus_args() {
    if [[ "${INSECURE_BUS:-0}" == 1 ]]; then
        echo --insecure-bus
        return
    fi
    # Two callers at once (a command started in the background) may both make it: the
    # second is refused (never over a file) and uses the first's.
    [[ -s "$state/bus.key" ]] || "${BIN_DIR:-target/release}/roam-server" bus-secret "$state/bus.key" >/dev/null 2>&1 ||
        [[ -s "$state/bus.key" ]] || { echo "error: could not write $state/bus.key" >&2; exit 1; }
    echo --bus-secret "$state/bus.key"
}

start_world() {
    local data=$1
    shift
    local log="$state/world.log"
    # shellcheck disable=SC2046
    "$@" "${BIN_DIR:-target/release}/roam-server" world "$data" --nats "$nats_url" \
        --world "${WORLD:-bench}" --state-dir "$state/world" $(bus_args) ${WORLD_ARGS:-} >"$log" 2>&1 &
    world=$!
    wait_line "$log" '^serve it with:' "$world" 120 "roam-server world"
}

start_edge() {
    local data=$1
    shift
    local log="$state/edge.log"
    # shellcheck disable=SC2046
    "$@" "${BIN_DIR:-target/release}/roam-server" edge "$data" --nats "$nats_url" \
        --world "${WORLD:-bench}" --listen 127.0.0.1:0 --state-dir "$state/edge" $(bus_args) \
        ${SERVE_ARGS:-} >"$log" 2>&1 &
    edge=$!
    wait_line "$log" '^connect with:' "$edge" 120 "roam-server edge"
    read -r addr token fingerprint < <(sed -n 's/^connect with: roam-client --connect \([^ ]*\) --token \([^ ]*\) --fingerprint \([^ ]*\).*/\1 \2 \3/p' "$log")
    [[ -n "${fingerprint:-}" ]] || { echo "error: the edge did not say how to connect" >&2; cat "$log" >&2; exit 1; }
}

start_cluster() {
    local data=$1
    shift
    [[ -n "${state:-}" ]] || state=$(mktemp -d)
    # Stopped on exit, unless the caller already said what to do then.
    [[ -n "$(trap -p EXIT)" ]] || trap 'stop_cluster; rm -rf "$state"' EXIT
    # shellcheck disable=SC2086
    start_nats ${CLUSTER_PREFIX:-}
    # shellcheck disable=SC2086
    start_world "$data" ${CLUSTER_PREFIX:-}
    start_edge "$data" "$@"
    server=$edge
    ln -sf edge.log "$state/server.log"
}

stop_pid() {
    local pid i
    for pid in "$@"; do
        [[ -n "$pid" ]] && kill -INT "$pid" 2>/dev/null || continue
        for ((i = 0; i < 100; i++)); do
            kill -0 "$pid" 2>/dev/null || break
            sleep 0.1
        done
        kill -KILL "$pid" 2>/dev/null || true
        wait "$pid" 2>/dev/null || true
    done
}

stop_cluster() {
    stop_pid "${edge:-}" "${world:-}" "${nats:-}"
}
