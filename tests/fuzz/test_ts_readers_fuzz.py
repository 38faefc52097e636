"""Fuzz: total-station observations (CSV, GSI-8/16) and robot points, damaged, read or refused."""

from __future__ import annotations

import numpy as np
from helpers import TS_DATA
from hypothesis import given
from hypothesis import strategies as st
from reader_mutations import all_finite, check_reader, fuzz_settings, mutated

from fabflow.positioning.polar import Observations
from fabflow.positioning.ts_io import read_observations, read_robot_points

OBS = (TS_DATA / "obs.csv").read_bytes()
GSI = [(TS_DATA / "obs_gsi8.gsi").read_bytes(), (TS_DATA / "obs_gsi16.gsi").read_bytes()]
ROBOT = [
    (TS_DATA / "robot_points.csv").read_bytes(),
    b"point_id,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n"
    b"P1,10,-60,100,0,50,0\nP2,20,-70,90,10,40,0\nP3,-15,-50,110,0,60,5\n",
]
OBS_XYZ = (
    b"point_id,x_m,y_m,z_m,prism_height_m\nP1,1.2,3.4,0.9,0\nP2,2.5,1.1,1.6,0.1\nP3,0.4,2.2,1.9,\n"
)


def observations_finite(obs: Observations) -> bool:
    """Every row complete and finite in its kind (polar or coordinates), heights finite."""
    polar = np.isfinite(np.c_[obs.hz, obs.v, obs.sd]).all(axis=1)
    coords = np.isfinite(obs.xyz).all(axis=1)
    return bool(np.all(polar | coords)) and all_finite(
        [obs.prism_height, obs.instrument_height, obs.station_xyz]
    )


@fuzz_settings(60)
@given(st.sampled_from([OBS, OBS_XYZ]).flatmap(mutated))
def test_observation_csv_files(data: bytes) -> None:
    check_reader(read_observations, data, ".csv", observations_finite)


@fuzz_settings(70)
@given(st.sampled_from(GSI).flatmap(lambda s: mutated(s, line_ops=False)))
def test_gsi_files(data: bytes) -> None:
    check_reader(read_observations, data, ".gsi", observations_finite)


@fuzz_settings(60)
@given(st.sampled_from(ROBOT).flatmap(mutated))
def test_robot_point_files(data: bytes) -> None:
    check_reader(read_robot_points, data, ".csv")
