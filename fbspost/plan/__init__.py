"""The controller's plan: blocks to timed, sampled motion, as the firmware would run it.

Takes the blocks (``read``) and the profile's limits; gives a ``planner.PlanStream`` (a growing
``Plan``): the trapezoidal (or jerk-limited) velocity profile with the firmware's look-ahead and
junction rules (Klipper's in ``klipper_rules``), the runs of motion with their lead and settle
margins, and the positions sampled on the profile's grid, settled as far as no later block can
change them.
"""
