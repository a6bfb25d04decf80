"""Bedside EIT pressure-sore monitor.

Data flows one way: ``drivers`` (buses, chips, scan engine) -> ``core``
(layouts, forward models, reconstruction) -> ``alerts`` -> ``store`` and
publishing -> the web UI. ``import appliance`` needs only numpy and scipy.
"""

import os

# The appliance's matrices are small (hundreds of rows) and its cores are shared
# with the web UI and the acquisition loop. Multi-threaded BLAS then loses far more
# to threads spinning for a busy core than it gains: a 256 x 256 Cholesky took
# 0.4 ms on one thread and 160 ms on two while another process ran (measured).
# These take effect only if set before numpy is first imported, so every entry
# point (the CLI, the tests' conftest, the benchmarks) imports appliance first.
for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

__version__ = "0.1.0"
