#!/usr/bin/env bash
# The GPU check on a bare, air-gapped CUDA node, as one line from the tree's root (deploy/gpu/README.md):
#   bash deploy/gpu/run_check.sh [gpu_check.py options, e.g. --quick or --items dit,vggt]
# Needs the tree plus deploy/gpu/wheels/ (fetch_wheels.sh, on a connected machine). Installs nothing into the
# node's Python: the wheels go into a temporary target, navcrafter is made importable from the tree (a namespace
# package of links to flows/ tasks/ models/ schemas/), gsplat's CUDA kernels are built in a capped step of their
# own (this device's compute capability, one job per CPU, resumable), then benchmarks/gpu_check.py runs under a
# deadline so that results.json / results.md are written before the whole budget is spent.
# Environment: OUT (results; default bench-out/gpu-check), PYTHON (default python3), WHEELS (default
# deploy/gpu/wheels), NAVCRAFTER_GPU_CACHE (installed wheels, links, build and scratch; default
# /tmp/navcrafter-gpu-check), CHECK_BUDGET_S (whole run, default 540), GSPLAT_BUILD_CAP (default 300),
# SKIP_GSPLAT_BUILD=1.
set -uo pipefail
start=$(date +%s)
HERE=$(cd "$(dirname "$0")" && pwd)
ROOT=$(cd "$HERE/../.." && pwd)
PY=${PYTHON:-python3}
WHEELS=${WHEELS:-$HERE/wheels}
CACHE=${NAVCRAFTER_GPU_CACHE:-/tmp/navcrafter-gpu-check}
OUTDIR=${OUT:-$ROOT/bench-out/gpu-check}
BUDGET=${CHECK_BUDGET_S:-540}
DEADLINE=$((start + BUDGET))
mkdir -p "$OUTDIR" "$CACHE"
exec > >(tee -a "$OUTDIR/run_check.log") 2>&1
say() { echo "run_check [$(($(date +%s) - start)) s]: $*"; }
die() { say "$1"; exit "${2:-1}"; }
DRY=0 items=gsplat prev=
for a in "$@"; do  # no gsplat build for the CPU dry run, nor for an --items list without gsplat
  [ "$a" = --dry-run ] && DRY=1
  [ "$prev" = --items ] && items=$a
  case "$a" in --items=*) items=${a#--items=} ;; esac
  prev=$a
done
case ",$items," in *,gsplat,*) GSPLAT=1 ;; *) GSPLAT=0 ;; esac
PYBIN=$(dirname "$(command -v "$PY" || echo "$PY")")
export PATH="$PYBIN:$PATH"  # the image's ninja (and cmake) live beside its python3

# 1. the carried wheels: exactly the pinned set, each hash in wheels.txt
ls "$WHEELS"/*.whl >/dev/null 2>&1 || die "no wheels in $WHEELS: run deploy/gpu/fetch_wheels.sh on a connected \
machine and copy deploy/gpu/wheels/ with the tree"
want=$(grep -cE '^[A-Za-z]' "$HERE/wheels.txt")
n=0
for w in "$WHEELS"/*.whl; do
  h=$(sha256sum "$w" | cut -d' ' -f1)
  grep -q "sha256:$h" "$HERE/wheels.txt" || die "$(basename "$w") is not pinned in wheels.txt (sha256 $h)"
  n=$((n + 1))
done
[ "$n" -eq "$want" ] || die "$n wheels in $WHEELS, wheels.txt pins $want"

# 2. into a temporary target (offline, no dependency resolution: the rest is the image's), once per wheel set
SITE=$CACHE/site
stamp=$(sha256sum "$WHEELS"/*.whl | cut -c1-64 | sha256sum | cut -c1-64)
if [ "$(cat "$SITE/.wheels" 2>/dev/null)" != "$stamp" ]; then
  rm -rf "$SITE"
  "$PY" -m pip install -q --disable-pip-version-check --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target "$SITE" "$WHEELS"/*.whl || die "pip could not install the wheels into $SITE"
  echo "$stamp" >"$SITE/.wheels"
  say "installed $n wheels into $SITE"
fi

# 3. navcrafter importable without installing it: the installed layout, as links to the tree
NAV=$CACHE/nav/navcrafter
mkdir -p "$NAV"
for d in flows tasks models schemas; do ln -sfn "$ROOT/$d" "$NAV/$d"; done
export PYTHONPATH="$SITE:$CACHE/nav${PYTHONPATH:+:$PYTHONPATH}"
export TORCH_EXTENSIONS_DIR=$CACHE/torch_extensions PYTHONUNBUFFERED=1 PREFECT_SERVER_ANALYTICS_ENABLED=false
cd "$ROOT" || exit 1

# 4. preflight: fail fast, with the reasons (preflight.json)
"$PY" benchmarks/gpu_check.py --preflight --out "$OUTDIR" "$@" || die "preflight failed (above; $OUTDIR/preflight.json)" 3

# 5. gsplat's kernels, in a capped step of their own (a cut build resumes on the next run on this machine)
if [ "$DRY" = 0 ]; then  # the same flags for the build and the gsplat item (else ninja rebuilds in the item)
  arch=${TORCH_CUDA_ARCH_LIST:-$(nvidia-smi --query-gpu=compute_cap --format=csv,noheader 2>/dev/null | head -1 | tr -d ' ')}
  [ -n "$arch" ] || arch=$("$PY" -c 'import torch; print("%d.%d" % torch.cuda.get_device_capability(0))')
  export TORCH_CUDA_ARCH_LIST=$arch MAX_JOBS=${MAX_JOBS:-$(nproc)}
fi
if [ "$DRY" = 0 ] && [ "$GSPLAT" = 1 ] && [ "${SKIP_GSPLAT_BUILD:-0}" != 1 ]; then
  cap=${GSPLAT_BUILD_CAP:-300}
  left=$((DEADLINE - $(date +%s) - 180))  # keep 3 min for the items
  [ "$left" -lt "$cap" ] && cap=$left
  if [ "$cap" -gt 30 ]; then
    say "building gsplat (TORCH_CUDA_ARCH_LIST=$arch MAX_JOBS=$MAX_JOBS, cap $cap s) ..."
    timeout -k 10 "$cap" "$PY" benchmarks/gpu_check.py --build-gsplat --out "$OUTDIR" >"$OUTDIR/gsplat-build.log" 2>&1
    rc=$?
    [ "$rc" = 124 ] && say "gsplat build cut at its cap ($cap s): run this again on the same machine to resume it"
    say "gsplat build exit $rc (log: gsplat-build.log)"
  else
    say "no time left to build gsplat ($left s)"
  fi
fi

# 6. the check, under the deadline; results.json / results.md rewritten after every item
say "running gpu_check (deadline in $((DEADLINE - $(date +%s))) s)"
"$PY" benchmarks/gpu_check.py --out "$OUTDIR" --work "$CACHE/work" --deadline "$DEADLINE" "$@"
rc=$?
say "done (exit $rc): $OUTDIR/results.md"
exit $rc
