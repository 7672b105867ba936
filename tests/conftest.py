"""Shared pytest fixtures."""

import pytest

try:
    from hubserver import HubServer
except ImportError:  # tests/ imported as a package
    from tests.hubserver import HubServer


@pytest.fixture
def hub_server(tmp_path_factory):
    """A Hub-protocol server on 127.0.0.1 (random free port), shut down after the test.

    It accepts one token with the "write" role and one with the "read" role:
    `hub_server.token("write")`, `hub_server.token("read")`.
    """
    server = HubServer(tmp_path_factory.mktemp("hub"),
                       {"hf_test_write_token": "write", "hf_test_read_token": "read"})
    try:
        yield server
    finally:
        server.close()
