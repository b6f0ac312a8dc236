"""The ``fbspost`` command line.

Takes arguments and files; gives exit status 0 on success, 1 on bad input (one line
``error: FILE:LINE: message`` on stderr, no traceback, no output file; with several programs,
one such line per failed file and the others still written), 2 on bad usage, 128 + the signal's
number when interrupted (130 for Ctrl-C, 143 for SIGTERM, 129 for SIGHUP), leaving no output or
temporary file behind.
"""
from . import compensate, profiles, simulate  # noqa: F401  (each registers its commands)
from .group import main

__all__ = ["main"]
