#!/usr/bin/env bash
# Issue-28 exploration on a lent GPU (session 5): lego 200² stage-1 runs (48/56/64/80 epochs, coarse-to-fine)
# and stage 2 continued from them, launched concurrently (selection on val only; the reported numbers are CPU runs).
# The lego data travels in .gpu_data/nerf_synthetic/lego_400 (ignored; copy it from $NSPLAT_DATA), wheels in .whl/.
# Usage (device tool): run `OUT=$OUT bash benchmarks/gpu_explore_lego.sh` with carry [".whl", ".gpu_data"].
# Measured: six concurrent processes ran at about 0.23 s per stage-1 step each, so none finished in 8 min.
set -u
cd "$(dirname "$0")/.."
T0=$SECONDS; DEADLINE=${DEADLINE:-470}
export NSPLAT_DATA=$PWD/.gpu_data OMP_NUM_THREADS=2 PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 NSPLAT_BUILD_DIR=$PWD/.nsplat_build
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/plyfile*.whl .whl/kornia*.whl
for sub in ops models; do [ -e "nsplat/$sub" ] || ln -s "../$sub" "nsplat/$sub"; done
export PYTHONPATH=$PWD:/tmp/site
nvidia-smi --query-gpu=name --format=csv,noheader
python3 -c "import torch; from nsplat.ops.build import backend; backend(torch.device('cuda')); backend(torch.device('cpu')); print('built')" || exit 1
echo "built at $((SECONDS - T0)) s"
G=/tmp/g; mkdir -p $G
left() { echo $((DEADLINE - (SECONDS - T0))); }
train() {  # name, overrides...
  local name=$1; shift
  local l; l=$(left); [ "$l" -lt 20 ] && { echo "$name skipped"; return; }
  local t=$SECONDS
  timeout "$l" python3 train.py --config configs/lego.yaml --device cuda --run $G/$name --overwrite log.progress=false \
    geometry.log.validate=240 log.validate=50 geometry.optim.reposition=false "$@" >$G/$name.log 2>&1
  echo "$name rc=$? $((SECONDS - t)) s (at $((SECONDS - T0)) s)"
}
s1() { train "p$1" neural.steps=0 geometry.optim.epochs=$2 "${@:3}"; }
s2() { [ -f $G/p$1/geometry.ply ] && train "p$1-s2-$2" geometry.init=ply geometry.ply=$G/p$1/geometry.ply geometry.optim.epochs=0 neural.steps=$2 neural.view_colour=true "${@:3}"; }
( s1 48 48; s2 48 250 & s2 48 500; wait ) &
( s1 64 64; s2 64 250 & s2 64 500; wait ) &
( s1 48c24 48 geometry.optim.coarse_epochs=24; s2 48c24 250 ) &
( s1 56 56; s2 56 250 ) &
( s1 80 80; s2 80 500 ) &
( s1 64c32 64 geometry.optim.coarse_epochs=32 ) &
wait
echo "total $((SECONDS - T0)) s"
cd $G && tar czf "$OUT/gpu_explore.tgz" $(find . -maxdepth 3 \( -name "*.json" -o -name "*.log" \) -not -path "*/checkpoints/*")
