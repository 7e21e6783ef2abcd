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

    check_no_repeated_flags(argv, cls)
    check_no_empty_paths(cls, argv)
    _reflow_field_docstrings()
    with _one_line_value_errors(cls, prog, argv):
        return tyro.cli(cls, args=argv, prog=prog, description=description, default=default)


def _reflow_field_docstrings() -> None:
    """Hand tyro each field docstring as paragraphs of one line. tyro joins a docstring's lines only where a line
    starts with a letter, and looks before it dedents: every continuation line of an indented field docstring
    starts with a space, so --help broke each help where the source line ended (`(0: one per` / `core, capped by
    memory)`). (tyro's docstring reader is private: where it is not found, the help stays as tyro draws it.)"""
    import inspect
    import re

    from tyro import _docstrings

    parse = getattr(_docstrings, "parse_docstring_from_object", None)
    if parse is None or getattr(parse, "reflowed", False):
        return

    def reflowed(obj) -> dict[str, str]:
        return {name: re.sub(r"(?<!\n)\n(?!\n)", " ", inspect.cleandoc(text)) for name, text in parse(obj).items()}

    reflowed.reflowed = True
    _docstrings.parse_docstring_from_object = reflowed


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


def check_no_repeated_flags(argv: list[str], cls: type | None = None) -> None:
    """ValueError for a field given twice. tyro (like argparse) would keep the last one only, so
    `--policy a --policy b` would silently evaluate b alone; a list flag takes all its values after one flag.
    tyro reads `--num_objects` as `--num-objects` and `--no-alone` as the other value of `--alone`: each spelling
    is one field's."""
    fields = _flag_types(cls)
    seen: dict[str, str] = {}  # field's flag -> the flag as first given
    for arg in argv:
        if arg == "--":
            break
        if arg.startswith("--"):
            flag = arg.split("=", 1)[0]
            key = _field_flag(flag, fields)
            if key in seen:
                spelled = f" (as {seen[key]} and {flag})" if seen[key] != flag else ""
                hint = f"give a list's values after one {key} (e.g. {key} A B)" if fields.get(key) else "give it once"
                raise ValueError(f"{key} is given twice{spelled}; {hint}")
            seen[key] = flag


def _field_flag(flag: str, fields: dict[str, bool]) -> str:
    """The flag of the field `flag` sets: `--num_objects` -> `--num-objects`, `--no-alone` -> `--alone`
    (`--train.no-foo` -> `--train.foo`)."""
    flag = "--" + flag[2:].replace("_", "-")
    prefix, _, name = flag[2:].rpartition(".")
    prefix = f"--{prefix}." if prefix else "--"
    if name.startswith("no-") and flag not in fields and (not fields or prefix + name[3:] in fields):
        return prefix + name[3:]
    return flag


def _flag_types(cls: type | None, prefix: str = "--") -> dict[str, bool]:
    """Every flag of dataclass `cls` as tyro names it (nested dataclasses' `--train.policy-type`, or `--regimes`
    where tyro.conf.arg(name="") drops the prefix) -> whether it takes a list of values."""
    import dataclasses
    import typing

    import tyro

    if cls is None or not dataclasses.is_dataclass(cls):
        return {}
    try:
        hints = typing.get_type_hints(cls, include_extras=True)
    except Exception:  # a hint that does not resolve here: no field known, every flag checked as spelled
        return {}
    arg_config = type(tyro.conf.arg())
    out: dict[str, bool] = {}
    for f in dataclasses.fields(cls):
        hint, name = hints[f.name], f.name
        if typing.get_origin(hint) is typing.Annotated:
            renamed = [m.name for m in hint.__metadata__ if isinstance(m, arg_config) and m.name is not None]
            hint, name = typing.get_args(hint)[0], renamed[-1] if renamed else name
        flag = prefix + name.replace("_", "-")
        kinds = [hint, *typing.get_args(hint)]
        nested = next((t for t in kinds if dataclasses.is_dataclass(t)), None)
        if nested is not None:
            out.update(_flag_types(nested, flag + "." if name else prefix))
        else:
            out[flag] = any(typing.get_origin(t) in (list, tuple, set, frozenset) or t in (list, tuple, set)
                            for t in kinds)
    return out


def _positionals(cls: type | None) -> dict[str, str]:
    """`--name` -> NAME (as the usage line spells it) for each positional field of dataclass `cls`."""
    import dataclasses
    import typing

    import tyro

    if cls is None or not dataclasses.is_dataclass(cls):
        return {}
    try:
        hints = typing.get_type_hints(cls, include_extras=True)
    except Exception:  # as _flag_types
        return {}
    marker, arg_config = typing.get_args(tyro.conf.Positional[int])[1], type(tyro.conf.arg())
    out = {}
    for f in dataclasses.fields(cls):
        meta = getattr(hints[f.name], "__metadata__", ())
        if marker in meta:
            metavars = [m.metavar for m in meta if isinstance(m, arg_config) and m.metavar]
            out["--" + f.name.replace("_", "-")] = metavars[-1] if metavars else f.name.upper()
    return out


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
def _one_line_value_errors(cls: type | None = None, prog: str = "", argv: list[str] | None = None):
    """A config's __post_init__ rejects bad values with a ValueError that names what is allowed; tyro would draw
    it, an unknown flag or a flag without its value in a box of 9 lines or more. Hand each back as a ValueError so
    main() prints it on one line, like every other bad input. (tyro's parse-error hook is marked experimental:
    without it, or for an event it does not name here, tyro's own box still says the same, exit 2.)"""
    import tyro

    errors = getattr(tyro, "_errors", None)
    hook = getattr(errors, "on_parse_error", None)
    if hook is None:
        yield
        return
    help_hint = f"`{prog} --help` lists the flags" if prog else "--help lists the flags"

    def flag_of(arg) -> str:
        names = getattr(getattr(arg, "lowered", None), "name_or_flags", None)
        return "/".join(names) if names else ""

    def handle(event):
        if isinstance(event, getattr(errors, "InstantiationFailure", ())):
            flag = flag_of(event.argument) if event.argument is not None else ""
            metavar = getattr(getattr(event.argument, "lowered", None), "metavar", None)
            given = _values_of(flag, argv or [])
            if flag.startswith("--") and metavar and given is not None:  # int('1.5')'s words name no flag's type
                # tyro's `{None}|INT` of an optional field: the flag takes the INT ("None" too, which it read)
                metavar = metavar.removeprefix("{None}|").removeprefix("{").removesuffix("}")
                raise ValueError(f"{flag} takes {metavar}, got {given!r}")
            # tyro's own failures go on with a list of the types it tried: their first line says it
            message = next((line.strip() for line in str(event.message).splitlines() if line.strip()), "bad value")
            raise ValueError(f"{flag}: {message}" if flag else message)
        if isinstance(event, getattr(errors, "UnrecognizedArgs", ())):
            raise ValueError(_unrecognized(list(event.tokens), cls, help_hint))
        if isinstance(event, getattr(errors, "BadValue", ())):
            flag = flag_of(event.argument) or "a flag"
            unknown = _unknown_flags(argv or [], cls)
            if not flag.startswith("-") and unknown:  # tyro reports a positional left empty before a flag it
                raise ValueError(_unrecognized(unknown, cls, help_hint))  # does not know: the unknown flag is news
            if event.offending_value is None:
                raise ValueError(f"{flag} needs a value; {help_hint}")
            raise ValueError(f"{flag} takes no value, got {event.offending_value!r}; {help_hint}")
        if isinstance(event, getattr(errors, "InvalidChoice", ())):
            raise ValueError(f"{flag_of(event.argument) or 'a flag'}: {event.value!r} is not allowed; allowed: "
                             f"{', '.join(event.choices)}")
        if isinstance(event, getattr(errors, "MissingArgs", ())):
            if event.unrecognized_tokens:  # a misspelt required flag is both: its spelling is the news
                raise ValueError(_unrecognized(list(event.unrecognized_tokens), cls, help_hint))
            names = [flag_of(a.arg) or a.arg.display_name() for a in event.missing_arguments]
            usage = _positionals(cls)  # positionals as the usage line spells them
            names = [n if n.startswith("-") else usage.get("--" + n.replace("_", "-"), n.upper().replace("-", "_"))
                     for n in names]
            names += [f for f in _required_on_command_line(cls) if f not in names and _values_of(f, argv or []) is None]
            raise ValueError(f"missing {', '.join(names)}; {help_hint}")

    with hook(handle):
        yield


def _required_on_command_line(cls: type | None) -> list[str]:
    """The flags of `cls` required on the command line though their fields have a default (REQUIRED_ON_COMMAND_LINE:
    a grid or a study fills them in): named with the flags tyro finds missing, so that one run names them all."""
    return ["--" + name.replace("_", "-") for name in getattr(cls, "REQUIRED_ON_COMMAND_LINE", ())]


def _unrecognized(tokens: list[str], cls: type | None, help_hint: str) -> str:
    """One line for tokens tyro did not recognize: the first unknown flag and the field nearest its spelling
    (`--polcy` -> `--policy`), or the stray value."""
    import difflib

    flags = [t for t in tokens if t.startswith("-")]
    if not flags:
        return f"unexpected argument {tokens[0]!r} (a value must follow its flag); {help_hint}"
    flag = flags[0].split("=", 1)[0]
    positionals = _positionals(cls)
    if _field_flag(flag, {}) in positionals:
        return f"{positionals[_field_flag(flag, {})]} is given without a flag, not as {flag}; {help_hint}"
    known = [f for f in _flag_types(cls) if f not in positionals]
    near = difflib.get_close_matches(_field_flag(flag, {}) if flag.startswith("--") else flag, known, n=1,
                                     cutoff=0.7)  # 0.6 offered --robot-mesh for --probe
    more = f" (and {len(flags) - 1} more)" if len(flags) > 1 else ""
    return f"unknown flag {flag}{more}" + (f" (did you mean {near[0]}?)" if near else "") + f"; {help_hint}"


def _unknown_flags(argv: list[str], cls: type | None) -> list[str]:
    """The flags in `argv` (before `--`) that name no field of `cls`; none where its fields cannot be read."""
    known = _flag_types(cls)
    if not known:
        return []
    flags = [a for a in argv[:argv.index("--") if "--" in argv else len(argv)] if a.startswith("--")]
    return [a for a in flags if _field_flag(a.split("=", 1)[0], known) not in known
            or _field_flag(a.split("=", 1)[0], known) in _positionals(cls)]


def _values_of(flag: str, argv: list[str]) -> str | None:
    """What `argv` gives `flag` (`--flag=v`, or the words after `--flag` up to the next flag), space-joined."""
    for i, arg in enumerate(argv):
        if arg == "--":
            break
        if arg.startswith(flag + "="):
            return arg.split("=", 1)[1]
        if arg == flag:
            rest = argv[i + 1:]
            n = next((j for j, a in enumerate(rest) if a.startswith("--")), len(rest))
            return " ".join(rest[:n])
    return None
