#!/usr/bin/env bash
# Server memory per viewer (docs/figures.md, command I): the server's anonymous RSS while 1 and
# then 5 viewers drive at 65,536 triangles over a 4097² data set; per viewer is
# (RSS with 5 − RSS with 1) ÷ 4, from the medians of 17 samples a run
# (`bytes_per_viewer`) and from their maxima (`bytes_per_viewer_max`). Prints one JSON line.
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

# The server's RssAnon while N viewers drive (20 s of frames): sampled every 0.5 s from 6 s
# to 14 s into the run, printed as "MEDIAN MAX". One sample (8 s in, as this script first
# took) moved by ±0.25 MB a viewer from run to run of one build: the cuts grow and give back
# their tables as they change.
measure() {
    "$BIN_DIR/roam-client" --connect "$addr" --token "$token" --fingerprint "$fingerprint" \
        --headless --viewers "$1" --budget "$BUDGET" --frames 1200 --skip-decode \
        --inputs "$state/drive.txt" >/dev/null &
    local client=$! samples=() i
    sleep 6
    for i in $(seq 1 17); do
        samples+=("$(rss_anon)")
        sleep 0.5
    done
    printf '%s\n' "${samples[@]}" | sort -n | awk '{ v[NR] = $1 } END { print v[int((NR + 1) / 2)], v[NR] }'
    wait $client
}

idle=$(rss_anon)
read -r one one_max < <(measure 1)
read -r five five_max < <(measure 5)
python3 -c "
import json
idle, one, five, one_max, five_max = $idle, $one, $five, $one_max, $five_max
print(json.dumps({'data_set': '$DATA', 'profile': '$PROFILE', 'budget': $BUDGET, 'rss_anon_idle': idle,
    'rss_anon_1_viewer': one, 'rss_anon_5_viewers': five,
    'rss_anon_1_viewer_max': one_max, 'rss_anon_5_viewers_max': five_max,
    'bytes_per_viewer': (five - one) / 4, 'bytes_per_viewer_max': (five_max - one_max) / 4}))"
