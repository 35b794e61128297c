"""Work side by side: results, errors raised as they were, the work beside stopped between its steps."""

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
