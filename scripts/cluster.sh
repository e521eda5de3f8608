#!/usr/bin/env bash
# One world served by edges over NATS (issue 23): the figures, each as JSON lines. This
# machine runs everything: nats-server (Debian's), `roam-server world`, and the edges or
# the load generator.
#
#   scripts/cluster.sh latency            (what the bus adds between a key and its frame)
#   scripts/cluster.sh fanout [N ...]     (snapshot fan-out; default 10 100 1000 vehicles)
#   scripts/cluster.sh capacity [N ...]   (viewers per edge core: EDGE=1 scripts/capacity.sh)
#   scripts/cluster.sh proofs [N]         (the world's CPU with the bus sealed against plain)
#   PROFILE=measure scripts/cluster.sh fanout 10 100 1000
#
# Every line has `loadavg` (the 1-minute load average when it was printed: this is a
# shared 2-core machine, so the figures are only as quiet as it was).
#
# latency: `roam-server serve` and a cluster (nats-server, `roam-server world`, one
# `roam-server edge`) run side by side on `data/kossou`, unpinned (as `scripts/lossy.sh`
# runs its server), each idle while the other is measured. ROUNDS rounds (default 4) of
# VIEWERS headless viewers in one process (default 4; `roam-client --headless --viewers
# 4 --budget 32768 --frames 900 --inputs DRIVE`, each driving its own vehicle, the drive
# changing keys every 100 ms: Up, Up-left, Up, Up-right) through `serve`, then through
# the edge: A/B/A/B, since the machine is noisy. One line per run: `via` (serve or
# edge), `run`, `input_to_frame_ms_median` and `_p99` (each key change to the first frame
# showing it applied, every viewer's changes pooled: the viewers' own stats),
# `frames_per_second`, `decode_errors`, `gap_ms_max`, `reconnects`; then a summary line:
# `serve_p99_ms` and `edge_p99_ms` (the runs' medians), `bus_adds_p99_ms` (edge − serve:
# issue 23 asks ≤ 5, aim ≤ 2), the same for the medians (`bus_adds_median_ms`), and each
# run's p99s (`serve_p99s`, `edge_p99s`). Why several viewers: a driver's latency moves
# with the phase of its key clock against the world's tick and with how many key states
# its world-side queue holds (`sim/world_core.rs`: PRIME, CATCH_UP, TRIM_AFTER); the
# viewers of one `--viewers N` process have their key clocks spread over the 10 ms step,
# so a run samples every phase. One viewer a run gave per-run medians from 9.9 to 23.2 ms
# through the same `serve` (16 runs), which hides a few milliseconds.
#
# fanout: nats-server and the world on the loopback; for each N, `roam-server bus-load`
# (the load generator, hidden from `--help`, documented in server/src/cli/bus_load.rs)
# stands in for EDGES fake edges (default 4): it joins N vehicles over request-reply,
# says each fake edge's hello every 500 ms, publishes each fake edge's drivers' key
# states every 10 ms (every vehicle driving: throttle and turns), counts each fake edge's
# snapshots, and after 3 s of warm-up measures WINDOW_S seconds (default 10). On 2
# CPUs the world is pinned alone to CPU 0, nats-server and the generator to CPU 1
# (`taskset`). One line per N: the generator's report (its keys in bus_load.rs's `report`) and
#   - world_cpu_us_per_tick: the world process's CPU time (utime + stime from
#     /proc/PID/stat, every thread: physics, key decoding, snapshot encoding, publishing)
#     over the window ÷ the ticks it made in the window (the snapshots' `tick`), µs.
#     Issue 23 asks ≤ 2,000 at 1,000 vehicles and 4 edges (aim ≤ 500);
#   - world_cpu_share, nats_cpu_share, generator_cpu_share: CPU seconds ÷ the window's;
#   - nats_cpu_us_per_tick: nats-server's CPU time (the fan-out itself) per tick;
#   - snapshot_bytes_per_s_per_edge: snapshot payload bytes a second each edge gets
#     (mean over the fake edges), snapshot_bytes_mean (one snapshot), snapshots_per_s;
#   - vehicles_moved: vehicles that moved over the window (every one must: a parked
#     load is no load); keys_to_snapshot_ms_median/_p99: a key state published to the
#     first snapshot showing it applied (the bus both ways plus the world's key queue).
#
# proofs: what sealing every bus message (issue 39: `--bus-secret`) costs the world.
# ROUNDS_SET rounds (default 3) of fanout's measure at N vehicles (default 1000) over EDGES
# fake edges, each round once with the cluster's secret and once `--insecure-bus` (A/B,
# alternating which goes first), nats-server and the world started afresh for each run.
# One line per run (fanout's, with `proofs`: true or false), then a summary:
# `sealed_us_per_tick` and `plain_us_per_tick` (the runs' medians of
# world_cpu_us_per_tick), their `ratio` (issue 39 asks ≤ 1.2), and each run's figures.
#
# capacity: `EDGE=1 scripts/capacity.sh N ...` (default as capacity.sh's): capacity.sh's
# measure of a `serve` core, the edge in `serve`'s place (pinned to CPU 0) and
# nats-server and the world on CPU 1 with the load generator; `server_cpu_*` are the
# edge's, plus `world_cpu_share` and `nats_cpu_share`, `mode: "edge"`.
#
# PROFILE (default release) is the cargo profile built and run (`measure`: a quicker
# build, no LTO); BIN_DIR=DIR runs the binaries there, unbuilt. DATA (data/kossou),
# BUDGET (32768), FRAMES (900), ROUNDS (4), VIEWERS (4), EDGES (4), WINDOW_S (10) and
# WORLD (`bench`, the world's name on NATS) set the runs; OUT=DIR keeps the logs and stats there.
#
# Measured on 2026-11-26, evening, PROFILE=measure, the 2 cores shared with other
# sessions (load average in each line; provisional):
# - latency, 4 viewers a run, before the world trimmed its key queues and the viewers'
#   key clocks were spread: +6.1 ms on the p99 (two sessions of 4 rounds). After, four
#   sessions (3, 6, 6, 6 rounds; load 0.1–1.5): +0.4, +2.0, +5.8, +4.6 ms on the p99;
#   the 21 rounds pooled, the medians of the runs' p99s 30.1 (serve) and 34.7 ms (edge):
#   +4.6 (the medians +2.5). On a 16-core machine (the GPU machine lent to that session,
#   stripped binaries and Debian's nats-server carried there, BIN_DIR set, nothing else
#   running), two sessions of 6 rounds: −1.3 and +0.8; pooled 26.5 and 25.9 ms: −0.7.
# - fanout, 4 fake edges, two runs: snapshots of 376 / 3,706 / 40,446 bytes at 10 / 100
#   / 1,000 vehicles, 37.6 KB / 371 KB / 4.04 MB a second to each edge, every snapshot
#   delivered; the world's CPU 100–180 / 170–230 / 560–700 µs a tick (≤ 2,000 asked at
#   1,000 vehicles, aim 500); nats-server 2–4.4 % of a core; every vehicle moving. Later
#   (the world finding a key event's driver by binary search, not a walk), two runs:
#   100–130 / 140–160 / 450–500 µs; seven runs at 1,000 that session (`fanout 1000`,
#   WINDOW_S=8 for five): six at 437–500 (median 462), one at 762 with load 0.8.
# - capacity, 40 and 60 viewers, two runs each, interleaved with `scripts/capacity.sh`
#   (serve) on the same build: the edge served 59.5–59.7 / 59.1 frames a second to its
#   slowest viewer at 224–229 / 210–211 µs of edge CPU a frame (51–52 % / 71 % of its
#   core); `serve` 179–183 / 171–184 µs a frame, its world included. The edge publishes
#   each viewer's key datagram as it comes (some 1,500 NATS messages a second at 40
#   viewers, from nats-server's /connz) where `serve`'s world thread takes them once a
#   tick: the likeliest part of the difference.
set -euo pipefail
cd "$(dirname "$0")/.."

MODE=${1:-}
(($#)) && shift
case "$MODE" in
latency | fanout | capacity | proofs) ;;
*)
    echo "usage: scripts/cluster.sh latency | fanout [N ...] | capacity [N ...] | proofs [N]" >&2
    exit 2
    ;;
esac
command -v nats-server >/dev/null || {
    echo "error: needs Debian's nats-server (apt-get install nats-server)" >&2
    exit 1
}
PROFILE=${PROFILE:-release}
DATA=${DATA:-data/kossou}
BUDGET=${BUDGET:-32768}
FRAMES=${FRAMES:-900}
ROUNDS=${ROUNDS:-4}
VIEWERS=${VIEWERS:-4}
EDGES=${EDGES:-4}
WINDOW_S=${WINDOW_S:-10}
export WORLD=${WORLD:-bench}
if [[ -z "${BIN_DIR:-}" ]]; then
    BIN_DIR="${CARGO_TARGET_DIR:-target}/$PROFILE"
    cargo build --profile "$PROFILE" -p roam-server -p roam-client >&2
fi
export BIN_DIR

if [[ "$MODE" == capacity ]]; then
    EDGE=1 exec scripts/capacity.sh "$@"
fi

# shellcheck source=scripts/lib.sh
source scripts/lib.sh
state=
serve_pid=
cleanup() {
    stop_pid "${edge:-}" "$serve_pid" "${world:-}" "${nats:-}"
    if [[ -n "${OUT:-}" ]]; then
        mkdir -p "$OUT"
        cp -r "$state"/. "$OUT"/ 2>/dev/null || true
    fi
    [[ -z "$state" ]] || rm -rf "$state"
}
trap cleanup EXIT
loadavg() { cut -d' ' -f1 /proc/loadavg; }

if [[ "$MODE" == latency ]]; then
    start_server "$DATA"
    trap cleanup EXIT
    serve_pid=$server serve_addr=$addr serve_token=$token serve_fingerprint=$fingerprint
    start_cluster "$DATA"
    # Keys change every 100 ms (10 ticks), 20 s of it: longer than the run.
    drive="$state/drive.txt"
    for _ in $(seq 1 50); do printf '10 U\n10 UL\n10 U\n10 UR\n'; done >"$drive"
    run() { # run VIA N ADDR TOKEN FINGERPRINT: VIEWERS viewers, one JSON line
        local via=$1 n=$2 stats="$state/$1-$2.json"
        timeout 120 "$BIN_DIR/roam-client" --connect "$3" --token "$4" --fingerprint "$5" \
            --headless --viewers "$VIEWERS" --budget "$BUDGET" --frames "$FRAMES" --inputs "$drive" \
            --stats "$stats" 2>"$state/$via-$n.err" ||
            { echo "error: the viewer through $via failed:" >&2; cat "$state/$via-$n.err" >&2; exit 1; }
        python3 - "$stats" "$via" "$n" "$(loadavg)" <<'EOF'
import json, sys
path, via, n, load = sys.argv[1:]
s = json.load(open(path))
keys = ["frames", "frames_per_second", "input_to_frame_ms_median", "input_to_frame_ms_p99",
        "decode_errors", "gap_ms_max", "reconnects"]
out = {"via": via, "run": int(n), "loadavg": float(load)}
out.update({k: s[k] for k in keys if k in s})
print(json.dumps(out, sort_keys=True), flush=True)
EOF
    }
    for r in $(seq 1 "$ROUNDS"); do
        run serve "$r" "$serve_addr" "$serve_token" "$serve_fingerprint" | tee -a "$state/runs.jsonl"
        run edge "$r" "$addr" "$token" "$fingerprint" | tee -a "$state/runs.jsonl"
    done
    python3 - "$state/runs.jsonl" "$(loadavg)" <<'EOF'
import json, statistics, sys
runs = [json.loads(l) for l in open(sys.argv[1])]
def med(via, key):
    return statistics.median(r[key] for r in runs if r["via"] == via)
out = {
    "summary": "latency", "rounds": len(runs) // 2, "loadavg": float(sys.argv[2]),
    "serve_p99_ms": med("serve", "input_to_frame_ms_p99"),
    "edge_p99_ms": med("edge", "input_to_frame_ms_p99"),
    "serve_median_ms": med("serve", "input_to_frame_ms_median"),
    "edge_median_ms": med("edge", "input_to_frame_ms_median"),
    "serve_p99s": [r["input_to_frame_ms_p99"] for r in runs if r["via"] == "serve"],
    "edge_p99s": [r["input_to_frame_ms_p99"] for r in runs if r["via"] == "edge"],
}
out["bus_adds_p99_ms"] = round(out["edge_p99_ms"] - out["serve_p99_ms"], 2)
out["bus_adds_median_ms"] = round(out["edge_median_ms"] - out["serve_median_ms"], 2)
print(json.dumps(out, sort_keys=True), flush=True)
EOF
    exit 0
fi

# fanout (and proofs: fanout at one N, sealed and plain)
state=$(mktemp -d)
world_cpu=() nats_cpu=()
if (($(nproc) >= 2)); then
    world_cpu=(taskset -c 0) nats_cpu=(taskset -c 1)
fi
# measure N [KEY=VALUE]: one bus-load run at N vehicles against the running world; one
# JSON line (with KEY=VALUE added, a JSON value).
measure() {
    local n=$1 extra=${2:-} report="$state/fanout-$1.json"
    # shellcheck disable=SC2046
    timeout $((${WINDOW_S%.*} + 120)) "${nats_cpu[@]}" "$BIN_DIR/roam-server" bus-load \
        --nats "$nats_url" --world "$WORLD" $(bus_args) --vehicles "$n" --edges "$EDGES" \
        --seconds "$WINDOW_S" --cpu-pid "world=$world" --cpu-pid "nats=$nats" \
        >"$report" 2>"$state/fanout-$n.err" ||
        { echo "error: bus-load with $n vehicles failed:" >&2; cat "$state/fanout-$n.err" >&2; exit 1; }
    python3 - "$report" "$(loadavg)" "$extra" <<'EOF'
import json, sys
r = json.loads(open(sys.argv[1]).read().strip().splitlines()[-1])
r["loadavg"] = float(sys.argv[2])
r["world_cpu_us_per_tick"] = r["cpu_us_per_tick"]["world"]
r["world_cpu_share"] = r["cpu_share"]["world"]
r["nats_cpu_us_per_tick"] = r["cpu_us_per_tick"]["nats"]
r["nats_cpu_share"] = r["cpu_share"]["nats"]
for k in ("cpu_s", "cpu_us_per_tick", "cpu_share"):
    del r[k]
if sys.argv[3]:
    key, value = sys.argv[3].split("=", 1)
    r[key] = json.loads(value)
print(json.dumps(r, sort_keys=True), flush=True)
EOF
}

if [[ "$MODE" == proofs ]]; then
    n=${1:-1000}
    ROUNDS=${ROUNDS_SET:-3}
    for r in $(seq 1 "$ROUNDS"); do
        order=(1 0)
        ((r % 2)) || order=(0 1)
        for insecure in "${order[@]}"; do
            export INSECURE_BUS=$insecure
            start_nats "${nats_cpu[@]}"
            WORLD_ARGS="--max-vehicles $((n + 64)) ${WORLD_ARGS:-}" start_world "$DATA" "${world_cpu[@]}"
            proofs=true
            ((insecure)) && proofs=false
            measure "$n" "proofs=$proofs" | tee -a "$state/proofs.jsonl"
            stop_pid "$world" "$nats"
            world='' nats=''
        done
    done
    python3 - "$state/proofs.jsonl" "$(loadavg)" "$n" <<'EOF'
import json, statistics, sys
runs = [json.loads(l) for l in open(sys.argv[1])]
def figures(sealed):
    return [r["world_cpu_us_per_tick"] for r in runs if r["proofs"] == sealed]
out = {"summary": "proofs", "vehicles": int(sys.argv[3]), "loadavg": float(sys.argv[2]),
       "sealed_runs": figures(True), "plain_runs": figures(False),
       "sealed_us_per_tick": statistics.median(figures(True)),
       "plain_us_per_tick": statistics.median(figures(False))}
out["ratio"] = round(out["sealed_us_per_tick"] / out["plain_us_per_tick"], 3)
out["vehicles_moved_min"] = min(r["vehicles_moved"] for r in runs)
print(json.dumps(out, sort_keys=True), flush=True)
EOF
    exit 0
fi

COUNTS=("$@")
((${#COUNTS[@]})) || COUNTS=(10 100 1000)
most=0
for n in "${COUNTS[@]}"; do ((n > most)) && most=$n; done
start_nats "${nats_cpu[@]}"
WORLD_ARGS="--max-vehicles $((most + 64)) ${WORLD_ARGS:-}" start_world "$DATA" "${world_cpu[@]}"
for n in "${COUNTS[@]}"; do
    measure "$n"
done
