"""Write the butterfly samples (run from the repository root):

- samples/butterfly.csv: the patent's butterfly, 0.8 mm per curve unit, timed to the patent stage's
  planner (100 mm/s, 5000 mm/s^2), sampled at 10 kHz;
- samples/butterfly-dense.gcode: the same motion as 1 ms G1 blocks, each with the F that gives it
  its time (what a CAM system with its own interpolator writes);
- samples/butterfly-polyline.gcode: the curve as 0.05 mm chords at F6000 (what a CAM system writes
  when the controller plans the motion).
"""
from pathlib import Path

import numpy as np

from fbspost.examples import BUTTERFLY_PARAMETER_END, butterfly, butterfly_curve
from fbspost.trajectory import Trajectory, write_trajectory_csv

HERE = Path(__file__).parent
SIZE_MM = 0.8


def program(points_mm: np.ndarray, feeds_mm_min: np.ndarray, title: str) -> str:
    lines = [f"({title})", "G21 G90 G17", f"G0 X{points_mm[0, 0]:.4f} Y{points_mm[0, 1]:.4f}"]
    previous = None
    for (x, y), feed in zip(points_mm[1:], feeds_mm_min):
        words = f"G1 X{x:.4f} Y{y:.4f}"
        if feed != previous:
            words += f" F{feed:.3f}"
            previous = feed
        lines.append(words)
    lines.append("M2")
    return "\n".join(lines) + "\n"


def main() -> None:
    times_s, x_mm, y_mm = butterfly(sample_rate_hz=10000.0, size_mm=SIZE_MM)
    write_trajectory_csv(HERE / "butterfly.csv", Trajectory({"X": x_mm, "Y": y_mm}, [f"{t:.4f}" for t in times_s]))

    dense = np.column_stack([x_mm, y_mm])[::10]  # 1 ms blocks
    dense = np.round(dense, 4)
    lengths = np.hypot(*np.diff(dense, axis=0).T)
    keep = np.concatenate([[True], lengths > 0])  # a block that does not move cannot carry time
    dense = dense[keep]
    durations = np.diff(np.flatnonzero(keep)) * 1e-3
    feeds = np.hypot(*np.diff(dense, axis=0).T) / durations * 60.0
    (HERE / "butterfly-dense.gcode").write_text(
        program(dense, np.round(feeds, 3), "butterfly, 1 ms blocks at the patent stage's planned timing"))

    theta = np.linspace(0.0, BUTTERFLY_PARAMETER_END, 400001)
    cx, cy = butterfly_curve(theta)
    curve = SIZE_MM * np.column_stack([cx, cy])
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(curve, axis=0).T))])
    stations = np.linspace(0.0, arc[-1], int(np.ceil(arc[-1] / 0.05)) + 1)
    chords = np.column_stack([np.interp(stations, arc, curve[:, 0]), np.interp(stations, arc, curve[:, 1])])
    (HERE / "butterfly-polyline.gcode").write_text(
        program(chords, np.full(len(chords) - 1, 6000.0), "butterfly, 0.05 mm chords at F6000"))


if __name__ == "__main__":
    main()
