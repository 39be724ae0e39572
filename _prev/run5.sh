#!/bin/bash
source /root/gpu-env.sh
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl 2>/dev/null
export PYTHONUNBUFFERED=1 PYTHONPATH=.:/tmp/site:$PYTHONPATH
mkdir -p $OUT/new
python3 -m pytest -q -p no:cacheprovider tests/test_gn_block.py -k cuda 2>&1 | tail -2
B="python3 bench/gn_block.py --out $OUT/new"
$B --sections peak,capture,efl --precisions tf32,fp16,bf16,fp32 --batches 200,4096 2>&1 | grep "warp-split\|rror"
$B --sections main --peers torch-compile-ro --precisions tf32,fp16 --batches 4096 --fwd-batches "" --compile-modes fwd 2>&1 | grep "torch-compile-ro" | grep -v fwdbwd
$B --sections main,errors --peers warp-split --precisions fp16,bf16,tf32,fp32 --batches 4096 --fwd-batches 65536 2>&1 | grep "warp-split\|error vs" | grep -v "fwdbwd\|train"
$B --sections profile --peers warp-split --precisions fp16 2>&1 | grep "^=="
cd $OUT && tar czf res.tgz new && rm -rf new
