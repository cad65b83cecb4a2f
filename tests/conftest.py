"""Test session settings and fixtures shared by every test module."""
import stages  # noqa: F401  (before any test imports torch: OMP_WAIT_POLICY, see stages/__init__.py)

from pathlib import Path

import pytest

from tests.factories.configs import REAL


def pytest_collection_modifyitems(items):
    """Every test that uses the `real` fixture carries the `real` marker (`-m "not real"` deselects them)."""
    for item in items:
        if "real" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.real)


@pytest.fixture
def real() -> Path:
    """The real captures beside the repository (../shared/real); the test skips when they are absent."""
    if not REAL.is_dir():
        pytest.skip(f"{REAL} not present (real captures beside the repository; a user's clone has none)")
    return REAL


@pytest.fixture
def one_thread():
    """torch on one thread during the test (tiny models: faster, and the same result on any machine)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(autouse=True)
def offline_hub(tmp_path_factory, monkeypatch) -> Path:
    """Tests never download: the Hugging Face Hub is offline (HF_HUB_OFFLINE, also for dag.py started by a test)
    and its cache an empty folder, whatever the machine has cached; `cached_depth_model` puts the default depth
    model there."""
    import huggingface_hub.constants as constants

    cache = tmp_path_factory.getbasetemp() / "hf_hub_empty"
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(cache))
    return cache


@pytest.fixture(scope="session")
def _tiny_default_depth_model(tmp_path_factory) -> Path:
    """A Hugging Face cache holding a tiny random model of the default depth model's architecture as its pinned
    snapshot (tests/factories/depth_models.py), built once per session."""
    from stages.lib.depth.models import DEFAULT_MODEL, DEPTH_MODELS
    from tests.factories.depth_models import fake_hub_cache

    cache = tmp_path_factory.getbasetemp() / "hf_hub_cached"
    fake_hub_cache(cache, DEPTH_MODELS[DEFAULT_MODEL])
    return cache


@pytest.fixture
def cached_depth_model(_tiny_default_depth_model, monkeypatch) -> Path:
    """The default depth model in the (offline) Hugging Face cache, as after its first download; returns the cache."""
    import huggingface_hub.constants as constants

    monkeypatch.setenv("HF_HUB_CACHE", str(_tiny_default_depth_model))
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(_tiny_default_depth_model))
    return _tiny_default_depth_model
