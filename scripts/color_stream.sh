#!/usr/bin/env bash
# Colour streamed by view (docs/figures.md, "Colour streamed by view"): for each data set, connect to
# first frame, bytes received before it, and colour bytes a second while a vehicle drives
# (`roam-server color-bench`: the server in process on loopback, a driver speaking the
# protocol, Up held). One JSON line per data set. The first run of a set builds its colour
# tile cache (DIR/.cache/color-tiles.bin); later runs map it.
#
#   scripts/color_stream.sh [DATA...]     (default: data/kossou and /tmp/g4097, generated
#                                          if missing; /tmp/g16385 too if it exists)
set -euo pipefail
cd "$(dirname "$0")/.."

export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
cargo build --profile measure -p roam-server >&2
BIN="$CARGO_TARGET_DIR/measure/roam-server"
if [[ $# -eq 0 ]]; then
    [[ -d /tmp/g4097 ]] || "$BIN" generate /tmp/g4097 --side 4097 >&2
    set -- data/kossou /tmp/g4097
    [[ -d /tmp/g16385 ]] && set -- "$@" /tmp/g16385
fi
for data in "$@"; do
    "$BIN" color-bench "$data" --seconds "${SECONDS_DRIVING:-10}" ${BENCH_ARGS:-}
done
