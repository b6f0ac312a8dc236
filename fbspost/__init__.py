"""fbspost: compensate servo- and vibration-induced motion errors with filtered B-splines.

A package per stage, lowest first (a package imports only from those below it):
``profile`` (machine profiles), ``errors`` (bad input), ``contour`` (the contour error's
measure); ``read`` (programs to blocks), ``plan`` (the controller's plan), ``fbs`` (the method),
``firmware`` (what each firmware does with the output), ``write`` (the output program), ``job``
(the whole job on one file), ``tools`` (simulate, identify, excite), ``cli`` (the ``fbspost``
command). docs/architecture.md is the map.
"""
import os
from importlib.metadata import PackageNotFoundError, version

# One BLAS thread unless told otherwise (read when numpy loads: the ``fbspost`` command loads it
# after this): the matrices are small and the axes already run on threads of their own; OpenBLAS's
# threads made the gear's optimize stage take 1.4 times the CPU time on two cores.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

try:
    __version__ = version("fbspost")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+source"
