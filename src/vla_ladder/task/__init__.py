"""GraspObject-v1: the ManiSkill3 task (env.py), its objects and the placement ladder (pure numpy)."""


def register() -> None:
    """Import the simulator-side module, which registers GraspObject-v1 with ManiSkill and gymnasium."""
    import vla_ladder.task.env  # noqa: F401
