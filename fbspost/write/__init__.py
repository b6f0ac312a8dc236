"""Writing the output: compensated samples back to G-code, and files that are never partial.

Takes the blocks in order, the compensated command of each axis and the write options; gives
the program text (``writer.write_program``): the copied lines byte-exact at their times, the
motion between them as G1 blocks (or G5 cubics, ``bezier``) within the tolerance, each F from
its block's time, the rounding residues of positions, extrusion and time carried.
``atomicfile.atomic_write`` writes through a temporary file renamed over the destination.
"""
