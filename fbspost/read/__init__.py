"""Reading programs: G-code text to blocks in machine millimetres.

Takes a program's path, its flavor (``FLAVORS``) and the machine profile; gives one ``Block``
per input line (``gcode.read_gcode``): its exact bytes, its kind (a move, a line passed through,
a stop), its linear pieces (arcs, G5 cubics and NURBS cut within a chord tolerance), the limits
it sets and the modal state. LinuxCNC programs that need its interpreter (subroutines,
expressions, canned cycles) are first expanded to plain G-code by ``rs274`` (``expand``).
Bad input raises ``errors.InputError`` naming the file and line.
"""
