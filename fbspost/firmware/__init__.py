"""What each target firmware does with what fbspost writes, and what fbspost writes around it.

Models of the firmwares' planners (Marlin ``marlin``, RepRapFirmware ``reprap``, LinuxCNC
``linuxcnc_tp``; Klipper's is the plan itself), dispatched by ``planners.replan``; their input
shapers (``shapers``, ``shaping``); whole motor steps (``steps``); the settings written around
the output and restored after it (``transparency``); LinuxCNC's time law (``linuxcnc_time``);
and ``verify``, which runs a written program through its firmware's model and the axes' modes
to decide whether the output or the original is kept.
"""
