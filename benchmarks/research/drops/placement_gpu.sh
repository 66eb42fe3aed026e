#!/bin/bash
# Issue 37 item 6: faithful DUSty-I and the ring_norm variant at one scale,
# trained side by side, then drop placement at every kept checkpoint.
# ring_norm left the library: apply placement_ring_norm.patch (git apply) first.
# On a lent GPU machine: INSTALL=1 bash benchmarks/research/drops/placement_gpu.sh
# (writes to $OUT; STEPS, EVERY, CURVE, SCALE as below).
set -u
STEPS=${STEPS:-10000}; EVERY=${EVERY:-1000}; SCALE=${SCALE:-paper}; PY=${PY:-python3}
OUT=${OUT:-/tmp/gpu_out}; W=${W:-/tmp/gpu_runs}; FRAC=${FRAC:-0.4}; CURVE=${CURVE:-2000}
mkdir -p "$OUT" "$W"
export DUSTY_JAX_CACHE=${DUSTY_JAX_CACHE:-/tmp/djcache} PYTHONPATH=$PWD
t0=$(date +%s)
stamp() { echo "[$(( $(date +%s) - t0 )) s] $*"; }
if [ -n "${INSTALL:-}" ]; then
  # wheels for the packages a GPU image lacks (trimesh, embreex, rtree, ml-collections,
  # tensorboardX), fetched beforehand with pip download --python-version 3.12
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
stamp "data at $D"; ls "$D" || exit 1
COMMON="--config experiments/study.py:dusty1,authors,$SCALE --config.num_steps=$STEPS
  --config.checkpoint_every=$EVERY --config.keep_every=$EVERY --config.log_every=100
  --config.image_every=$STEPS --config.checkpoint_minutes=0"
XLA_PYTHON_CLIENT_MEM_FRACTION=$FRAC $PY -m dusty_jax.train $COMMON --workdir $W/faithful \
  > $OUT/faithful.log 2>&1 &
XLA_PYTHON_CLIENT_MEM_FRACTION=$FRAC $PY -m dusty_jax.train $COMMON --workdir $W/ring_norm \
  --config.drops.ring_bias=True --config.drops.ring_norm=True --config.drops.ring_control=0.2 \
  > $OUT/ring_norm.log 2>&1 &
wait
stamp trained
for r in faithful ring_norm; do tr '\r' '\n' < $OUT/$r.log | grep -v "step/s\|s/step" | tail -5; done
$PY benchmarks/research/drops/placement_curve.py --runs faithful=$W/faithful,ring_norm=$W/ring_norm \
  --data-dir "$D" --split val --num 64 --steps 300 --every $CURVE --out $OUT \
  --name placement_${SCALE}_val --title "DUSty-I, $SCALE scale, faithful vs ring_norm: 64 validation scans"
stamp "val curves"
[ -n "${SKIP_TEST:-}" ] && exit 0
$PY benchmarks/research/drops/placement_curve.py --runs faithful=$W/faithful,ring_norm=$W/ring_norm \
  --data-dir "$D" --split test --num 64 --steps 300 --every $STEPS --out $OUT \
  --name placement_${SCALE}_test --title "DUSty-I, $SCALE scale, final step: 64 test scans"
stamp done
