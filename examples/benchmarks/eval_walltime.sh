#!/bin/bash
# Wall time of greedy MT10 evaluation (docs/metaworld.md, "Vectorised evaluation"), one environment at a time vs 10 in lockstep (same seeds, same machine).
set -e
for n in 1 10; do
  rm -rf runs/batch/eval_envs$n
  start=$(date +%s.%N)
  .venv/bin/hf-specvla eval --policy policies/mt10_vla --tasks MT10 --episodes 2 --num-envs $n --threads 1 \
      --output-dir runs/batch/eval_envs$n > runs/batch/eval_envs$n.log 2>&1
  end=$(date +%s.%N)
  echo "num_envs=$n wall_s=$(echo "$end - $start" | bc)"
done
