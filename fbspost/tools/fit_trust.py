"""How far to trust a fit: its refusals, warnings and the tolerances to write.

Takes a ``Fit`` and the band it was fitted over (with the coherence where known); gives a ``Trust``
(``assess_fit``): what makes the fit unusable or doubtful, and the frequency and damping
tolerances to write for robust compensation. The thresholds are the constants here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .modal_fit import DAMPING_BOUNDS, Fit

# Good fits give errors far below these: the noisy FRFs of tests/test_identify.py (1% noise) an RMS
# error of 0.07 to 0.23% of the peak and a largest one of 1.5 to 2.1%; simulated recordings of
# excite's sweep 0.04 to 0.35% and 0.3 to 2.6%, with a mean coherence of 0.99. A sweep the
# firmware re-timed (the recording is not of the program) gave 31% and 100%, coherence 0.72.
# Refused: an error of 10% of the peak is twice the residual vibration Klipper's shapers are
# designed to leave (5%: SHAPER_VIBRATION_REDUCTION = 20 in its shaper_defs.py), so compensation
# with that model cannot be expected to beat them; a largest error of half the peak means a mode
# missed or a recording of something else; a mean coherence below 0.8 means a fifth of the
# measured power is not the axis' response to the program.
# Warned: errors ten times the simulated recordings' (3%, 20%), a tenth of the power unexplained.
WARN_RMS_ERROR, REFUSE_RMS_ERROR = 0.03, 0.10  # RMS error over the band / peak |G|
WARN_MAX_ERROR, REFUSE_MAX_ERROR = 0.20, 0.50  # largest error / peak |G|
WARN_COHERENCE, REFUSE_COHERENCE = 0.90, 0.80  # mean coherence over the band
LOW_DAMPING = 0.005  # below machine axes' (Klipper assumes 0.1 for a printer; the patent stage's lowest: 0.007)
DC_GAIN_RANGE = (0.5, 2.0)  # a position axis follows a slow command: the fit's DC gain is near 1
# The tolerances written: 3 standard deviations (99.7% of a normal estimate within them), at least
# what a machine drifts by between measurement and use (temperature, belt tension, the print's
# mass: a few % of frequency; damping, which friction sets, more), and at most what robust FBS
# covers: with 13% and 20% and wider it lost to the best shaper on two prints of three (robust.md).
COVERAGE = 3.0
MIN_FREQUENCY_TOLERANCE, MIN_DAMPING_TOLERANCE = 0.02, 0.05
MAX_TOLERANCE = 0.20
# The zeros and a time offset trade along a valley of the fit (modal_fit._along_the_valley), whose
# near ties go to the smaller offset: a controller's and an accelerometer's own delay, what is left
# after the recording's alignment on the sweep, is a fraction of a millisecond. A fit whose offset is
# more than EXPECTED_OFFSET_S is chosen by the data alone, and with another minimum within
# RIVAL_COST of its cost whose response differs by more than RIVAL_ERROR of the peak, the data does
# not decide. Seen on simulated recordings of excite's sweep of tests/data/truth-stage.toml's X
# (a net lead of 0.91 ms) on the model of LinuxCNC's planner, 7 noise draws of a 10 s sweep: the
# other minimum 1.5% above to 1.5% below (two of them 20% off the truth), one 4.5% above; with 30 s
# sweeps 7.3% above or none. The belt recordings of tests/test_identify.py have minima 0.1% to 2%
# apart too, but with offsets under 0.3 ms, where the tie rule holds.
EXPECTED_OFFSET_S = 0.4e-3
RIVAL_COST, RIVAL_ERROR = 0.03, 0.05
# A coarse estimate has no uncertainty of its own: README's values for a machine not measured.
COARSE_FREQUENCY_TOLERANCE, COARSE_DAMPING_TOLERANCE = 0.10, 0.16


@dataclass(frozen=True)
class Trust:
    """What ``assess_fit`` found: problems that make a fit unusable (``refusals``) or doubtful
    (``warnings``), each a short phrase, and the relative tolerances to write for the axis."""

    refusals: tuple[str, ...]
    warnings: tuple[str, ...]
    frequency_spread: float  # COVERAGE standard deviations relative to the value, the largest over the modes
    damping_spread: float
    frequency_tolerance: float  # the spread, at least the floor, at most MAX_TOLERANCE
    damping_tolerance: float


def assess_fit(fit: Fit, frequency_hz: np.ndarray, coherence: np.ndarray | None = None) -> Trust:
    """How far to trust ``fit`` of a response measured at ``frequency_hz`` (with ``coherence``
    where known): its error, the coherence, each mode's damping and place in the band, and the
    uncertainty of its frequencies and dampings (see the thresholds above)."""
    refusals, warnings = [], []
    error = f"RMS error {100 * fit.rms_error:.3g}% and max {100 * fit.max_error:.3g}% of the peak"
    if fit.rms_error > REFUSE_RMS_ERROR or fit.max_error > REFUSE_MAX_ERROR:
        refusals.append(f"{error} (usable: under {100 * REFUSE_RMS_ERROR:g}% and {100 * REFUSE_MAX_ERROR:g}%)")
    elif fit.rms_error > WARN_RMS_ERROR or fit.max_error > WARN_MAX_ERROR:
        warnings.append(f"{error} (good fits: under {100 * WARN_RMS_ERROR:g}% and {100 * WARN_MAX_ERROR:g}%)")
    if coherence is not None:
        mean = float(np.mean(coherence))
        phrase = f"mean coherence {mean:.2f}: {100 * (1 - mean):.0f}% of the measured power is not the response"
        if mean < REFUSE_COHERENCE:
            refusals.append(phrase)
        elif mean < WARN_COHERENCE:
            warnings.append(phrase)
    f_lo, f_hi = frequency_hz[0], frequency_hz[-1]
    for i, m in enumerate(fit.modes, start=1):
        if not DAMPING_BOUNDS[0] * 1.01 < m.damping < DAMPING_BOUNDS[1] * 0.99:
            refusals.append(f"mode {i}'s damping {m.damping:.3g} is at the fit's bound")
        elif m.damping < LOW_DAMPING:
            warnings.append(f"mode {i}'s damping {m.damping:.3g} is below machines' ({LOW_DAMPING:g})")
        # its resonance spans f (1 +- zeta): nearer an end than that it is only partly measured
        margin = m.frequency_hz * min(max(m.damping, 0.01), 0.05)
        if m.frequency_hz - f_lo < margin or f_hi - m.frequency_hz < margin:
            warnings.append(f"mode {i} at {m.frequency_hz:.4g} Hz is at the end of the band "
                            f"{f_lo:.4g}..{f_hi:.4g} Hz: measure a wider one")
    if abs(fit.delay_s) > EXPECTED_OFFSET_S and fit.rival_cost < RIVAL_COST and fit.rival_error > RIVAL_ERROR:
        than = f"{100 * abs(fit.rival_cost):.2g}% {'worse' if fit.rival_cost >= 0 else 'better'}"
        warnings.append(f"the recording cannot tell the axis' zeros from a time offset: another fit, with other "
                        f"zeros and {100 * fit.rival_error:.2g}% of the peak away, is {than} (this fit's offset "
                        f"{1e3 * fit.delay_s:+.2g} ms); a longer sweep tells them apart (excite --duration 30 or more)")
    dc_gain = sum(m.alpha / m.omega_rad_s**2 for m in fit.modes)
    if not DC_GAIN_RANGE[0] < dc_gain < DC_GAIN_RANGE[1]:
        warnings.append(f"the fit's DC gain is {dc_gain:.3g}, not about 1")
    spreads = []
    for what, sds in (("frequency", fit.frequency_sd), ("damping", fit.damping_sd)):
        spreads.append(COVERAGE * max(sds, default=0.0))
        if spreads[-1] > MAX_TOLERANCE:
            by = f"by {100 * spreads[-1]:.3g}% ({COVERAGE:g} standard deviations)" if math.isfinite(spreads[-1]) else ""
            refusals.append(f"mode {int(np.argmax(sds)) + 1}'s {what} is uncertain {by or 'wholly'}, more than "
                            f"the {100 * MAX_TOLERANCE:g}% robust FBS covers")
    tolerances = [min(max(spread, floor), MAX_TOLERANCE)
                  for spread, floor in zip(spreads, (MIN_FREQUENCY_TOLERANCE, MIN_DAMPING_TOLERANCE), strict=True)]
    return Trust(tuple(refusals), tuple(warnings), *spreads, *tolerances)
