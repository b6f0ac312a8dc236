"""Write the butterfly samples (run from the repository root):

- samples/butterfly.csv: the patent's butterfly, 0.8 mm per curve unit, timed to the patent stage's
  planner (100 mm/s, 5000 mm/s^2), sampled at 10 kHz;
- samples/butterfly-dense.gcode: the same motion as 1 ms G1 blocks, each with the F that gives it
  its time (what a CAM system with its own interpolator writes);
- samples/butterfly-polyline.gcode: the curve as 0.05 mm chords at F6000 (what a CAM system writes
  when the controller plans the motion).
"""
from pathlib import Path

from fbspost.examples import butterfly, butterfly_dense_program, butterfly_polyline_program
from fbspost.trajectory import Trajectory, write_trajectory_csv

HERE = Path(__file__).parent
SIZE_MM = 0.8


def main() -> None:
    times_s, x_mm, y_mm = butterfly(sample_rate_hz=10000.0, size_mm=SIZE_MM)
    write_trajectory_csv(HERE / "butterfly.csv", Trajectory({"X": x_mm, "Y": y_mm}, [f"{t:.4f}" for t in times_s]))
    (HERE / "butterfly-dense.gcode").write_text(butterfly_dense_program(SIZE_MM))
    (HERE / "butterfly-polyline.gcode").write_text(butterfly_polyline_program(SIZE_MM))


if __name__ == "__main__":
    main()
