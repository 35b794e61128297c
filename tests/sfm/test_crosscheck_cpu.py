"""The cross-check's report lists each step's CPU seconds beside its wall seconds (issue 40)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ffrecon.sfm.crosscheck.options import PairingMode
from ffrecon.sfm.crosscheck.run import _no_model_result
from ffrecon.sfm.features import FeatureStats
from ffrecon.timing import Timings


def test_the_report_has_each_steps_cpu_seconds():
    names = ("a.png", "b.png")
    features = FeatureStats(names, np.zeros(2, int), np.zeros(2, int), np.zeros(2, int), 1, 0)
    timings = Timings((("feature_extraction", 2.0), ("matching", 1.0), ("mapping", 0.5)), (3.5, 1.9, 0.5))
    result = _no_model_result(
        names,
        num_models=0,
        pairing=PairingMode.EXHAUSTIVE,
        mapper=None,
        mapper_runs=(),
        shared_camera=True,
        focal_prior=np.zeros(2, bool),
        camera_groups=np.zeros(2, int),
        features=features,
        timings=timings,
        database_path=Path("database.db"),
    )
    report = result.to_report()
    assert report["cpu_s"] == {"feature_extraction": 3.5, "matching": 1.9, "mapping": 0.5, "total": 5.9}
    assert set(report["cpu_s"]) == set(report["timings_s"])
