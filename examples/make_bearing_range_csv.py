"""Write the example data of the README's "bring your own model" section (plain NumPy).

A target passes behind a sensor at the origin (its bearing crosses ±pi) and is measured at
irregular times by bearing and range with glint noise (10 % of the draws from a 5x wider Gaussian);
three cells are missing. ``bearing_range.csv`` holds what a user would have (time, bearing, range);
``bearing_range_truth.csv`` holds the true positions, for the test only.

    python examples/make_bearing_range_csv.py
"""

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent / "data"


def main(seed: int = 0, n: int = 40) -> None:
    rng = np.random.default_rng(seed)
    times = np.round(np.cumsum(rng.uniform(0.2, 2.0, n)), 3)
    x, vx, y, vy = -120.0, 0.8, 25.0, -1.8
    rows, truth, t_prev = [], [], 0.0
    for t in times:
        dt = t - t_prev
        t_prev = t
        ax, ay = rng.normal(0, np.sqrt(0.05 / dt), 2)  # piecewise-constant acceleration, variance q / dt
        x, vx = x + dt * vx + 0.5 * dt * dt * ax, vx + dt * ax
        y, vy = y + dt * vy + 0.5 * dt * dt * ay, vy + dt * ay
        glint = rng.uniform() < 0.1
        s = 5.0 if glint else 1.0
        bearing = np.arctan2(y, x) + rng.normal(0, 0.01 * s)
        rng_m = np.hypot(x, y) + rng.normal(0, 1.0 * s)
        bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
        rows.append([t, bearing, rng_m])
        truth.append([t, x, y])
    rows = np.asarray(rows, dtype=object)
    for i, j in [(7, 1), (8, 2), (21, 1)]:
        rows[i, j] = ""
    HERE.mkdir(exist_ok=True)
    with open(HERE / "bearing_range.csv", "w") as fh:
        fh.write("time,bearing,range\n")
        for t, b, r in rows:
            fh.write(f"{t:.3f},{b if b == '' else f'{b:.6f}'},{r if r == '' else f'{r:.3f}'}\n")
    np.savetxt(HERE / "bearing_range_truth.csv", np.asarray(truth), delimiter=",", fmt="%.6f",
               header="time,x,y", comments="")


if __name__ == "__main__":
    main()
