#!/usr/bin/env bash
# Builds what the browser viewer (issue 15) will reuse for wasm32-unknown-unknown: the
# protocol and the viewer's clock-free core, colour cache, camera, HUD and renderer
# (`roam-client --lib`; its QUIC, window and headless modules are native only). Uses
# Debian's Rust for the web, which builds the standard library from source (see
# ../shared/STACK.md, "Browser"); as root it installs it:
#   apt-get install -y rustc-web cargo-web rust-web-src lld-16
#
#   scripts/wasm-check.sh        (prints the wasm size of roam-client's lib as JSON)
set -euo pipefail
cd "$(dirname "$0")/.."

if ! command -v wasm-ld-16 >/dev/null || [[ ! -d /usr/lib/rustlib/src/rust/library ]]; then
    if [[ $(id -u) -eq 0 ]]; then
        apt-get install -y rustc-web cargo-web rust-web-src lld-16 >&2
    else
        echo "error: needs Debian's rustc-web, cargo-web, rust-web-src and lld-16:" \
            "sudo apt-get install -y rustc-web cargo-web rust-web-src lld-16" >&2
        exit 1
    fi
fi
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}/wasm
RUSTC_BOOTSTRAP=1 RUSTC=/usr/bin/rustc CARGO_TARGET_WASM32_UNKNOWN_UNKNOWN_LINKER=wasm-ld-16 \
    /usr/bin/cargo build --release --target wasm32-unknown-unknown \
    -Zbuild-std=std,panic_abort -p roam-protocol -p roam-client --lib >&2
rlib="$CARGO_TARGET_DIR/wasm32-unknown-unknown/release/libroam_client.rlib"
printf '{"target":"wasm32-unknown-unknown","roam_client_rlib_bytes":%d}\n' "$(stat -c %s "$rlib")"
