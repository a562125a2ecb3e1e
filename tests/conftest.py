"""Shared fixtures: every test that takes ``device`` runs on the CPU, and on cuda:0 when present."""

import pytest
import warp as wp

wp.config.quiet = True
wp.init()

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return wp.get_device(request.param)


@pytest.fixture
def base_scene(tmp_path):
    """tests/robustness_cases.py's small valid scene, as ``base.toml`` in the test's folder."""
    from tests.robustness_cases import BASE  # noqa: PLC0415

    path = tmp_path / "base.toml"
    path.write_text(BASE)
    return path
