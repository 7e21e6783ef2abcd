"""A config dataclass from its command line: tyro parses the flags, __post_init__ validates, errors fit on one line.

Every command's config is a dataclass whose fields are its flags and whose field docstrings are the help.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import TypeVar

T = TypeVar("T")


def parse_config(cls: type[T], argv: list[str], prog: str, description: str | None = None,
                 default: T | None = None) -> T:
    """`cls` from `argv` (flags not given take their defaults, or `default`'s values); a value its __post_init__
    rejects raises ValueError with the message that names what is allowed."""
    import tyro

    check_no_repeated_flags(argv)
    check_no_empty_paths(cls, argv)
    with _one_line_value_errors():
        return tyro.cli(cls, args=argv, prog=prog, description=description, default=default)


def unchecked(cls: type[T], values: dict) -> T:
    """An instance of dataclass `cls` holding `values` (fields not in it take their defaults) without running its
    __post_init__: parse_config's `default` when the values were saved for another machine (a run resumed here),
    so that only the command line's result is validated, once the flags given have replaced them."""
    import dataclasses

    obj = object.__new__(cls)
    for f in dataclasses.fields(cls):
        if f.name in values:
            object.__setattr__(obj, f.name, values[f.name])
        elif f.default is not dataclasses.MISSING:
            object.__setattr__(obj, f.name, f.default)
        elif f.default_factory is not dataclasses.MISSING:
            object.__setattr__(obj, f.name, f.default_factory())
    return obj


def check_no_repeated_flags(argv: list[str]) -> None:
    """ValueError for a flag given twice. tyro (like argparse) would keep the last one only, so
    `--policy a --policy b` would silently evaluate b alone; a list flag takes all its values after one flag."""
    seen = set()
    for arg in argv:
        if arg == "--":
            break
        if arg.startswith("--"):
            flag = arg.split("=", 1)[0]
            if flag in seen:
                raise ValueError(f"{flag} is given twice; give a list's values after one {flag} (e.g. {flag} A B)")
            seen.add(flag)


def check_no_empty_paths(cls: type, argv: list[str]) -> None:
    """ValueError for a path flag given an empty value (`--out ""`, an unset shell variable): tyro reads it as
    Path(""), which is ".", so results would land in the current directory."""
    import dataclasses
    import pathlib
    import typing

    if not dataclasses.is_dataclass(cls):
        return
    hints = typing.get_type_hints(cls, include_extras=False)
    paths = {"--" + f.name.replace("_", "-") for f in dataclasses.fields(cls)
             if pathlib.Path in (hints[f.name], *typing.get_args(hints[f.name]))}
    for i, arg in enumerate(argv):
        if arg == "--":
            break
        flag, eq, value = arg.partition("=")
        if flag in paths and ((eq and not value.strip()) or (not eq and i + 1 < len(argv) and not argv[i + 1].strip())):
            raise ValueError(f"{flag} is empty; give a path (an empty one would mean the current directory)")


@contextmanager
def _one_line_value_errors():
    """A config's __post_init__ rejects bad values with a ValueError that names what is allowed; tyro would draw
    it in a box. Hand it back as a ValueError so main() prints it on one line, like every other bad input.
    (tyro's parse-error hook is marked experimental: without it, tyro's own box still says the same, exit 2.)"""
    import tyro

    errors = getattr(tyro, "_errors", None)
    hook = getattr(errors, "on_parse_error", None)
    if hook is None:
        yield
        return

    def handle(event):
        if isinstance(event, errors.InstantiationFailure):
            arg = event.argument
            flag = "/".join(arg.lowered.name_or_flags) if arg is not None and arg.lowered.name_or_flags else ""
            # tyro's own failures go on with a list of the types it tried: their first line says it
            message = next((line.strip() for line in str(event.message).splitlines() if line.strip()), "bad value")
            raise ValueError(f"{flag}: {message}" if flag else message)

    with hook(handle):
        yield
