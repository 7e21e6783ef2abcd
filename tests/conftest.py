import os

import pytest

# Offline by construction: no hub, no asset prompt, no wandb.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
os.environ.setdefault("MS_SKIP_ASSET_DOWNLOAD_PROMPT", "1")
os.environ.setdefault("WANDB_MODE", "disabled")


@pytest.fixture(scope="session")
def make_env():
    """gym.make for GraspObject-v1 that closes every env it made at the end of the session."""
    import gymnasium as gym

    import vla_ladder.task.env  # noqa: F401  (registers the env)

    made = []

    def _make(**kwargs):
        env = gym.make("GraspObject-v1", **kwargs)
        made.append(env)
        return env

    yield _make
    for env in made:
        env.close()
