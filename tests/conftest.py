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
