"""fbspost: compensate servo- and vibration-induced motion errors with filtered B-splines.

Stages, one module each: ``gcode`` (reading programs), ``planner`` (the controller's plan),
``profile`` (machine profiles), ``dynamics`` (exact discrete axis models), ``splines``
(B-spline bases), ``optimizer`` (the FBS solve), ``writer`` (the output program), ``pipeline``
(the whole job on one file), ``trajectory`` (sampled trajectories as CSV), ``shapers``
(Klipper's input shapers), ``simulate`` (methods compared through the model), ``plots`` (their
plots), ``cli`` (the ``fbspost`` command).
"""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("fbspost")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+source"
