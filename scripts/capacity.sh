#!/usr/bin/env bash
# Viewers served per server core (README, command E).
#
# The server runs pinned to CPU 0; the load generator (`roam-client --headless --viewers N
# --skip-decode`: N viewers that acknowledge every frame without decoding it) runs pinned
# to CPU 1. For each N it prints one JSON line: the generator's report (frames_per_second_min
# is what the figure reads: >= 55 counts as served at 60 Hz) plus the CPU share each process
# used over the run, so a saturated generator is seen rather than mistaken for the server.
#
#   scripts/capacity.sh [N ...]          (default: 5 10 15 20 25 30 35 40)
#   BUDGET=32768 FRAMES=300 DATA=data/kossou scripts/capacity.sh 20 30
set -euo pipefail
cd "$(dirname "$0")/.."

BUDGET=${BUDGET:-32768}
FRAMES=${FRAMES:-300}
DATA=${DATA:-data/kossou}
COUNTS=("$@")
((${#COUNTS[@]})) || COUNTS=(5 10 15 20 25 30 35 40)
if (($(nproc) < 2)); then
    echo "error: needs two CPUs (one for the server, one for the load generator)" >&2
    exit 1
fi

cargo build --release -p roam-server -p roam-client >&2
# shellcheck source=scripts/lib.sh
source scripts/lib.sh
start_server "$DATA" taskset -c 0

# CPU seconds (user + system) a process has used so far.
cpu() { awk -v hz="$(getconf CLK_TCK)" '{ print ($14 + $15) / hz }' "/proc/$1/stat"; }

for n in "${COUNTS[@]}"; do
    before=$(cpu $server)
    start=$(date +%s.%N)
    report=$(/usr/bin/time -f '%U %S' -o "$state/time" taskset -c 1 target/release/roam-client \
        --connect "$addr" --token "$token" --fingerprint "$fingerprint" --headless \
        --viewers "$n" --budget "$BUDGET" --frames "$FRAMES" --skip-decode)
    end=$(date +%s.%N)
    after=$(cpu $server)
    read -r user sys <"$state/time"
    python3 - "$report" "$n" "$start" "$end" "$before" "$after" "$user" "$sys" <<'EOF'
import json, sys
report, n, start, end, before, after, user, sys_ = sys.argv[1:]
r = json.loads(report)
wall = float(end) - float(start)
r["server_cpu_share"] = round((float(after) - float(before)) / wall, 3)
r["generator_cpu_share"] = round((float(user) + float(sys_)) / wall, 3)
r["viewers"] = int(n)
print(json.dumps(r, sort_keys=True))
EOF
done
