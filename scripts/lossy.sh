#!/usr/bin/env bash
# The stream over bad links: one server (`roam-server serve`), and for each link a seeded
# lossy relay (`roam-relay`, the same delay and loss each way) with one headless viewer
# driving through it. Prints one line per link: frames taken per second,
# input→frame latency (median and p99, ms), decode errors, and what the relay dropped.
#
#   scripts/lossy.sh                     (links: direct 40/0 0/0.05 25/0.02 40/0.05)
#   scripts/lossy.sh direct 40/0.05      (LINK: `direct`, or DELAY_MS/LOSS each way)
#   PROFILE=measure SEED=2 JITTER_MS=5 OUT=/tmp/lossy scripts/lossy.sh
#
# PROFILE (default release) is the cargo profile built and run (`measure`: a quicker
# build); BUDGET (32768), FRAMES (900), DATA (data/kossou), SEED (1), JITTER_MS (0) and
# DRIVE (an input script; default 16 s of throttle and turns) set the run; OUT keeps each
# link's stats JSON, relay counters and server log there.
set -euo pipefail
cd "$(dirname "$0")/.."

PROFILE=${PROFILE:-release}
BUDGET=${BUDGET:-32768}
FRAMES=${FRAMES:-900}
DATA=${DATA:-data/kossou}
SEED=${SEED:-1}
JITTER_MS=${JITTER_MS:-0}
LINKS=("$@")
((${#LINKS[@]})) || LINKS=(direct 40/0 0/0.05 25/0.02 40/0.05)
BIN_DIR="${CARGO_TARGET_DIR:-target}/$PROFILE"
export BIN_DIR

cargo build --profile "$PROFILE" -p roam-server -p roam-client -p roam-tests --bins >&2
# shellcheck source=scripts/lib.sh
source scripts/lib.sh
start_server "$DATA"
relay=
cleanup() {
    [[ -n "$relay" ]] && kill "$relay" 2>/dev/null && wait "$relay" 2>/dev/null
    kill -INT "$server" 2>/dev/null
    wait "$server" 2>/dev/null
    [[ -n "${OUT:-}" ]] && cp "$state/server.log" "$OUT/" 2>/dev/null
    rm -rf "$state"
}
trap cleanup EXIT
out=${OUT:-$state}
mkdir -p "$out"

# About 16 s of driving (one step per 10 ms): throttle, and turns both ways; or $DRIVE.
drive=${DRIVE:-$state/drive.txt}
[[ -n "${DRIVE:-}" ]] || printf '300 U\n200 UL\n300 U\n200 UR\n300 U\n300 -\n' >"$drive"

printf '%-14s %8s %10s %10s %8s  %s\n' link fps i2f_med i2f_p99 dec_err "relay: lost/forwarded to server, to client"
for link in "${LINKS[@]}"; do
    name=${link//\//_}
    stats="$out/$name.json"
    target=$addr
    relay_log=
    if [[ $link != direct ]]; then
        IFS=/ read -r delay loss <<<"$link"
        relay_log="$out/$name.relay"
        "$BIN_DIR/roam-relay" --to "$addr" --delay-ms "$delay" --jitter-ms "$JITTER_MS" \
            --loss "$loss" --seed "$SEED" >"$relay_log" 2>&1 &
        relay=$!
        for _ in $(seq 1 100); do
            grep -q '^listening on ' "$relay_log" && break
            kill -0 "$relay" 2>/dev/null || { cat "$relay_log" >&2; exit 1; }
            sleep 0.05
        done
        target=$(sed -n 's/^listening on //p' "$relay_log")
        [[ -n $target ]] || { echo "error: the relay did not say where it listens" >&2; exit 1; }
    fi
    "$BIN_DIR/roam-client" --connect "$target" --token "$token" --fingerprint "$fingerprint" \
        --headless --budget "$BUDGET" --inputs "$drive" --frames "$FRAMES" --stats "$stats" >&2
    counters=-
    if [[ -n $relay ]]; then
        kill "$relay"
        wait "$relay" 2>/dev/null || true
        relay=
        counters=$(sed -n 's/^roam-relay: //p' "$relay_log" |
            sed -E 's/to server: ([0-9]+) forwarded \([0-9]+ bytes\), ([0-9]+) lost, ([0-9]+) overflowed; to client: ([0-9]+) forwarded \([0-9]+ bytes\), ([0-9]+) lost, ([0-9]+) overflowed/\2+\3\/\1, \5+\6\/\4/')
    fi
    python3 - "$stats" "$link" "$counters" <<'EOF'
import json, sys
path, link, counters = sys.argv[1:]
with open(path) as f:
    s = json.load(f)
print(f"{link:<14} {s['frames_per_second']:8.1f} {s['input_to_frame_ms_median']:10.0f} "
      f"{s['input_to_frame_ms_p99']:10.0f} {s['decode_errors']:8d}  {counters}", flush=True)
EOF
done
