"""Set-up shared by every test module."""

import signal

import pytest


@pytest.fixture(autouse=True, scope="session")
def ctrl_c_is_delivered():
    """Several tests send themselves Ctrl-C. A shell starts a background job with SIGINT ignored, and
    the product keeps it so (``pipeline.cli.main``); the tests start from Python's own handler."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Every test starts with one torch thread, whatever an earlier test set: two threads on the two
    shared cores wait on each other whenever another process runs (the val50 test took 46 s with two
    and 2.5 s with one, under a load of 5), and no test then depends on what an earlier one left."""
    import torch

    torch.set_num_threads(1)
    yield
