#!/usr/bin/python3
"""The headless "display" of bench/firmware.py's LinuxCNC runs: moves to $TP_START (X Y, and Z where
given) by MDI, then records joint.0/1/2.motor-pos-cmd every servo period (halsampler, sim.hal's sampler) to
$TP_OUT while $TP_PROGRAM runs in auto mode, and stops recording once the machine is at rest."""
import os
import subprocess
import sys
import time

import linuxcnc

stat, command = linuxcnc.stat(), linuxcnc.command()


def wait(done, timeout_s=600.0):
    end = time.time() + timeout_s
    while time.time() < end:
        stat.poll()
        if done():
            return True
        time.sleep(0.01)
    return False


def idle():
    return stat.interp_state == linuxcnc.INTERP_IDLE and stat.queue == 0 and stat.inpos


for state in (linuxcnc.STATE_ESTOP_RESET, linuxcnc.STATE_ON):
    command.state(state)
    command.wait_complete()
command.mode(linuxcnc.MODE_MDI)
command.wait_complete()
start = os.environ["TP_START"].split()  # X Y, and Z where the program gives it
command.mdi("G21 G90 G0 " + " ".join(f"{axis}{value}" for axis, value in zip("XYZ", start, strict=False)))
command.wait_complete()
wait(idle)
time.sleep(0.1)
# (line-buffered: a block of stdio buffer still unwritten at the end was lost with it, and the
# record ended short of the program)
sampler = subprocess.Popen(["stdbuf", "-oL", "halsampler", "-c", "0"], stdout=open(os.environ["TP_OUT"], "w"))
command.mode(linuxcnc.MODE_AUTO)
command.wait_complete()
command.program_open(os.environ["TP_PROGRAM"])
command.wait_complete()
command.auto(linuxcnc.AUTO_RUN, 0)
command.wait_complete()  # (the task has the run: else idle() may still see the state before it)
wait(lambda: not idle(), 10.0)
def settled(hold_s=0.3):
    """At rest for ``hold_s`` on end: under load the queue runs dry for moments mid-program."""
    if not idle():
        return False
    end = time.time() + hold_s
    while time.time() < end:
        time.sleep(0.01)
        stat.poll()
        if not idle():
            return False
    return True


finished = wait(settled)
time.sleep(0.1)


def recorded_at_rest():
    """The record has reached where the machine rests: halsampler reads the sampler's FIFO
    behind the motion (more so under load), so it is stopped only then."""
    with open(os.environ["TP_OUT"], "rb") as f:
        f.seek(max(0, os.path.getsize(os.environ["TP_OUT"]) - 200))
        lines = f.read().splitlines()
    stat.poll()
    try:
        last = [float(v) for v in lines[-2].split()]  # (a whole line: the last may be half written)
    except (IndexError, ValueError):
        return False
    return all(abs(a - b) < 2e-6 for a, b in zip(last, stat.position[:3], strict=False))


wait(recorded_at_rest, 30.0)
time.sleep(0.1)
sampler.terminate()
print("LinuxCNC run " + ("done" if finished else "timed out"), file=sys.stderr)
