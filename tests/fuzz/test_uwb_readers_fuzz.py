"""Fuzz: UWB ranges, IMU records and anchors files, damaged, are read or refused cleanly."""

from __future__ import annotations

from helpers import DATA
from hypothesis import given
from hypothesis import strategies as st
from reader_mutations import check_reader, fuzz_settings, mutated

from fabflow.localize.uwb_files import load_anchors_file
from fabflow.positioning.uwb_io import read_imu_csv, read_ranges_csv

STATIC = DATA / "uwb" / "static"
MOVING = DATA / "uwb" / "moving"
IDS = ["A1", "A2", "A3", "A4"]
RANGES = (STATIC / "ranges.csv").read_bytes()[:4000]
IMU = (MOVING / "imu.csv").read_bytes()[:4000]
ANCHORS = [(STATIC / "anchors.yaml").read_bytes(), (MOVING / "anchors.yaml").read_bytes()]
YAML_JUNK = [
    b"[" * 5000,
    b"{a: " * 3000,
    b"- " * 3000 + b"1",
    b"anchors: {A1: [0, 0, 1]}\nanchors: {A2: [1, 0, 1]}\n",
    b"anchors: &a {A1: [0, 0, *a]}\n",
    b"a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
    b"c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]\nd: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c]\n"
    b"e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d]\nf: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e]\n"
    b"g: [*f, *f, *f, *f, *f, *f, *f, *f, *f]\n",
    b"anchors: !!python/object/apply:os.system [echo hi]\n",
    b"sigma: !!int abc\n",
    b"anchors: {A1: [0, 0, " + b"9" * 5000 + b"]}\n",
    b"anchors: {A1: [0, 0, 1], A2: [4, 0, 1], A3: [4, 6, 1], A4: [0, 6, 3]}\ntags: []\n",
]


def _ranges_ok(log: object) -> bool:
    import numpy as np

    return bool(
        np.all(np.isfinite(log.t)) and np.all(np.isfinite(log.range)) and np.all(log.range >= 0)
    )


@fuzz_settings(60)
@given(mutated(RANGES))
def test_ranges_files(data: bytes) -> None:
    log = check_reader(lambda p: read_ranges_csv(p, IDS, 2), data, ".csv")
    assert log is None or _ranges_ok(log)


@fuzz_settings(60)
@given(mutated(IMU))
def test_imu_files(data: bytes) -> None:
    check_reader(read_imu_csv, data, ".csv")


@fuzz_settings(70)
@given(st.one_of(st.sampled_from(ANCHORS).flatmap(mutated), st.sampled_from(YAML_JUNK)))
def test_anchors_files(data: bytes) -> None:
    check_reader(load_anchors_file, data, ".yaml")
