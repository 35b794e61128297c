"""Splat tests run torch on one thread: on a shared 2-core machine two OpenMP threads can be ten
times slower than one whenever the other core is busy (measured; see tools/bench_splat.py)."""

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
