"""Every test process runs BLAS on one thread, as the ``fbspost`` command does (fbspost/__init__.py
sets it, but only takes effect if numpy loads after it, and test modules import numpy first).
Set before any test module loads: the axes' processes a test starts inherit it, and with
OpenBLAS's threads on one side only, the two sides round differently (a 1e-4 mm digit of one
line of the gear's head, OpenBLAS 0.3.31)."""
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
