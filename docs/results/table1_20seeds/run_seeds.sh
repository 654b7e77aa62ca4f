#!/usr/bin/env bash
# Issue 35's remaining Table 1 repeats, one run per call of this worker loop; start it once per
# core you can spare. Each run is claimed with mkdir (so two workers never take the same one),
# runs at nice 19 on one thread from a worktree of the commit all 60 runs share, and resumes where
# it stopped if killed (same command, same output_dir). Publishing stays a manual step:
#   python docs/results/publish_run.py <worktree>/outputs/t20/<variant>/<env>/seed<n> \
#       docs/results/table1_20seeds/<variant>/<env>/seed<n> --root <worktree>
# Usage: docs/results/table1_20seeds/run_seeds.sh [worktree] [python]
set -u
# With the kernel's autogroup scheduling on (sessions weighed against each other), `nice` alone
# leaves this loop half the machine; lowering its session's group makes it yield to other work.
echo 19 > "/proc/$$/autogroup" 2>/dev/null || true
COMMIT=89871241a159182b8c8864d8a2474010b9be48cd
HERE="$(cd "$(dirname "$0")" && pwd)"
TREE="${1:-../frozen}"
PY="${2:-$PWD/.venv/bin/python}"
[ -d "$TREE" ] || git worktree add --detach "$TREE" "$COMMIT"
TREE="$(cd "$TREE" && pwd)"
[ "$(git -C "$TREE" rev-parse HEAD)" = "$COMMIT" ] || { echo "error: $TREE is not at $COMMIT" >&2; exit 2; }
mkdir -p "$TREE/outputs/t20/claims"
for seed in $(seq 0 19); do
  for job in "base industrial_benchmark" "base drone" "offset_noise industrial_benchmark"; do
    set -- $job; variant=$1; env=$2
    [ -f "$HERE/$variant/$env/seed$seed/results.json" ] && continue        # published
    mkdir "$TREE/outputs/t20/claims/$variant-$env-$seed" 2>/dev/null || continue  # taken
    extra=(); [ "$variant" = offset_noise ] && extra=(validation.policy=offset_noise)
    out="outputs/t20/$variant/$env/seed$seed"
    mkdir -p "$TREE/$(dirname "$out")"
    echo "$(date -u +%FT%TZ) start $variant $env seed$seed"
    (cd "$TREE" && nice -n 19 env OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 "$PY" -m torchrl_recon.cli \
        explore "recipes/$env/explore.yaml" "seed=$seed" threads=1 progress=false \
        logger.backend=none "output_dir=$out" "${extra[@]}" > "$out.log" 2>&1 || true)
    if [ -f "$TREE/$out/results.json" ]; then
      echo "$(date -u +%FT%TZ) done $variant $env seed$seed"
    else
      echo "$(date -u +%FT%TZ) FAILED $variant $env seed$seed (see $TREE/$out.log)"
      rmdir "$TREE/outputs/t20/claims/$variant-$env-$seed"
    fi
  done
done
