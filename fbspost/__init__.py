"""fbspost: compensate servo- and vibration-induced motion errors with filtered B-splines.

Stages, one module each: ``gcode`` (reading programs), ``planner`` (the controller's plan),
``profile`` (machine profiles), ``dynamics`` (exact discrete axis models), ``splines``
(B-spline bases), ``optimizer`` (the FBS solve), ``writer`` (the output program), ``pipeline``
(the whole job on one file), ``offload`` (its axes in processes of their own), ``trajectory``
(sampled trajectories as CSV), ``shapers`` (Klipper's input shapers), ``simulate`` (methods
compared through the model), ``plots`` (their plots), ``cli`` (the ``fbspost`` command).
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
