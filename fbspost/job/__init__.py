"""The whole job on one file: read, plan, compensate, fall back, write and verify, streaming.

Takes a program's path, an output path, a machine profile and ``CompensateOptions``; gives the
written file and a ``Report`` (``pipeline.compensate_file``).

It streams, so that memory stays bounded however long the program. The planner reads the
blocks 4096 at a time and settles what they decide (the pieces whose junction speeds no later
block can change, their samples, the lines' and the runs' times); each axis' optimizer stream
takes the samples 16384 at a time and gives back the command as far as its look-ahead decides
it; the fallback holds each axis' samples for its decisions (about 3 s of them on the printer
profile, 14 s on the patent's stage); the writer writes blocks as soon as their ends are known
(at most 2000 samples a block) and drops what is behind. Every sum and scan is carried over the
batches in the order one batch would take it, so the output is byte for byte that of the
program processed whole (tests/test_streaming.py), except that ``--format g5`` fits each run of
motion whole.

Each compensated axis has threads of its own for its optimizer and fallback (``axes``), but
most of the work is Python that holds the GIL. So for a program of 256 kB and more each axis
runs in a process of its own (``processes``, ``offload``: on Linux forked with its imports
done, elsewhere started as ``python -m fbspost.job.offload``). The first process reads, plans
and writes; it samples the plan once and answers each axis' requests with the next samples of
its columns, the runs and the settled moves (``planfeed``), and plans at most 65536 samples
ahead of what it has written, so that what it holds stays bounded. With ``--jobs`` above 1
every core already has a file, and the axes stay on threads. The output is the same either way
(tests/test_speed.py).

The check before committing (``verification``, ``firmware.verify``) is forked before the axes'
processes: it plans the original while the output is made, then reads the output's temporary
file as the writer announces its flushed length, re-planned in chunks of 50,000 lines with
their modes' state carried, so the verdict comes soon after the last line, in bounded memory.
"""
