"""Write samples/butterfly.csv: the patent's butterfly, 0.8 mm per curve unit, timed to the
patent stage's planner (100 mm/s, 5000 mm/s^2), sampled at 10 kHz. Run from the repository root."""
from pathlib import Path

from fbspost.examples import butterfly
from fbspost.trajectory import Trajectory, write_trajectory_csv

times_s, x_mm, y_mm = butterfly(sample_rate_hz=10000.0, size_mm=0.8)
write_trajectory_csv(Path(__file__).with_name("butterfly.csv"),
                     Trajectory({"X": x_mm, "Y": y_mm}, [f"{t:.4f}" for t in times_s]))
