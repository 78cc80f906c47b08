#!/usr/bin/env bash
# Everything issue 17 asks of a GPU, in one command for a lent device machine (docs/performance.md,
# "GPU"): the CUDA tests, then the throughput benchmark. About 9 minutes on one GPU; the outputs go
# to $OUT (the device tool's folder that comes back) or ./gpu_out.
#
# Prepared here (CPU machine), once:   make gpu-wheels    (.whl/: hydra-core, omegaconf, antlr4, the
#                                                          pure-Python packages the device image lacks)
# Then one device call:                run(command="bash benchmarks/gpu_session.sh", carry=[".whl"],
#                                          timeout_s=600)
# The device image has python3 with CUDA torch, numpy, pytest, matplotlib, tensorboard and scipy.
set -uo pipefail
out=${OUT:-gpu_out}
mkdir -p "$out"
if compgen -G ".whl/*.whl" > /dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        && export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=.${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
{ nvidia-smi; python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"; } \
    > "$out/machine.txt" 2>&1
cat "$out/machine.txt"
# 1. the CUDA tests: host synchronisation, the smoothers, association and set metrics, the batch-last
#    kernels of GPB2, the VSIMM, IMM-TF, the two-filter smoother and the EKF/UKF banks, every study with
#    device=cuda (at most 220 s)
timeout 220 python3 -m pytest -q -p no:cacheprovider -rs -n 4 -k cuda tests/test_host_sync.py \
    tests/smoothing/test_two_filter.py tests/smoothing/test_parallel.py tests/test_pda.py tests/test_set_metrics.py \
    tests/test_association_cuda.py tests/test_batch_last_cuda.py \
    tests/experiments/test_studies.py 2>&1 | tee "$out/cuda_tests.log"
# 2. throughput (the script stops escalating past 40 s a size and ends within about 5 minutes)
timeout 320 python3 benchmarks/gpu.py ${GPU_ARGS:-} 2>&1 | tee "$out/gpu_benchmark.log"
