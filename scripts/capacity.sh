#!/usr/bin/env bash
# Viewers served per server core (docs/figures.md, command E), every viewer driving.
#
# The server runs pinned to CPU 0; the load generator (`roam-client --headless --viewers N
# --skip-decode`: N viewers that acknowledge every frame without decoding it, and let colour
# tiles go undecoded after the join's) runs pinned to CPU 1. Every viewer drives: `scripts/capacity-drive.txt` (45 s of throttle, brakes and
# turns both ways), played again each time it ends (`--loop-inputs`), each viewer from
# another of its lines. For each N, one JSON line: the generator's report (its keys, see
# `client/src/stats.rs`) and
#   - frames_per_second_min: the slowest viewer's frames taken a second (>= 55 counts as
#     served at 60 Hz); frames_sent_per_second_min: the slowest viewer's frames the server
#     made a second (from the frame numbers); frames_lost: made and not taken;
#   - join_errors: viewers that could not join (the others are measured), errors: viewers
#     whose session ended early;
#   - gap_ms_max: the longest time between two frames, after each viewer's first;
#   - server_cpu_us_per_frame: the server's CPU time over the run ÷ frames taken (all
#     viewers), µs;
#   - server_cpu_share, generator_cpu_share: CPU seconds ÷ wall seconds of the run, so a
#     saturated generator (near 1.0) is seen rather than mistaken for the server.
#
#   scripts/capacity.sh [N ...]          (default: 5 10 15 20 25 30 35 40)
#   scripts/capacity.sh --in-step [N ...] (every viewer drives the script from its first
#                                          line, each step at the same instant: a group
#                                          turning together; each line adds "in_step": true)
#   scripts/capacity.sh --join-storm     (the join storm: see below)
#   PROFILE=measure BUDGET=32768 FRAMES=1800 DATA=data/kossou scripts/capacity.sh 20 30
#
# The join storm: 20 viewers, each its own generator process, join 0.3 s apart and
# drive; 6 s after the 20th, 10 more join at once in one process (every generator process
# on CPU 1). One JSON line with each group's figures (`staggered`, `burst`: gap_ms_max
# after each viewer's first frame, frames_per_second_min, frames_sent_per_second_min,
# frames_lost, first_frame_after_join_ms_max) and the CPU figures over the whole storm;
# then one line for 40 viewers joining at once (one process, `--viewers 40`), as above.
#
# SERVER_LOG=FILE keeps the server's log there. BIN_DIR=DIR runs the binaries found there,
# unbuilt (to compare two builds in turn).
#
# EDGE=1 measures an edge's core instead (issue 23; `scripts/cluster.sh capacity`):
# nats-server, `roam-server world` and `roam-server edge` (scripts/lib.sh's
# start_cluster), the edge pinned to CPU 0 where `serve` would be, nats-server and the
# world on CPU 1 beside the load generator. `server_cpu_*` are then the edge's; each line
# adds `mode: "edge"`, `world_cpu_share` and `nats_cpu_share`, and SERVER_LOG keeps the
# edge's log (SERVE_ARGS go to the edge).
#
# PROFILE (default release) is the cargo profile built and run (`measure`: a quicker
# build, no LTO); DRIVE replaces the drive script.
set -euo pipefail
cd "$(dirname "$0")/.."

PROFILE=${PROFILE:-release}
BUDGET=${BUDGET:-32768}
FRAMES=${FRAMES:-1800}
DATA=${DATA:-data/kossou}
DRIVE=${DRIVE:-scripts/capacity-drive.txt}
STORM=0
IN_STEP=()
if [[ "${1:-}" == "--in-step" ]]; then
    IN_STEP=(--in-step)
    shift
fi
if [[ "${1:-}" == "--join-storm" ]]; then
    STORM=1
    shift
fi
COUNTS=("$@")
((${#COUNTS[@]})) || COUNTS=(5 10 15 20 25 30 35 40)
# More viewers than the server admits by default (64): it is told to take them all.
most=0
for n in "${COUNTS[@]}"; do ((n > most)) && most=$n; done
if ((most > 64)); then
    SERVE_ARGS="--max-viewers $most ${SERVE_ARGS:-}"
    export SERVE_ARGS
fi
if (($(nproc) < 2)); then
    echo "error: needs two CPUs (one for the server, one for the load generator)" >&2
    exit 1
fi
if [[ -z "${BIN_DIR:-}" ]]; then
    BIN_DIR="${CARGO_TARGET_DIR:-target}/$PROFILE"
    cargo build --profile "$PROFILE" -p roam-server -p roam-client >&2
fi
export BIN_DIR
# shellcheck source=scripts/lib.sh
source scripts/lib.sh
if [[ "${EDGE:-0}" == 1 ]]; then
    CLUSTER_PREFIX="taskset -c 1" start_cluster "$DATA" taskset -c 0
    trap 'stop_cluster; [[ -z "${SERVER_LOG:-}" ]] || cp "$state/server.log" "$SERVER_LOG"; rm -rf "$state"' EXIT
else
    start_server "$DATA" taskset -c 0
    # SERVER_LOG=FILE keeps the server's log (its summary lines: key frames, late frames).
    trap 'stop_server; [[ -z "${SERVER_LOG:-}" ]] || cp "$state/server.log" "$SERVER_LOG"; rm -rf "$state"' EXIT
fi

# CPU seconds (user + system) a process has used so far.
cpu() { awk -v hz="$(getconf CLK_TCK)" '{ print ($14 + $15) / hz }' "/proc/$1/stat"; }
now() { date +%s.%N; }
# With EDGE=1: the world's and nats-server's CPU seconds so far (else nothing).
cluster_cpu() { if [[ "${EDGE:-0}" == 1 ]]; then echo "$(cpu "$world") $(cpu "$nats")"; fi; }

# generate NAME VIEWERS: one generator process on CPU 1, in the background; its report
# goes to $state/NAME.json, its CPU time to $state/NAME.time.
generate() {
    /usr/bin/time -f '%U %S' -o "$state/$1.time" taskset -c 1 "$BIN_DIR/roam-client" \
        --connect "$addr" --token "$token" --fingerprint "$fingerprint" --headless \
        --viewers "$2" --budget "$BUDGET" --frames "$FRAMES" --skip-decode \
        --inputs "$DRIVE" --loop-inputs "${IN_STEP[@]}" --stats "$state/$1.json" 2>"$state/$1.err" ||
        { echo "error: generator $1 failed:" >&2; cat "$state/$1.err" >&2; }
}

# summary START END SERVER_CPU_BEFORE GROUP=NAME,NAME... ...: one JSON line from the
# generators' reports (grouped) and the CPU figures over START..END.
summary() {
    local start=$1 end=$2 before=$3
    shift 3
    python3 - "$state" "$start" "$end" "$before" "$(cpu "$server")" "$@" <<'EOF'
import json, os, sys
state, start, end, before, after, *groups = sys.argv[1:]
wall = float(end) - float(start)
out, frames, gen_cpu = {}, 0, 0.0

def merge(reports):
    """One group's figures from its processes' reports."""
    g = {
        "viewers": sum(r["viewers"] for r in reports),
        "frames": sum(r["frames"] for r in reports),
        "frames_sent": sum(r["frames_sent"] for r in reports),
        "frames_lost": sum(r["frames_lost"] for r in reports),
        "errors": sum(r["errors"] for r in reports),
        "join_errors": sum(r.get("join_errors", 0) for r in reports),
        "reconnects": sum(r["reconnects"] for r in reports),
        "frames_per_second_min": min(r["frames_per_second_min"] for r in reports),
        "frames_sent_per_second_min": min(r["frames_sent_per_second_min"] for r in reports),
        "gap_ms_max": max(r["gap_ms_max"] for r in reports),
        "first_frame_after_join_ms_max": max(r["first_frame_after_join_ms_max"] for r in reports),
    }
    n = g["viewers"]
    g["frames_per_second"] = sum(r["frames_per_second"] * r["viewers"] for r in reports) / n
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in g.items()}

for group in groups:
    label, names = group.split("=")
    reports = []
    for name in names.split(","):
        reports.append(json.load(open(f"{state}/{name}.json")))
        user, sys_ = open(f"{state}/{name}.time").read().split()[-2:]
        gen_cpu += float(user) + float(sys_)
    g = merge(reports)
    frames += g["frames"]
    if label == "all":
        # One group: its keys at the top level, beside the first process's whole report.
        out.update({k: v for k, v in reports[0].items() if k not in g})
        out.update(g)
    else:
        out[label] = g
server_cpu = float(after) - float(before)
out["server_cpu_share"] = round(server_cpu / wall, 3)
out["generator_cpu_share"] = round(gen_cpu / wall, 3)
out["server_cpu_us_per_frame"] = round(server_cpu / max(frames, 1) * 1e6, 1)
out["wall_s"] = round(wall, 2)
if os.environ.get("IN_STEP"):
    out["in_step"] = True
cluster = os.environ.get("CLUSTER_CPU", "").split()
if len(cluster) == 4:  # EDGE=1: world and nats-server before, then after
    out["mode"] = "edge"
    out["world_cpu_share"] = round((float(cluster[2]) - float(cluster[0])) / wall, 3)
    out["nats_cpu_share"] = round((float(cluster[3]) - float(cluster[1])) / wall, 3)
print(json.dumps(out, sort_keys=True))
EOF
}

# One process of N viewers joining at once.
at_once() {
    local n=$1 before start end cluster
    before=$(cpu "$server")
    cluster=$(cluster_cpu)
    start=$(now)
    generate "n$n" "$n"
    end=$(now)
    IN_STEP="${IN_STEP[*]}" CLUSTER_CPU="$cluster $(cluster_cpu)" summary "$start" "$end" "$before" "all=n$n"
}

if ((STORM)); then
    before=$(cpu "$server")
    cluster=$(cluster_cpu)
    start=$(now)
    pids=()
    names=()
    for i in $(seq 1 20); do
        generate "s$i" 1 &
        pids+=($!)
        names+=("s$i")
        sleep 0.3
    done
    sleep 5.7
    generate burst 10 &
    pids+=($!)
    wait "${pids[@]}"
    end=$(now)
    CLUSTER_CPU="$cluster $(cluster_cpu)" summary "$start" "$end" "$before" "staggered=$(
        IFS=,
        echo "${names[*]}"
    )" "burst=burst"
    at_once 40
    exit 0
fi

for n in "${COUNTS[@]}"; do
    at_once "$n"
done
