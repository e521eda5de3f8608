#!/usr/bin/env bash
# The figures of docs/operations.md: what a junk flood costs a running
# server while a real viewer joins through it (`roam-flood`, one JSON line), and whether
# eight viewers asking the most triangles at the most frames a second slow the world
# (one JSON line from the server's summary log: its ticks a second and dropped ticks),
# and, as root, what a full recording disk does (one JSON line).
#
#   PROFILE=measure scripts/operations.sh      (PROFILE=release by default)
set -euo pipefail
cd "$(dirname "$0")/.."

PROFILE=${PROFILE:-release}
DATA=${DATA:-data/kossou}
cargo build --profile "$PROFILE" -p roam-server -p roam-client -p roam-tests --bins >&2
BIN_DIR="${CARGO_TARGET_DIR:-target}/$PROFILE"
export BIN_DIR
# shellcheck source=scripts/lib.sh
source scripts/lib.sh

# 1. 2,000 idle and 2,000 stalled junk connections; a viewer joins once 1,000 are open.
# Then, from the server's summary log (one a second; the wait lets the last one come), the
# longest any connection stayed pending before its hello or the server's close of it,
# against the deadline (5 s by default): what the server did, where the flood's
# `junk_close_ms_max_by_end` is what the junk heard, and when.
SERVE_ARGS="--log-every 1" start_server "$DATA"
"$BIN_DIR/roam-flood" --connect "$addr" --fingerprint "$fingerprint" --token "$token" \
    --pid "$server" --idle 2000 --stalled 2000 --frames 300
sleep 1.5
stop_server
awk '/ summary /{ for (i = 1; i <= NF; i++) { split($i, kv, "=");
        if (kv[1] == "pending_longest_ms" && kv[2] + 0 > max) max = kv[2] + 0 } }
    END { printf "{\"server_pending_longest_ms\":%d,\"hello_deadline_ms\":5000}\n", max }' \
    "$state/server.log"
rm -rf "$state"

# 2. Eight greedy viewers (2^20 triangles, 240 frames a second, not decoding) for 20 s.
# Each reserves 67 MiB of --max-memory (admission's estimate at 2^20 triangles): 4G seats
# all eight whatever the machine's default (half its available memory).
SERVE_ARGS="--log-every 2 --max-memory 4G" start_server "$DATA"
"$BIN_DIR/roam-client" --connect "$addr" --token "$token" --fingerprint "$fingerprint" \
    --headless --viewers 8 --budget 1048576 --frame-rate 240 --skip-decode --frames 100000 \
    --stats "$state/greedy.json" >/dev/null 2>&1 &
viewers=$!
sleep 20
kill -INT "$viewers" 2>/dev/null || true
wait "$viewers" 2>/dev/null || true
stop_server
awk '/ summary /{
        for (i = 1; i <= NF; i++) {
            split($i, kv, "=");
            if (kv[1] == "ticks_per_s" && kv[2] + 0 > 0) { n++; t = kv[2] + 0; if (min == "" || t < min) min = t; sum += t }
            if (kv[1] == "dropped_ticks") dropped += kv[2];
            if (kv[1] == "fps") { f = kv[2] + 0; if (f > fps) fps = f }
        }
    }
    END { printf "{\"summaries\":%d,\"world_ticks_per_s_min\":%s,\"world_ticks_per_s_mean\":%.2f,\"dropped_ticks\":%d,\"frames_served_per_s_max\":%s}\n", n, min, sum / n, dropped, fps }' \
    "$state/server.log"

# 3. (as root: it mounts a tmpfs) A recording disk that fills: a 16 KB tmpfs, one driver
# changing keys every tick for 15 s, then a second driver. One JSON line: the world's
# ticks a second and dropped ticks from the summaries, the error line, whether the second
# driver joined (unrecorded), and whether the cut file replays.
if ((EUID == 0)); then
    rec=$(mktemp -d)
    mount -t tmpfs -o size=16k tmpfs "$rec"
    SERVE_ARGS="--log-every 3 --record-dir $rec" start_server "$DATA"
    awk 'BEGIN { split("U UL UR D L R", k, " "); for (i = 0; i < 2000; i++) print "1 " k[i % 6 + 1] }' \
        >"$state/keys.txt"
    "$BIN_DIR/roam-client" --connect "$addr" --token "$token" --fingerprint "$fingerprint" \
        --headless --inputs "$state/keys.txt" --frames 900 --stats "$state/d1.json" >/dev/null 2>&1
    "$BIN_DIR/roam-client" --connect "$addr" --token "$token" --fingerprint "$fingerprint" \
        --headless --frames 120 --stats "$state/d2.json" >/dev/null 2>&1 && second=true || second=false
    stop_server
    file=$(ls "$rec"/*.rec)
    "$BIN_DIR/roam-server" replay "$file" --data "$DATA" >/dev/null 2>&1 && replays=true || replays=false
    bytes=$(stat -c %s "$file")
    umount "$rec"
    awk -v second="$second" -v replays="$replays" -v bytes="$bytes" '
        / summary /{ for (i = 1; i <= NF; i++) { split($i, kv, "=");
            if (kv[1] == "ticks_per_s" && kv[2] + 0 > 0) { t = kv[2] + 0; if (min == "" || t < min) min = t }
            if (kv[1] == "dropped_ticks") dropped += kv[2] } }
        / ERROR / && /recording/ { errors++ }
        /joined unrecorded/ { unrecorded++ }
        END { printf "{\"world_ticks_per_s_min\":%s,\"dropped_ticks\":%d,\"recording_errors\":%d,\"joins_unrecorded\":%d,\"second_driver_served\":%s,\"file_bytes\":%d,\"file_replays\":%s}\n",
              min, dropped, errors, unrecorded, second, bytes, replays }' "$state/server.log"
fi
