import os

import pytest

# Offline by construction: no hub, no asset prompt, no wandb.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
os.environ.setdefault("MS_SKIP_ASSET_DOWNLOAD_PROMPT", "1")
os.environ.setdefault("WANDB_MODE", "disabled")


@pytest.fixture(autouse=True)
def _root_logging_restored():
    """The root logger's handlers and level as before each test. LeRobot's training loop (init_logging) gives the
    root logger a handler on the sys.stderr of the moment, a test's captured stream, closed once that test ends: a
    later test's LeRobot warning then wrote a 'Logging error' traceback into the stderr it reads."""
    import logging

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


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


@pytest.fixture
def refused(capsys):
    """refused(cases, *paths): each `vla-ladder` argv of (argv, message) pairs exits 2 with one line on stderr holding
    `message`, and none of `paths` (what the commands would have written) exists afterwards."""
    from vla_ladder.cli import main

    def check(cases, *paths):
        for argv, message in cases:
            assert main(argv) == 2, argv
            err = capsys.readouterr().err
            assert message in err and len(err.strip().splitlines()) == 1, err
        for path in paths:
            assert not path.exists(), f"{path} was written"
    return check
