"""Regenerate the UWB test data (run from the repository root; seeded, deterministic).

static/: a platform standing still for 2 s, two tags, the cabin anchors.
moving/: one tag and an IMU on a platform driving a 1.5 m line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from fabflow.positioning.uwb_io import write_imu_csv, write_ranges_csv
from fabflow.sensors.imu import ImuErrorModel, simulate_imu
from fabflow.sensors.uwb import UwbErrorModel, draw_bias, ranging_schedule, simulate_ranges
from fabflow.sensors.uwb_trajectories import PlanarTrajectory

HERE = Path(__file__).parent
IDS = ["A1", "A2", "A3", "A4"]
ANCHORS = np.array([[0.0, 0.0, 1.0], [4.8, 0.0, 1.0], [4.8, 6.0, 1.0], [0.0, 6.0, 3.2]])
T_WORLD_UWB = np.array([-0.4, -1.0, 0.0])
TAGS = np.array([[0.8, 0.0, 1.5], [-0.8, 0.0, 1.5]])
T_PLATFORM_BASE = [0.3, 0.0, 0.6]
PLATFORM_XY_YAW = (1.6, 2.2, np.radians(30.0))


def _anchors_yaml(path: Path, bias, tags: np.ndarray) -> None:
    data = {
        "anchors": {k: [float(v) for v in a] for k, a in zip(IDS, ANCHORS, strict=True)},
        "T_world_uwb": {"xyz": [float(v) for v in T_WORLD_UWB]},
        "sigma": 0.05,
        "sigma_growth": 0.01,
        "multipath_sigma": 0.0,  # simulated without multipath: an open site
        "tags": [[float(v) for v in t] for t in tags],
        "calibration": {
            k: [round(float(a), 4), round(float(b), 5)]
            for k, a, b in zip(IDS, bias.offset, bias.scale, strict=True)
        },
        "T_platform_base": {"xyz": T_PLATFORM_BASE},
    }
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")


def main() -> None:
    rng = np.random.default_rng(20261122)
    model = UwbErrorModel(sigma_1m=0.05, growth=0.01)  # the noise the files were made with
    anchors_w = ANCHORS + T_WORLD_UWB
    bias = draw_bias(4, model, rng)

    out = HERE / "static"
    out.mkdir(exist_ok=True)
    x, y, yaw = PLATFORM_XY_YAW
    c, s = np.cos(yaw), np.sin(yaw)
    tags_w = np.array([x, y, 0.0]) + TAGS @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    t, ti, ai = ranging_schedule(2.0, 60.0, 4, n_tags=2)
    sim = simulate_ranges(anchors_w, tags_w[ti], model, rng, bias=bias)
    r = np.take_along_axis(sim.ranges, ai[..., None], axis=-1)[..., 0]
    write_ranges_csv(out / "ranges.csv", t.ravel(), ti.ravel(), ai.ravel(), r.ravel(), IDS)
    _anchors_yaml(out / "anchors.yaml", bias, TAGS)

    out = HERE / "moving"
    out.mkdir(exist_ok=True)
    traj = PlanarTrajectory(np.array([[1.2, 1.5], [2.7, 1.5]]), 2.0, speed=0.3, rest_s=1.5)
    t, _, ai = ranging_schedule(traj.duration, 60.0, 4)
    truth = traj.sample(t.ravel()).p.reshape(*t.shape, 3)
    sim = simulate_ranges(anchors_w, truth, model, rng, bias=bias)
    r = np.take_along_axis(sim.ranges, ai[..., None], axis=-1)[..., 0]
    write_ranges_csv(
        out / "ranges.csv", t.ravel(), np.zeros(t.size, int), ai.ravel(), r.ravel(), IDS
    )
    imu = simulate_imu(traj, 100.0, ImuErrorModel(), rng)
    write_imu_csv(out / "imu.csv", imu.t, imu.accel, imu.gyro)
    _anchors_yaml(out / "anchors.yaml", bias, np.zeros((1, 3)))


if __name__ == "__main__":
    main()
