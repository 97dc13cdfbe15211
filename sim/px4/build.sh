#!/usr/bin/env bash
# PX4 v1.16.0 SITL for the runtime and its px4 test tier (`make px4`, part of `make setup`).
#
#   sim/px4/build.sh requirements   PX4's Python build requirements (build-requirements.txt, pinned) from the package
#                                   index into a cached venv, $NESO_PX4_PYTHON (default ~/.cache/neso/px4-build-python);
#                                   a no-op once installed (a stamp names the file's SHA-256). Needs the package index.
#   sim/px4/build.sh                PX4 v1.16.0 SITL built once into $NESO_PX4_HOME (default
#                                   ~/.cache/neso/px4-<tag>, <tag> the source's own); offline: its generators run from
#                                   that venv, never a pip install.
#
# The source, first found: $PX4_SRC (a PX4-Autopilot tree; built as is, named by its own tag, target $PX4_TARGET,
# default px4_sitl_nofft if its board file exists, else px4_sitl_default); the tarball and Micro-CDR bundle in
# <checkout>/../shared/px4/ (PX4 v1.16.0 + the 5 submodules SITL needs; their README is the recipe followed here);
# a build already kept in the cache; or PX4's official repository at tag v1.16.0 (the same 5 submodules and Micro-CDR,
# shallow, kept in ~/.cache/neso/px4-src-v1.16.0) when the network reaches github.com. None of these: one line naming
# the three ways, exit 1 (make setup fails: nothing that needs PX4 could run). A $PX4_SRC at another tag is built
# under its tag and named, and the exit is 1 too: the runtime and its tests fly v1.16.0.
#
# Kept: the stripped bin/px4 with its symlinks and etc/ (~9 MB); the 382 MB build tree is deleted. A stamp (.built,
# naming the source: the tarball's SHA-256, or the tree's git describe and path) makes a second run a no-op; a changed
# source rebuilds. ~4 min of every core (255 s measured on 2): on a shared machine run the first build under the
# machine's lock, e.g. `flock /tmp/neso-heavy.lock make px4`.
set -euo pipefail

WANTED=v1.16.0  # sim/px4_sitl.py PX4_VERSION
OFFICIAL="${NESO_PX4_REPO:-https://github.com/PX4/PX4-Autopilot.git}"  # overridable: a mirror, or a test's repository
MICRO_CDR=https://github.com/eProsima/Micro-CDR.git  # the URL PX4's CMake clones; fetched from $MICRO_CDR_FROM
MICRO_CDR_FROM="${NESO_MICRO_CDR_REPO:-$MICRO_CDR}"
MICRO_CDR_TAG=v2.0.1
# the submodules a SITL build needs (../shared/px4/README.md); PX4's others stay out (GIT_SUBMODULES_ARE_EVIL)
SUBMODULES=(src/modules/mavlink/mavlink src/drivers/gps/devices src/lib/events/libevents
            src/modules/uxrce_dds_client/Micro-XRCE-DDS-Client src/lib/heatshrink/heatshrink)

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
cache="${XDG_CACHE_HOME:-$HOME/.cache}/neso"
pyenv="${NESO_PX4_PYTHON:-$cache/px4-build-python}"
requirements="$here/build-requirements.txt"
shared="${NESO_SHARED:-$repo/../shared}/px4"
tarball="$(realpath -m "$shared/px4-$WANTED-sitl-src.tar.xz")"
bundle="$(realpath -m "$shared/micro-cdr-$MICRO_CDR_TAG.bundle")"
clone="${NESO_PX4_CLONE:-$cache/px4-src-$WANTED}"
ways="set PX4_SRC to a PX4-Autopilot tree at $WANTED, put px4-$WANTED-sitl-src.tar.xz in $shared/, or let git reach $OFFICIAL (tag $WANTED)"

requirements_stamp() { printf 'sha256 %s\n' "$(sha256sum "$requirements" | cut -d' ' -f1)"; }

if [ "${1:-}" = requirements ]; then
    if [ -x "$pyenv/bin/python" ] && [ "$(cat "$pyenv/.installed" 2>/dev/null)" = "$(requirements_stamp)" ]; then
        exit 0
    fi
    echo "px4: PX4's Python build requirements ($(grep -c '==' "$requirements") pinned) into $pyenv"
    rm -rf "$pyenv" && python3 -m venv "$pyenv"
    "$pyenv/bin/pip" install --quiet --disable-pip-version-check -r "$requirements" \
        || { rm -rf "$pyenv"; echo "px4: could not install $requirements from the package index into $pyenv" >&2; exit 1; }
    requirements_stamp > "$pyenv/.installed"  # last: a venv without it is installed again
    exit 0
fi

# -- which source, and its tag ------------------------------------------------------------------------------------
tag_of() {  # a tree's tag as git describes it: v1.16.0, or v1.16.0-3-gabcdef0 past it, -dirty when modified
    git -C "$1" describe --tags --always --dirty 2>/dev/null || echo untagged
}
built_home() { echo "${NESO_PX4_HOME:-$cache/px4-$1}"; }

if [ -n "${PX4_SRC:-}" ]; then
    [ -f "$PX4_SRC/Makefile" ] && [ -d "$PX4_SRC/src/modules" ] \
        || { echo "px4: PX4_SRC=$PX4_SRC is no PX4-Autopilot tree (no Makefile, src/modules)" >&2; exit 2; }
    kind=tree src="$PX4_SRC" tag="$(tag_of "$PX4_SRC")"
    source_id="PX4_SRC $tag $PX4_SRC"
elif [ -f "$tarball" ]; then
    # its content, not its path or time: the same tarball in another checkout's ../shared is the same source
    kind=tarball src="$tarball" tag=$WANTED
    source_id="tarball sha256 $(sha256sum "$tarball" | cut -d' ' -f1)"
elif [ -x "$(built_home $WANTED)/bin/px4" ]; then
    home="$(built_home $WANTED)"
    echo "px4: kept the build in $home ($(sed -n 2p "$home/.built" 2>/dev/null)); its source is not here to check"
    exit 0
elif [ -f "$clone/Makefile" ] || timeout 30 git ls-remote --exit-code --tags "$OFFICIAL" "refs/tags/$WANTED" >/dev/null 2>&1; then
    kind=clone src="$clone" tag=$WANTED
    source_id="official $OFFICIAL $WANTED"
else
    echo "px4: PX4 $WANTED not found: $ways" >&2
    exit 1
fi
home="$(built_home "$tag")"

if [ -f "$home/.built" ] && [ "$(head -1 "$home/.built")" = "$source_id" ] && [ -x "$home/bin/px4" ]; then
    echo "px4: up to date in $home ($(sed -n 2p "$home/.built"))"
    exit 0
fi

for tool in cmake ninja git make c++; do
    command -v "$tool" >/dev/null || { echo "px4: $tool is missing; as root run: apt-get install -y build-essential cmake ninja-build git" >&2; exit 1; }
done
# PX4's code generators want their own Python packages (empy < 4: PX4 v1.16 uses its 3.x API), installed at set-up
[ -x "$pyenv/bin/python" ] && [ "$(cat "$pyenv/.installed" 2>/dev/null)" = "$(requirements_stamp)" ] \
    || { echo "px4: PX4's Python build requirements are not in $pyenv: run \`make setup\` (or $0 requirements) first" >&2; exit 1; }
export PATH="$pyenv/bin:$PATH"

work="$(mktemp -d "${TMPDIR:-/tmp}/neso-px4-build.XXXXXX")"
trap 'rm -rf "$work"' EXIT
start=$(date +%s)
git_q() { git -c user.name=neso -c user.email=neso@localhost -c init.defaultBranch=main -c advice.addEmbeddedRepo=false \
              -c advice.detachedHead=false "$@" >/dev/null 2>&1; }

if [ "$kind" = clone ] && [ ! -f "$clone/.neso-complete" ]; then
    # PX4's official repository at the tag, shallow, with the SITL's submodules and Micro-CDR (cloned at build time by
    # the DDS client's CMake) fetched now, so that a rebuild needs no network
    echo "px4: cloning PX4 $WANTED from $OFFICIAL into $clone"
    rm -rf "$clone" && mkdir -p "$(dirname "$clone")"
    git_q clone --depth 1 --branch "$WANTED" "$OFFICIAL" "$clone" \
        && (cd "$clone" && git_q submodule update --init --depth 1 -- "${SUBMODULES[@]}") \
        && git_q clone --mirror "$MICRO_CDR_FROM" "$clone.micro-cdr.git" \
        || { rm -rf "$clone" "$clone.micro-cdr.git"; echo "px4: could not clone PX4 $WANTED from $OFFICIAL: $ways" >&2; exit 1; }
    # as in ../shared/px4's tree (its README): gyro_fft's generated CMSIS table is not needed by a simulated vehicle
    printf 'CONFIG_MODULES_GYRO_FFT=n\n' > "$clone/boards/px4/sitl/nofft.px4board"
    touch "$clone/.neso-complete"
fi

if [ "$kind" = tree ]; then
    target="${PX4_TARGET:-}"
    if [ -z "$target" ]; then
        target=px4_sitl_default
        [ -f "$src/boards/px4/sitl/nofft.px4board" ] && target=px4_sitl_nofft
    fi
elif [ "$kind" = clone ]; then
    target="${PX4_TARGET:-px4_sitl_nofft}"
    printf '[url "%s"]\n\tinsteadOf = %s\n' "$clone.micro-cdr.git" "$MICRO_CDR" > "$work/gitconfig"
    export GIT_CONFIG_GLOBAL="$work/gitconfig"
else
    echo "px4: unpacking $tarball"
    mkdir "$work/src" && tar -xJf "$tarball" -C "$work/src" --strip-components=1
    src="$work/src"
    target="${PX4_TARGET:-px4_sitl_nofft}"
    # PX4's CMake reads its version from git (a tag) and wants a .git in each submodule it uses.
    for sub in "${SUBMODULES[@]}"; do
        (cd "$src/$sub" && git_q init -q && git_q commit -q --allow-empty -m vendored)
    done
    (cd "$src" && git_q init -q && git_q add -A && git_q commit -q -m "PX4 $WANTED (tarball)" && git_q tag "$WANTED")
    # The DDS client's CMake clones Micro-CDR: from the bundle beside the tarball.
    printf '[url "%s"]\n\tinsteadOf = %s\n' "$bundle" "$MICRO_CDR" > "$work/gitconfig"
    export GIT_CONFIG_GLOBAL="$work/gitconfig"
fi

echo "px4: building $target of PX4 $tag from $src (~4 min on 2 cores)"
export GIT_SUBMODULES_ARE_EVIL=1
make -C "$src" "$target" > "$work/build.log" 2>&1 || { tail -30 "$work/build.log" >&2; echo "px4: build failed (log above)" >&2; exit 1; }

build="$src/build/$target"
staged="$home.new"
rm -rf "$staged" && mkdir -p "$staged"
cp -a "$build/bin" "$staged/bin"
strip "$staged/bin/px4"
cp -a "$build/etc" "$staged/etc"
echo "$tag" > "$staged/version"
printf '%s\n%s, %s, built in %d s\n' "$source_id" "$tag" "$target" "$(( $(date +%s) - start ))" > "$staged/.built"
rm -rf "$home" && mv "$staged" "$home"
[ "$kind" != clone ] || rm -rf "$src/build/$target"  # our clone's 382 MB build tree (the tarball's goes with $work)
echo "px4: built PX4 $tag ($target) in $(( $(date +%s) - start )) s into $home"
if [ "$tag" != "$WANTED" ]; then
    echo "px4: PX4_SRC is at $tag, not $WANTED: fly it with NESO_PX4_HOME=$home; the runtime's tests need $WANTED ($ways)" >&2
    exit 1
fi
