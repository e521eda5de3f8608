#!/usr/bin/env bash
# Import figures: time and peak memory of `roam-server import` per source format,
# on the real SRTM3 tile data/srtm/n07_w006_3arc_v2.tif (1201², see data/srtm/README.md).
# The example `import_sources` writes the tile as SRTM .hgt, 16-bit PNG, Terrarium PNG and
# PGM (the 1025² data/kossou cut: a PGM must be 2^N + 1 a side), and bilinearly upsampled
# ×3 to 3601² (what an SRTM1 tile holds) as .hgt, GeoTIFF, 16-bit PNG and Terrarium PNG.
# Each is imported to $SIDE² (4097 by default) under /usr/bin/time -v; one JSON line each:
# {"format":…,"source":"WxH","side":…,"seconds":…,"peak_rss_mb":…}.
#
#   PROFILE=measure scripts/import_figures.sh      (PROFILE=release by default)
set -euo pipefail
cd "$(dirname "$0")/.."

PROFILE=${PROFILE:-release}
SIDE=${SIDE:-4097}
TILE=${TILE:-data/srtm/n07_w006_3arc_v2.tif}
cargo build --profile "$PROFILE" -p roam-server --bin roam-server --example import_sources >&2
BIN_DIR="${CARGO_TARGET_DIR:-target}/$PROFILE"

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$BIN_DIR/examples/import_sources" "$TILE" "$work"

# measure FORMAT SOURCE_SIZE FILE [import flags...]
measure() {
    local format=$1 size=$2 file=$3
    shift 3
    rm -rf "$work/out"
    /usr/bin/time -v -o "$work/time" \
        "$BIN_DIR/roam-server" import "$file" "$work/out" --side "$SIDE" "$@" >/dev/null
    awk -v format="$format" -v size="$size" -v side="$SIDE" '
        /Elapsed \(wall clock\)/ { n = split($NF, t, ":"); s = 0; for (i = 1; i <= n; i++) s = s * 60 + t[i] }
        /Maximum resident set size/ { rss = $NF / 1024 }
        END { printf "{\"format\":\"%s\",\"source\":\"%s\",\"side\":%d,\"seconds\":%.2f,\"peak_rss_mb\":%.1f}\n",
              format, size, side, s, rss }' "$work/time"
}

measure geotiff 1201x1201 "$TILE"
measure hgt 1201x1201 "$work/N07W006.hgt"
measure png16 1201x1201 "$work/grey16.png" --h-scale 92
measure terrarium 1201x1201 "$work/terrarium.png" --rgb-encoding terrarium --h-scale 92
measure pgm 1025x1025 "$work/kossou.pgm" --h-scale 92 --v-scale 0.01
measure geotiff 3601x3601 "$work/s1/n07_w006_1arc.tif"
measure hgt 3601x3601 "$work/s1/N07W006.hgt"
measure png16 3601x3601 "$work/s1/grey16.png" --h-scale 30.87
measure terrarium 3601x3601 "$work/s1/terrarium.png" --rgb-encoding terrarium --h-scale 30.87
# The colour map from an image instead of derived from the heights (no colorize).
measure hgt+color 3601x3601 "$work/s1/N07W006.hgt" --color data/kossou/color.ppm
