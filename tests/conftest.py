"""Shared fixtures for the whole suite."""

import pytest
import torch


@pytest.fixture(autouse=True)
def single_torch_thread():
    """Small networks run fastest on one thread; on a busy machine two threads can be 20x slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
