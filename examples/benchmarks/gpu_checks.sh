#!/usr/bin/env bash
# The GPU checks of issues 84 and 85, prepared for a lent GPU machine (the `device` tool): each part fits one call's
# 10 minutes (the first compiled speculative call of a batch size compiles ~290 s on an H200 with a cold inductor
# cache: docs/benchmarks.md); results land in $OUT (or ./runs/gpu_checks here): JSON and logs.
#
#   bash examples/benchmarks/gpu_checks.sh serve 1   # #85 item 5: openvla-7b's shapes (random weights, bf16) served,
#   bash examples/benchmarks/gpu_checks.sh serve 4   # bucket K, K robots, `exact` against a compiled-greedy server:
#                                                    # actions/s, ms an action, forwards a call, tokens unlike greedy's
#   bash examples/benchmarks/gpu_checks.sh bench 1   # #85 items 3-4: gpu_openvla.py --batch-sizes K, every method
#   bash examples/benchmarks/gpu_checks.sh bench 4   # against the fastest greedy (none:compile included), departures
#   bash examples/benchmarks/gpu_checks.sh start 1   # #84 item 5: gpu_openvla.py --batch-sizes 1 on the graph folder
#                                                    # runs/gpu_graphs ($GPU_CHECKS_GRAPHS): the first call a cold
#                                                    # process; the same again
#                                                    # on the still-warm machine (within its 30 s) a warm one
#   GPU_CHECKS_TINY=1 bash examples/benchmarks/gpu_checks.sh start 1  # any part on a tiny random OpenVLA, on the
#                                                    # CPU (PYTHON=...: an interpreter other than python3)
#   HF_SPECVLA_DYNAMIC_WIDTHS=1 bash examples/benchmarks/gpu_checks.sh bench 1  # the round's widths of 2 nodes and
#                                                    # more as one graph on the GPU too (the CPU's default, issue 84):
#                                                    # its compile time and steady state against `bench 1`'s
#
# Packages the machine's image lacks (transformers >= 5.20, the server's) travel as wheels in ./.whl (carry it), made
# here with the device README's `pip download` line: transformers==5.24.0 json-numpy==2.1.1 starlette==1.10.0
# uvicorn==0.55.0 (its huggingface-hub, tokenizers and safetensors are new enough there). `serve` reads openvla-7b's
# tokenizer and processor files from ../shared/openvla-reference/hub-openvla-7b, which does not travel: copy it to
# ./.ref/hub-openvla-7b (git-excluded, 2.5 MB) and carry .ref too (or set GPU_CHECKS_PROCESSOR_FILES).
set -euo pipefail
cd "$(dirname "$0")/../.."
part="${1:-}"
robots="${2:-1}"
case "$part" in
  serve | bench | start) ;;
  *) echo "usage: $0 serve K|bench K|start 1   (GPU_CHECKS_TINY=1: a tiny model on the CPU)" >&2; exit 2 ;;
esac
case "$robots" in
  [1-9] | [1-9][0-9]) ;;
  *) echo "usage: $0 $part K: K robots or rows (the bucket, the batch size), an integer 1..99, got '$robots'" >&2
     exit 2 ;;
esac
out="${OUT:-runs/gpu_checks}"
mkdir -p "$out"
python="${PYTHON:-python3}"  # the interpreter with torch (the machine's python3 there)
tiny="${GPU_CHECKS_TINY:-}"
if [ -z "$tiny" ] && compgen -G ".whl/*.whl" > /dev/null; then
  "$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH="/tmp/site:${PYTHONPATH:-}"
fi
export PYTHONPATH="$PWD/src:${PYTHONPATH:-}" PYTHONUNBUFFERED=1
"$python" -c "import torch, transformers; print('torch', torch.__version__, 'transformers', transformers.__version__,
      'device', torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'cpu')"
case "$part" in
  serve)
    files="${GPU_CHECKS_PROCESSOR_FILES:-.ref/hub-openvla-7b}"
    [ -d "$files" ] || files=../shared/openvla-reference/hub-openvla-7b
    shapes=(--shapes 7b --device cuda --dtype bfloat16 --steps 12 --repeats 2 --processor-files "$files")
    [ -n "$tiny" ] && shapes=(--shapes tiny --steps 4 --repeats 1 --threads 1)
    "$python" examples/benchmarks/openvla_serving.py "${shapes[@]}" --robots "$robots" --buckets "$robots" \
      --output "$out/openvla_serving_k$robots.json" 2>&1 | tee "$out/serve_k$robots.log"
    ;;
  bench)
    size=(--batch-sizes "$robots" --budget-s 420)
    [ -n "$tiny" ] && size=(--tiny)
    "$python" examples/benchmarks/gpu_openvla.py "${size[@]}" --json "$out/gpu_openvla_b$robots.json" 2>&1 \
      | tee "$out/bench_b$robots.log"
    ;;
  start)
    # kept on the machine between two calls (runs/ is ignored: it stays while the machine is warm), never brought back
    export HF_SPECVLA_GRAPH_CACHE="${GPU_CHECKS_GRAPHS:-$PWD/runs/gpu_graphs}"
    if [ -d "$HF_SPECVLA_GRAPH_CACHE" ]; then start=warm; else start=cold; fi
    size=(--batch-sizes "$robots" --budget-s 300)
    [ -n "$tiny" ] && size=(--tiny)
    SECONDS=0
    "$python" examples/benchmarks/gpu_openvla.py "${size[@]}" --json "$out/gpu_openvla_$start.json" 2>&1 \
      | tee "$out/start_$start.log"
    files=$(find "$HF_SPECVLA_GRAPH_CACHE" -name '*.graph' | wc -l)
    echo "$start process: $SECONDS s from launch to exit ($files graph files)" | tee -a "$out/start_$start.log"
    ;;
esac
