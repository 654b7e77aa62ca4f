#!/usr/bin/env bash
# Table 1 at 20 seeds (issue 35): the shipped explore recipes for IB and the Drone, and IB with
# validation.policy=offset_noise, all at commit 8987124, one run at a time (resumable: a run that
# stopped resumes; a published one is skipped). Run from the checkout's root, in the background:
#   setsid nohup bash docs/results/table1_20seeds/run_seeds.sh ../t20 > t20.log 2>&1 &
# It makes a worktree of 8987124 at $1 (default ../t20) and runs there with this checkout's venv;
# publish each finished run with
#   python docs/results/publish_run.py $1/outputs/t20/<variant>/<env>/seed<n> \
#       docs/results/table1_20seeds/<variant>/<env>/seed<n> --root $1
set -u
here=$(pwd)
tree=${1:-../t20}
[ -d "$tree" ] || git worktree add "$tree" 8987124
tree=$(cd "$tree" && pwd)
py="$here/.venv/bin/python"
cd "$tree"
export PYTHONPATH="$tree" OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
for s in $(seq 0 19); do
  for spec in "industrial_benchmark base" "drone base" "industrial_benchmark offset_noise"; do
    set -- $spec
    env=$1 variant=$2 out=outputs/t20/$2/$1/seed$s
    [ -f "$here/docs/results/table1_20seeds/$variant/$env/seed$s/results.json" ] && continue
    [ -f "$out/results.json" ] && continue
    extra=""; [ "$variant" = offset_noise ] && extra="validation.policy=offset_noise"
    mkdir -p "$(dirname "$out")"
    echo "$(date -u +%FT%T) start $out"
    nice -n 5 "$py" -m torchrl_recon.cli explore "recipes/$env/explore.yaml" seed=$s threads=1 \
      progress=false logger.backend=none output_dir=$out $extra > "$out.log" 2>&1 \
      || echo "$(date -u +%FT%T) FAILED $out"
    echo "$(date -u +%FT%T) end $out"
  done
done
