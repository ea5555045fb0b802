"""relaxmap services: one package per service, a pure core and a thin bus node each."""

import os

# One BLAS thread per process, set before numpy loads. The services' dense products are small (a dot
# over the links, 2x2 blocks) and six processes share the cores: a threaded OpenBLAS spins and waits
# for busy cores, which made one 14k-element dot product take 140 ms instead of 20 us under load
# (measured on 2 cores). An explicit setting in the environment wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
