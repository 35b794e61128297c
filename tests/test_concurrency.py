"""Work side by side: results, errors raised as they were, the work beside stopped between its steps."""

import dataclasses
import shutil
import threading
import time

import pytest

from ffrecon.concurrency import Cancelled, CoreShare, run_beside
from ffrecon.errors import InputError, ModelError


def test_both_results_and_the_cores_left_beside_a_claim():
    cores = CoreShare(4)
    seen = []
    claimed = threading.Event()

    def here():
        with cores.claim(3):
            claimed.set()
            time.sleep(0.3)
        return "here"

    def beside():
        claimed.wait()
        seen.append(cores.step())  # while the claim holds
        time.sleep(0.5)
        seen.append(cores.step())  # after it
        return "beside"

    assert run_beside(here, beside, cores) == ("here", "beside")
    assert seen == [1, 4]


def test_an_error_here_stops_the_work_beside_at_its_next_step_and_is_raised_as_it_was():
    cores = CoreShare(2)
    steps = []

    def beside():
        for k in range(100):
            cores.step()
            steps.append(k)
            time.sleep(0.02)

    def here():
        time.sleep(0.1)
        raise ModelError("bad.onnx: outputs hold non-finite values", "re-export it")

    with pytest.raises(ModelError) as caught:
        run_beside(here, beside, cores)
    assert caught.value.problem == "bad.onnx: outputs hold non-finite values" and caught.value.fix == "re-export it"
    assert 0 < len(steps) < 100  # stopped between steps, and had ended before the error was raised
    n = len(steps)
    time.sleep(0.1)
    assert len(steps) == n


@pytest.mark.parametrize("error", [InputError("no vocabulary tree", "pass one"), KeyboardInterrupt()])
def test_an_error_beside_is_raised_here_after_this_side_ends(error):
    cores = CoreShare(2)
    done = []

    def beside():
        raise error

    def here():
        time.sleep(0.1)
        done.append(True)
        return 1

    with pytest.raises(type(error)) as caught:
        run_beside(here, beside, cores)
    assert caught.value is error and done == [True]
    with pytest.raises(Cancelled):
        cores.step()


def test_the_feedforward_stage_claims_onnxruntimes_threads_only_while_the_network_runs(
    small_demo, tmp_path, monkeypatch
):
    """One core for the stage's own thread throughout; onnxruntime's other threads only around each run."""
    import onnxruntime as ort

    from ffrecon.capture import CaptureOptions, run_capture
    from ffrecon.models.stage import run_feedforward_sharing
    from ffrecon.pipeline import RunOptions

    capture = run_capture(small_demo.images, CaptureOptions(), tmp_path / "run")
    options = RunOptions()
    options = dataclasses.replace(options, feedforward=dataclasses.replace(options.feedforward, threads=3))
    cores = CoreShare(8)
    left_during_runs = []
    real_run = ort.InferenceSession.run

    def spying_run(session, *args, **kwargs):
        left_during_runs.append(cores.step())
        return real_run(session, *args, **kwargs)

    monkeypatch.setattr(ort.InferenceSession, "run", spying_run)
    real_claim = cores.claim
    left_outside_runs = []

    def recording_claim(threads):
        left_outside_runs.append(cores.step())  # as each claim starts: the stage's, then each run's
        return real_claim(threads)

    monkeypatch.setattr(cores, "claim", recording_claim)
    ff = run_feedforward_sharing(capture, small_demo.model, options.feedforward, tmp_path / "run", cores)
    assert len(ff.prediction) == 8 and left_during_runs
    assert set(left_during_runs) == {8 - 3}  # the stage's core and onnxruntime's two others while it runs
    assert left_outside_runs[0] == 8 and set(left_outside_runs[1:]) == {8 - 1}  # otherwise the stage's one
    assert cores.step() == 8  # all released when the stage ends


def test_sift_extraction_asks_for_its_threads_before_each_batch(small_demo, tmp_path):
    from ffrecon.sfm.features import CameraModel, SiftOptions, create_database, extract_sift, feature_stats

    images = tmp_path / "images"
    images.mkdir()
    for copy in range(2):  # 16 images: batches of 8 (at least 8 an extraction, at most four batches)
        for path in sorted(small_demo.images.iterdir()):
            shutil.copy(path, images / f"{copy}_{path.name}")
    names = sorted(p.name for p in images.iterdir())
    db = tmp_path / "database.db"
    create_database(db, images, names, camera_model=CameraModel.PINHOLE, single_camera=True)
    asked = []
    extract_sift(db, images, names, SiftOptions(), threads=lambda: asked.append(len(asked)) or 1)
    assert len(asked) == 2
    assert (feature_stats(db, names).num_keypoints > 100).all()  # every image extracted, once
