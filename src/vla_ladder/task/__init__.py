"""GraspObject-v1: the ManiSkill3 task, its objects and the placement ladder."""

from vla_ladder.task.layouts import REGIMES, SPLITS, Layout, sample_layout  # noqa: F401
from vla_ladder.task.objects import OBJECT_NAMES, OBJECTS  # noqa: F401

ENV_ID = "GraspObject-v1"


def register() -> None:
    """Import the simulator-side module, which registers GraspObject-v1 with ManiSkill and gymnasium."""
    import vla_ladder.task.env  # noqa: F401
