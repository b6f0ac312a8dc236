"""The filtered B-spline method: per axis, the command whose modelled motion tracks the plan.

Takes an axis' planned samples, its modes (``profile.Mode``) and limits; gives the compensated
command on the same grid. ``dynamics`` discretizes each mode exactly (zero-order hold) in
parallel form; ``splines`` builds the B-spline bases; ``optimizer`` solves for the control
points window by window, the state carried exactly; ``smoothing`` and ``varying`` give it a
robust target and modes that change with the machine's state; ``fallback`` blends toward the
plan where compensating would do harm.
"""
