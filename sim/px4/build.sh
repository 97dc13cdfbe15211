#!/usr/bin/env bash
# Build PX4 v1.16.0 SITL once into a cache outside the checkout (`make px4`, part of `make setup`).
#
# Source, first found: $PX4_SRC (a lab's own PX4-Autopilot tree at any tag; built as is, target
# $PX4_TARGET, default px4_sitl_nofft if its board file exists, else px4_sitl_default), or the tarball
# and Micro-CDR bundle in <checkout>/../shared/px4/ (PX4 v1.16.0 + the 5 submodules SITL needs;
# their README is the recipe followed here). Neither: one line saying so, exit 0 (nothing that needs
# PX4 can run; `neso up --vehicle px4` then says where the binary was looked for).
#
# Kept: the stripped bin/px4 with its symlinks and etc/ (~9 MB) in $NESO_PX4_HOME (default
# ~/.cache/neso/px4-v1.16.0); the 382 MB build tree is deleted. A stamp (.built, naming the source: the
# tarball's SHA-256, or $PX4_SRC's git describe and path) makes a second run a no-op; a changed source rebuilds. ~4 min of every core (255 s measured on 2):
# on a shared machine run the first build under the machine's lock, e.g. `flock /tmp/neso-heavy.lock make px4`.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
home="${NESO_PX4_HOME:-$HOME/.cache/neso/px4-v1.16.0}"
shared="${NESO_SHARED:-$repo/../shared}/px4"
tarball="$(realpath -m "$shared/px4-v1.16.0-sitl-src.tar.xz")"
bundle="$(realpath -m "$shared/micro-cdr-v2.0.1.bundle")"

if [ -n "${PX4_SRC:-}" ]; then
    [ -f "$PX4_SRC/Makefile" ] && [ -d "$PX4_SRC/src/modules" ] \
        || { echo "px4: PX4_SRC=$PX4_SRC is no PX4-Autopilot tree (no Makefile, src/modules)" >&2; exit 2; }
    source_id="PX4_SRC $(cd "$PX4_SRC" && git describe --always --tags --dirty 2>/dev/null || echo untracked) $PX4_SRC"
elif [ -f "$tarball" ]; then
    # its content, not its path or time: the same tarball in another checkout's ../shared is the same source
    source_id="tarball sha256 $(sha256sum "$tarball" | cut -d' ' -f1)"
elif [ -x "$home/bin/px4" ]; then
    echo "px4: kept the build in $home ($(sed -n 2p "$home/.built" 2>/dev/null)); its source is not here to check"
    exit 0
else
    echo "px4: no PX4 source (set PX4_SRC to a PX4-Autopilot tree, or put px4-v1.16.0-sitl-src.tar.xz in $shared); PX4 SITL not built"
    exit 0
fi

if [ -f "$home/.built" ] && [ "$(head -1 "$home/.built")" = "$source_id" ] && [ -x "$home/bin/px4" ]; then
    echo "px4: up to date in $home ($(sed -n 2p "$home/.built"))"
    exit 0
fi

for tool in cmake ninja git make c++; do
    command -v "$tool" >/dev/null || { echo "px4: $tool is missing; as root run: apt-get install -y build-essential cmake ninja-build git" >&2; exit 1; }
done

work="$(mktemp -d "${TMPDIR:-/tmp}/neso-px4-build.XXXXXX")"
trap 'rm -rf "$work"' EXIT
start=$(date +%s)

# PX4's code generators want their own Python packages (empy < 4: PX4 v1.16 uses its 3.x API).
python3 -m venv "$work/venv"
"$work/venv/bin/pip" install --quiet 'empy<4' jinja2 kconfiglib pyyaml jsonschema packaging future pyros-genmsg lxml
export PATH="$work/venv/bin:$PATH"

if [ -n "${PX4_SRC:-}" ]; then
    src="$PX4_SRC"
    target="${PX4_TARGET:-}"
    if [ -z "$target" ]; then
        target=px4_sitl_default
        [ -f "$src/boards/px4/sitl/nofft.px4board" ] && target=px4_sitl_nofft
    fi
else
    echo "px4: unpacking $tarball"
    mkdir "$work/src" && tar -xJf "$tarball" -C "$work/src" --strip-components=1
    src="$work/src"
    target="${PX4_TARGET:-px4_sitl_nofft}"
    # PX4's CMake reads its version from git (a tag) and wants a .git in each submodule it uses.
    git_q() { git -c user.name=neso -c user.email=neso@localhost -c init.defaultBranch=main -c advice.addEmbeddedRepo=false \
                  "$@" >/dev/null 2>&1; }
    for sub in src/modules/mavlink/mavlink src/drivers/gps/devices src/lib/events/libevents \
               src/modules/uxrce_dds_client/Micro-XRCE-DDS-Client src/lib/heatshrink/heatshrink; do
        (cd "$src/$sub" && git_q init -q && git_q commit -q --allow-empty -m vendored)
    done
    (cd "$src" && git_q init -q && git_q add -A && git_q commit -q -m "PX4 v1.16.0 (tarball)" && git_q tag v1.16.0)
    # The DDS client's CMake clones Micro-CDR: from the bundle beside the tarball.
    printf '[url "%s"]\n\tinsteadOf = https://github.com/eProsima/Micro-CDR.git\n' "$bundle" > "$work/gitconfig"
    export GIT_CONFIG_GLOBAL="$work/gitconfig"
fi

echo "px4: building $target from ${PX4_SRC:-$tarball} (~4 min on 2 cores)"
export GIT_SUBMODULES_ARE_EVIL=1
make -C "$src" "$target" > "$work/build.log" 2>&1 || { tail -30 "$work/build.log" >&2; echo "px4: build failed (log above)" >&2; exit 1; }

build="$src/build/$target"
version="$("$build/bin/px4" --version 2>/dev/null | head -1 || true)"
staged="$home.new"
rm -rf "$staged" && mkdir -p "$staged"
cp -a "$build/bin" "$staged/bin"
strip "$staged/bin/px4"
cp -a "$build/etc" "$staged/etc"
git -C "$src" describe --always --tags > "$staged/version" 2>/dev/null || echo unknown > "$staged/version"
printf '%s\n%s, %s, built in %d s\n' "$source_id" "$(cat "$staged/version")" "$target" "$(( $(date +%s) - start ))" > "$staged/.built"
rm -rf "$home" && mv "$staged" "$home"
echo "px4: built $(cat "$home/version") ($target) in $(( $(date +%s) - start )) s into $home"
