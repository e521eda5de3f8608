#!/usr/bin/env bash
# Large terrain (docs/data.md and docs/figures.md, "Large terrain"): for each data set, one JSON line with
#   - generate_s: `roam-server generate` time, when the script had to make the set;
#   - check_cold_s / check_warm_s: `check` building the cache (only when there was none) and
#     opening it (`.cache/`: heights, variance tree);
#   - serve_to_listening_s: `roam-server serve` started to its `listening on` line (cache
#     warm: the second start; the first start, which builds the colour tiles, is
#     serve_first_to_listening_s); of the warm start, from its log: serve_open_ms (heights
#     and variance tree through the cache), serve_hash_ms (the data set's hash, cached in
#     `.cache/content.hash`), serve_server_start_ms (`Server::start`);
#   - rss_mb_one_viewer / peak_rss_mb: the server's resident memory with one headless
#     viewer driving for 600 frames (VmRSS as it leaves, VmHWM);
#   - first_frame_after_join_ms, frames_per_second: from the viewer's stats.
#
#   PROFILE=measure scripts/large_terrain.sh [DATA...]
#     (default: /tmp/synth-4097 and /tmp/synth-16385, generated if missing: 1.3 GB on disk)
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/lib.sh

PROFILE=${PROFILE:-release}
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
cargo build --profile "$PROFILE" -p roam-server -p roam-client >&2
BIN_DIR="$CARGO_TARGET_DIR/$PROFILE"
export ROAM_TOKEN=large-terrain-measuring-token

now() { date +%s.%N; }
elapsed() { awk -v a="$(now)" -v b="$1" 'BEGIN { printf "%.3f", a - b }'; }

# Starts `serve DATA` and sets $listening_s: started to its "listening on" line (the
# connect line start_server waits for comes right after it). Leaves it running.
start_timed() {
    local t0
    t0=$(now)
    start_server "$1"
    listening_s=$(elapsed "$t0")
    grep -q '^listening on' "$state/server.log"
}

if [[ $# -eq 0 ]]; then
    set -- /tmp/synth-4097 /tmp/synth-16385
fi
for data in "$@"; do
    generate_s=null
    if [[ ! -f "$data/map" ]]; then
        side=${data##*-}
        t0=$(now)
        "$BIN_DIR/roam-server" generate "$data" --side "$side" --seed 1 >/dev/null
        generate_s=$(elapsed "$t0")
    fi
    check_cold_s=null
    if [[ ! -d "$data/.cache" ]]; then
        t0=$(now)
        "$BIN_DIR/roam-server" check "$data" >/dev/null
        check_cold_s=$(elapsed "$t0")
    fi
    t0=$(now)
    "$BIN_DIR/roam-server" check "$data" >/dev/null
    check_warm_s=$(elapsed "$t0")
    # The first start builds the colour tiles when they are not cached yet.
    start_timed "$data"
    first=$listening_s
    stop_server
    rm -rf "$state"
    start_timed "$data"
    warm=$listening_s
    stats="$state/stats.json"
    printf '300 U\n200 UL\n200 U\n200 UR\n300 U\n' >"$state/drive.txt"
    "$BIN_DIR/roam-client" --connect "$addr" --token "$token" --fingerprint "$fingerprint" \
        --headless --frames 600 --stats "$stats" --inputs "$state/drive.txt" >/dev/null 2>&1 ||
        { echo "error: the viewer failed" >&2; exit 1; }
    # Where the warm start went, from its log: the data set opened (heights, variance
    # tree), its hash for the recordings, `Server::start`.
    ms_of() { sed -n "s/.*$1 \([0-9]*\) ms.*/\1/p" "$state/server.log" | head -1; }
    open_ms=$(ms_of "opened .* in")
    hash_ms=$(ms_of "data set hash [a-z]* in")
    start_ms=$(ms_of "server started in")
    rss_kb=$(awk '/^VmRSS:/ {print $2}' "/proc/$server/status")
    hwm_kb=$(awk '/^VmHWM:/ {print $2}' "/proc/$server/status")
    python3 - "$data" "$generate_s" "$check_cold_s" "$check_warm_s" "$first" "$warm" \
        "$rss_kb" "$hwm_kb" "$stats" "${open_ms:-null}" "${hash_ms:-null}" "${start_ms:-null}" <<'EOF'
import json, sys
data, gen, cold, warm_check, first, warm, rss, hwm, stats, open_ms, hash_ms, start_ms = sys.argv[1:]
s = json.load(open(stats))
num = lambda v: None if v == "null" else round(float(v), 3)
print(json.dumps({
    "data_set": data,
    "generate_s": num(gen),
    "check_cold_s": num(cold),
    "check_warm_s": num(warm_check),
    "serve_first_to_listening_s": num(first),
    "serve_to_listening_s": num(warm),
    "serve_open_ms": num(open_ms),
    "serve_hash_ms": num(hash_ms),
    "serve_server_start_ms": num(start_ms),
    "rss_mb_one_viewer": round(int(rss) / 1024, 1),
    "peak_rss_mb": round(int(hwm) / 1024, 1),
    "first_frame_after_join_ms": s.get("first_frame_after_join_ms_max"),
    "frames_per_second": s.get("frames_per_second"),
    "color_bytes": s.get("color_bytes"),
}))
EOF
    stop_server
    rm -rf "$state"
done
