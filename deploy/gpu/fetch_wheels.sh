#!/usr/bin/env bash
# On a machine that reaches PyPI: download the wheels the GPU node lacks (wheels.txt) into deploy/gpu/wheels/,
# verify their sha256 (pip's hash-checking mode) and that the tree plus the wheels fit in what travels (64 MiB).
#   bash deploy/gpu/fetch_wheels.sh [DEST]          # DEST defaults to deploy/gpu/wheels
#   PYVER=3.11 bash deploy/gpu/fetch_wheels.sh DEST  # the same versions for another Python (the test's stand-in)
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
ROOT=$(cd "$HERE/../.." && pwd)
DEST=${1:-$HERE/wheels}
PYVER=${PYVER:-3.12}
PY=${PYTHON:-python3}
LIMIT=$((64 * 1024 * 1024))
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# only what wheels.txt names, hash-checked; into a fresh folder, so no stale version stays beside the new one
"$PY" -m pip download --quiet --disable-pip-version-check --no-deps --only-binary=:all: --require-hashes \
  --python-version "$PYVER" --implementation cp --platform manylinux_2_28_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -r "$HERE/wheels.txt" -d "$tmp"
want=$(grep -cE '^[A-Za-z]' "$HERE/wheels.txt")
got=$(find "$tmp" -name '*.whl' | wc -l)
[ "$got" -eq "$want" ] || { echo "fetch_wheels: $got wheels for $want pins in wheels.txt" >&2; exit 1; }
mkdir -p "$DEST"
rm -f "$DEST"/*.whl
mv "$tmp"/*.whl "$DEST"/
(cd "$DEST" && sha256sum -- *.whl >SHA256SUMS)
wheels=$(cat "$DEST"/*.whl | wc -c)
# what travels with them: the tree's tracked and untracked-not-ignored files (a plain copy: everything but .git,
# .venv, caches and outputs)
if git -C "$ROOT" rev-parse --git-dir >/dev/null 2>&1; then
  tree=$(cd "$ROOT" && git ls-files -z --cached --others --exclude-standard | du -cb --files0-from=- | tail -1 | cut -f1)
else
  tree=$(du -sb --exclude=.git --exclude=.venv --exclude=wheels --exclude=bench-out --exclude=__pycache__ "$ROOT" | cut -f1)
fi
total=$((tree + wheels))
awk -v n="$got" -v py="$PYVER" -v w="$wheels" -v t="$tree" -v a="$total" 'BEGIN { m = 1048576;
  printf "fetch_wheels: %d wheels (Python %s), %.1f MiB; tree %.1f MiB; together %.1f MiB of 64 MiB\n", n, py, w/m, t/m, a/m }'
if [ "$total" -gt "$LIMIT" ]; then
  echo "fetch_wheels: tree + wheels exceed 64 MiB: they cannot travel together" >&2
  exit 1
fi
echo "fetch_wheels: sha256 verified against wheels.txt; wheels in $DEST"
