#!/bin/bash
source /root/gpu-env.sh
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl 2>/dev/null
export PYTHONUNBUFFERED=1 PYTHONPATH=.:/tmp/site:$PYTHONPATH
mkdir -p $OUT/new $OUT/off
python3 -m pytest -q -p no:cacheprovider tests/test_gn_block.py -k cuda 2>&1 | tail -1
for flag in True False True; do
python3 -c "
import sys, runpy; sys.path.insert(0, '.')
import gnwarp.gn_warp as g; g._PRECAST_GATHERED = $flag
sys.argv = ['gn_block.py', '--sections', 'peak,capture', '--precisions', 'fp16,bf16', '--batches', '200,4096', '--out', '$OUT/' + ('new' if $flag else 'off')]
runpy.run_path('bench/gn_block.py', run_name='__main__')
" 2>&1 | grep "warp-split" | sed "s/^/precast=$flag /"
done
python3 bench/gn_block.py --sections profile --peers warp-split --precisions fp16 --out $OUT/new 2>&1 | grep "^=="
cd $OUT && tar czf res.tgz new off && rm -rf new off
