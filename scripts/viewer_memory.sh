#!/usr/bin/env bash
# Server memory per viewer (docs/figures.md, command I): the server's anonymous RSS while 1 and
# then 5 viewers drive at 65,536 triangles over a 4097² data set; per viewer is
# (RSS with 5 − RSS with 1) ÷ 4. Prints one JSON line.
#
#   scripts/viewer_memory.sh [DATA]     (default: /tmp/synth-4097, generated if missing)
#   PROFILE=measure BUDGET=32768 scripts/viewer_memory.sh
#
# PROFILE (default release) is the cargo profile built and run (`measure`: a quicker
# build, no LTO); BUDGET (default 65536) the triangles each viewer asks for.
set -euo pipefail
cd "$(dirname "$0")/.."

DATA=${1:-/tmp/synth-4097}
BUDGET=${BUDGET:-65536}
PROFILE=${PROFILE:-release}
BIN_DIR="${CARGO_TARGET_DIR:-target}/$PROFILE"
export BIN_DIR
cargo build --profile "$PROFILE" -p roam-server -p roam-client >&2
[[ -d "$DATA" ]] || "$BIN_DIR/roam-server" generate "$DATA" --side 4097 --seed 1 >&2

# shellcheck source=scripts/lib.sh
source scripts/lib.sh
start_server "$DATA"
# Throttle and turns both ways: the cut keeps changing.
printf '300 U\n200 UL\n200 U\n200 UR\n300 U\n' >"$state/drive.txt"

rss_anon() { awk '/^RssAnon:/ { print $2 * 1024 }' "/proc/$server/status"; }

# RssAnon of the server 8 s into a run of N driving viewers (20 s of frames).
measure() {
    "$BIN_DIR/roam-client" --connect "$addr" --token "$token" --fingerprint "$fingerprint" \
        --headless --viewers "$1" --budget "$BUDGET" --frames 1200 --skip-decode \
        --inputs "$state/drive.txt" >/dev/null &
    local client=$!
    sleep 8
    rss_anon
    wait $client
}

idle=$(rss_anon)
one=$(measure 1)
five=$(measure 5)
python3 -c "
import json
idle, one, five = $idle, $one, $five
print(json.dumps({'data_set': '$DATA', 'profile': '$PROFILE', 'budget': $BUDGET, 'rss_anon_idle': idle,
    'rss_anon_1_viewer': one, 'rss_anon_5_viewers': five,
    'bytes_per_viewer': (five - one) / 4}))"
