"""The commands beside compensate, built on the same stages.

``simulate`` (with ``plots``) models a program through the axes' modes, original, FBS and
input shapers side by side; ``identify`` fits a profile's modes from a measurement (a
frequency response, an accelerometer recording of ``excite``'s sweep, or Klipper's own
figures); ``excite`` writes that sweep; ``trajectory`` reads and writes sampled CSV for the
optimizer alone; ``examples`` makes the patent's butterfly.
"""
