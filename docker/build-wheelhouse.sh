#!/usr/bin/env bash
# Collect every Python wheel the images need into a wheelhouse on the host:
# $LIFECYCLE_BUILD_CACHE/wheelhouse (default ~/.cache/lifecycle-manager/wheelhouse, kept per
# machine, so that a fresh clone, as in CI, does not collect it again).
#
# The Dockerfile installs only from this folder (pip --no-index), so `docker build` needs
# no access to PyPI; this is also how an image is built in a factory without internet:
# run this script where PyPI is reachable, carry the folder over, build there.
#
# Target: CPython 3.11 on x86_64 Linux (glibc), as Debian bookworm and python:3.11-slim-bookworm
# are. Wheels come from PyPI as published (manylinux / pure Python); the few sdist-only
# packages (pure Python, e.g. empy) are built into py3-none-any wheels here. A wheel that
# only fits the build host (linux_x86_64) is refused.
#
# Cached: nothing is done when requirements.txt (and requirements-image.txt) have not changed since the last run
# (the stamp holds its hash). --force rebuilds.
set -euo pipefail

HERE="$(cd "$(dirname "$0")" && pwd)"
ROOT="$(dirname "$HERE")"
CACHE="${LIFECYCLE_BUILD_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/lifecycle-manager}"
OUT="$CACHE/wheelhouse"
REQ="$ROOT/requirements.txt"
STAMP="$OUT/.requirements.sha256"

# A Python 3.11 for x86_64 Linux to run pip with (the project's venv when there is one).
PY="${WHEELHOUSE_PYTHON:-}"
if [ -z "$PY" ]; then
    for candidate in "$ROOT/.venv/bin/python" python3.11 python3; do
        if command -v "$candidate" >/dev/null 2>&1 &&
           "$candidate" -c 'import sys; assert sys.version_info[:2] == (3, 11)' 2>/dev/null; then
            PY="$candidate"; break
        fi
    done
fi
[ -n "$PY" ] || { echo "build-wheelhouse: a Python 3.11 is needed (set WHEELHOUSE_PYTHON)" >&2; exit 1; }
"$PY" - <<'PY' || exit 1
import platform, sys
if platform.machine() != "x86_64" or not sys.platform.startswith("linux"):
    sys.exit(f"build-wheelhouse: run this on x86_64 Linux (this is {sys.platform}/{platform.machine()})")
PY

want="$(cat "$REQ" "$HERE/requirements-image.txt" | sha256sum | cut -d' ' -f1)"
if [ "${1:-}" != "--force" ] && [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ]; then
    echo "wheelhouse is up to date ($(ls "$OUT"/*.whl | wc -l) wheels in $OUT)"
    exit 0
fi

mkdir -p "$CACHE"
tmp="$(mktemp -d "$CACHE/wheelhouse.new.XXXXXX")"
trap 'rm -rf "$tmp"' EXIT
echo "collecting wheels for requirements.txt into $OUT ..."
quiet() { grep -v "is ignored: it is neither" >&2 || true; }
# `pip wheel` takes published wheels as they are and builds wheels from sdists (pure Python).
# requirements-image.txt adds what the image's interpreter needs beyond the host's (markers).
"$PY" -m pip wheel --quiet --disable-pip-version-check -r "$REQ" -r "$HERE/requirements-image.txt" \
    -w "$tmp" 2> >(quiet)
cp "$REQ" "$tmp/requirements.txt"

# Every wheel must fit cp311 on manylinux x86_64 (or be pure Python).
"$PY" - "$tmp" <<'PY'
import pathlib, re, sys
bad = []
for wheel in sorted(pathlib.Path(sys.argv[1]).glob("*.whl")):
    python, abi, plat = wheel.stem.split("-")[-3:]
    pythons, abis, plats = python.split("."), abi.split("."), plat.split(".")
    py_ok = any(p in ("py3", "py2", "cp311") or re.fullmatch(r"cp3\d?", p) and abi == "abi3" for p in pythons)
    abi_ok = any(a in ("none", "abi3", "cp311") for a in abis)
    plat_ok = any(p == "any" or re.fullmatch(r"manylinux(1|2010|2014|_2_\d+)_x86_64", p) for p in plats)
    if not (py_ok and abi_ok and plat_ok):
        bad.append(wheel.name)
if bad:
    sys.exit("build-wheelhouse: wheels that do not fit cp311/manylinux x86_64:\n  " + "\n  ".join(bad))
PY

echo "$want" > "$tmp/.requirements.sha256"
rm -rf "$OUT"
mv "$tmp" "$OUT"
trap - EXIT
echo "wheelhouse: $(ls "$OUT"/*.whl | wc -l) wheels, $(du -sh "$OUT" | cut -f1) in $OUT"
