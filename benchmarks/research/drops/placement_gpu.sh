#!/bin/bash
# Issue 37 on a lent GPU, in one call:
#  1. the faithful DUSty-I at the paper's width for STEPS steps, its drop placement scored on
#     validation scans while it trains (every CURVE steps; as trained, one offset per ring, and
#     levels per (ring, depth) cell, placement_curve.py --follow), then on test scans at the end;
#  2. beside it, SEEDS training seeds of the faithful DUSty-I at the CPU study's scale, each
#     exported (EMA generator) for scoring with levels on a CPU.
# On a lent machine: INSTALL=1 bash benchmarks/research/drops/placement_gpu.sh
# (wheels in .gpu/wheels: trimesh, embreex, rtree, ml-collections, tensorboardX). Everything
# stops at BUDGET seconds; what is done by then is under $OUT.
# (The 2026-11-26 screen of faithful vs ring_norm: git show 7947373:<this file>.)
set -u
STEPS=${STEPS:-10000}; EVERY=${EVERY:-1000}; CURVE=${CURVE:-2000}; SCALE=${SCALE:-paper}
SEEDS=${SEEDS:-0,1,2,3,4}; NUM=${NUM:-64}; ISTEPS=${ISTEPS:-300}; SEED_STEPS=${SEED_STEPS:-2500}; BUDGET=${BUDGET:-560}
PY=${PY:-python3}; OUT=${OUT:-/tmp/gpu_out}; W=${W:-/tmp/gpu_runs}
mkdir -p "$OUT" "$W"
export DUSTY_JAX_CACHE=${DUSTY_JAX_CACHE:-/tmp/djcache} PYTHONPATH=$PWD PYTHONUNBUFFERED=1
t0=$(date +%s)
stamp() { echo "[$(( $(date +%s) - t0 )) s] $*"; }
left() { echo $(( BUDGET - ($(date +%s) - t0) )); }
if [ -n "${INSTALL:-}" ]; then
  $PY -m pip install --no-deps --no-index -q ${WHEELS:-.gpu/wheels}/*.whl 2>&1 | tail -2
  nvidia-smi -L
fi
stamp data
# A file, not stdin: the simulation's spawned workers import the main module.
cat > $W/data.py <<PYEOF
from dusty_jax import configs, sensor
from dusty_jax.data import pipeline
if __name__ == '__main__':
  c = configs.study('dusty1', 'authors', '$SCALE')
  print(pipeline.dataset_dir(c, sensor.from_config(c.sensor), log=lambda *a: None))
PYEOF
D=$($PY $W/data.py | tail -1)
stamp "data at $D"; ls "$D" >/dev/null || exit 1

XLA_PYTHON_CLIENT_MEM_FRACTION=0.45 timeout $(left) $PY -m dusty_jax.train \
  --config experiments/study.py:dusty1,authors,$SCALE --workdir $W/faithful \
  --config.num_steps=$STEPS --config.checkpoint_every=$EVERY --config.keep_every=$EVERY \
  --config.log_every=100 --config.image_every=$STEPS --config.checkpoint_minutes=0 \
  > $OUT/faithful.log 2>&1 &
TRAIN=$!
XLA_PYTHON_CLIENT_MEM_FRACTION=0.2 timeout $(left) $PY benchmarks/research/drops/placement_curve.py \
  --runs faithful=$W/faithful --data-dir "$D" --split val --num $NUM --steps $ISTEPS \
  --every $CURVE --follow $STEPS --minutes $(echo "$(left) / 60" | bc -l) --out $OUT \
  --name placement_${SCALE}_val --title "faithful DUSty-I, $SCALE width: 64 validation scans" \
  > $OUT/curve.log 2>&1 &
CURVE_PID=$!
(
  cat > $W/export.py <<'PYEOF'
import sys
from dusty_jax import generator
params, _ = generator.load(sys.argv[1], log=lambda *a: None)
generator.export(params, sys.argv[2], source=sys.argv[1])
PYEOF
  for s in ${SEEDS//,/ }; do
    [ "$(left)" -lt 60 ] && { echo "seed $s: no time left"; break; }
    XLA_PYTHON_CLIENT_MEM_FRACTION=0.12 timeout $(( $(left) - 10 )) $PY -m dusty_jax.train \
      --config experiments/study.py:dusty1,authors,cpu --workdir $W/seed$s \
      --config.seed=$s --config.num_steps=$SEED_STEPS --config.checkpoint_minutes=0 \
      --config.image_every=$SEED_STEPS 2>&1 | tr '\r' '\n' | grep -v "it/s\|s/it" | tail -4
    XLA_PYTHON_CLIENT_MEM_FRACTION=0.05 JAX_PLATFORMS=cpu $PY $W/export.py $W/seed$s $W/seed$s.npz \
      && cp $W/seed$s/metrics.jsonl $W/seed$s.metrics.jsonl && stamp "seed $s exported"
    # three exports to a file: a file over 16 MiB would not come back
    (cd $W && tar cf $OUT/seeds_a.tar $(ls seed*.npz seed*.jsonl | grep "seed[012]\.") &&
     ls seed*.npz | grep -qv "seed[012]\." && tar cf $OUT/seeds_b.tar $(ls seed*.npz seed*.jsonl | grep -v "seed[012]\."))
  done
) > $OUT/seeds.log 2>&1 &
SEED_PID=$!
wait $TRAIN; stamp "trained (rc $?)"
tr '\r' '\n' < $OUT/faithful.log | grep -v "step/s\|s/step" | tail -4
wait $CURVE_PID; stamp "val curve (rc $?)"; cat $OUT/curve.log | tail -8
[ "$(left)" -gt 45 ] && XLA_PYTHON_CLIENT_MEM_FRACTION=0.2 timeout $(left) \
  $PY benchmarks/research/drops/placement_curve.py --runs faithful=$W/faithful --data-dir "$D" \
  --split test --num $NUM --steps $ISTEPS --at $STEPS --out $OUT --name placement_${SCALE}_test \
  --title "faithful DUSty-I, $SCALE width, step $STEPS: 64 test scans" 2>&1 | tail -3
rm -f $OUT/placement_${SCALE}_test.png  # eight files come back; drawn again from the JSON
stamp "test"
wait $SEED_PID; stamp "seeds"; cat $OUT/seeds.log
ls -la $OUT; stamp done
