"""Shared fixtures: every test that takes ``device`` runs on the CPU, and on cuda:0 when present."""

import pytest
import warp as wp

wp.config.quiet = True
wp.init()

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return wp.get_device(request.param)
