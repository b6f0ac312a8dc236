"""The whole job on one file: read, plan, compensate, fall back, write and verify, streaming.

Takes a program's path, an output path, a machine profile and ``CompensateOptions``; gives the
written file and a ``Report`` (``pipeline.compensate_file``). It runs the stages of the
packages below on stretches of the program in bounded memory; ``offload`` runs each axis'
compensation in a process of its own beside the writer, fed the plan by ``planfeed``.
"""
