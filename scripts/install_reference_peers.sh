#!/usr/bin/env bash
# Install the reference OpenIGTLink peers used by the interop tests:
#   Debian's libopenigtlink-dev + openigtlink-examples, with the example programs built by cmake
#   into a cache folder ($OCC_IGTL_EXAMPLES, default $ROOT/.cache/igtl-examples/bin).
# Idempotent; exits non-zero (and says why) when it cannot.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
CACHE="${OCC_IGTL_EXAMPLES:-$ROOT/.cache/igtl-examples}"
SRC=/usr/share/doc/openigtlink-examples/examples

have_library() {
    # Debian/Ubuntu put the CMake package in /usr/lib/openigtlink; other layouts use cmake/ dirs
    local f
    for f in /usr/lib/openigtlink/OpenIGTLinkConfig.cmake \
             /usr/lib/*/openigtlink/OpenIGTLinkConfig.cmake \
             /usr/lib/*/cmake/OpenIGTLink*/OpenIGTLinkConfig.cmake \
             /usr/lib/cmake/OpenIGTLink*/OpenIGTLinkConfig.cmake; do
        [ -e "$f" ] && return 0
    done
    return 1
}
if [ ! -d "$SRC" ] || ! have_library; then
    if [ "$(id -u)" != 0 ]; then
        echo "[peers] not root: cannot apt-get install libopenigtlink-dev openigtlink-examples" >&2
        exit 1
    fi
    echo "[peers] installing libopenigtlink-dev openigtlink-examples cmake g++ (apt)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null || true
    apt-get install -y -qq libopenigtlink-dev openigtlink-examples cmake g++ make >/dev/null
fi
if [ -x "$CACHE/bin/TrackerClient" ] && [ -x "$CACHE/bin/ReceiveServer" ]; then
    exit 0
fi
command -v cmake >/dev/null || { echo "[peers] cmake missing" >&2; exit 1; }
echo "[peers] building the reference examples into $CACHE (about 15 s)"
rm -rf "$CACHE/build" "$CACHE/src"  # src: left over by an interrupted run, cp -r would nest
mkdir -p "$CACHE/build" "$CACHE/bin"
cp -r "$SRC" "$CACHE/src"
# Debian ships some example sources gzip-compressed.
find "$CACHE/src" -name '*.gz' -exec gunzip -f {} +
cmake -S "$CACHE/src" -B "$CACHE/build" -DCMAKE_BUILD_TYPE=Release >"$CACHE/cmake.log" 2>&1 \
    || { echo "[peers] cmake configure failed, see $CACHE/cmake.log" >&2; exit 1; }
cmake --build "$CACHE/build" -j2 >>"$CACHE/cmake.log" 2>&1 \
    || { echo "[peers] build failed, see $CACHE/cmake.log" >&2; exit 1; }
find "$CACHE/build" -type f -perm -u+x ! -name '*.so*' ! -path '*CMakeFiles*' -exec cp {} "$CACHE/bin/" \;
rm -rf "$CACHE/src"
echo "[peers] built: $(ls "$CACHE/bin" | tr '\n' ' ')"
