"""Command lines from typed config dataclasses: one `--flag` per field, its help from the field's doc.

A field is declared with `option(default, doc, choices=..., required=...)`; `build_parser` turns the
dataclass into an argparse parser and `command_line` writes the command that reproduces a config.
"""

from __future__ import annotations

import argparse
import shlex
from dataclasses import MISSING, field, fields
from typing import Any

__all__ = ["HelpFormatter", "build_parser", "command_line", "option"]


class HelpFormatter(argparse.HelpFormatter):
    """Shows a flag's default once: not for required flags, empty defaults, or helps that already state it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "(default" in text or action.required or not action.option_strings or action.default in (None, "", argparse.SUPPRESS):
            return text
        return text + " (default: %(default)s)"


def option(default: Any, doc: str, **extra: Any) -> Any:
    """A dataclass field with its `--help` text (and argparse extras such as `choices` or `required`)."""
    return field(default=default, metadata={"help": doc, **extra})


def build_parser(cls: type, prog: str, description: str) -> argparse.ArgumentParser:
    """An argparse parser with one `--flag` per field of the dataclass `cls`; defaults shown once."""
    parser = argparse.ArgumentParser(prog=prog, description=description, formatter_class=HelpFormatter)
    for f in fields(cls):
        meta = f.metadata
        kwargs: dict[str, Any] = {"help": meta.get("help", ""), "dest": f.name}
        if f.type in ("bool", bool):
            kwargs["action"] = argparse.BooleanOptionalAction
            kwargs["default"] = f.default
        else:
            kwargs["type"] = {"int": int, "float": float, "str": str}[f.type if isinstance(f.type, str) else f.type.__name__]
            if meta.get("required"):
                kwargs["required"] = True
            elif f.default is not MISSING:
                kwargs["default"] = f.default
            if "choices" in meta:
                kwargs["choices"] = meta["choices"]
        parser.add_argument("--" + f.name.replace("_", "-"), **kwargs)
    return parser


def command_line(
    cls: type,
    prog: str,
    config: dict[str, Any],
    always: tuple[str, ...] = ("name",),
    skip: tuple[str, ...] = ("progress", "resume", "overwrite"),
) -> str:
    """The `prog` command that reproduces `config`: the flags whose values differ from the defaults (and `always`), none of `skip`."""
    parts = [prog]
    for f in fields(cls):
        if f.name not in config or f.name in skip:
            continue
        value = config[f.name]
        if value == f.default and f.name not in always:
            continue
        flag = "--" + f.name.replace("_", "-")
        if isinstance(value, bool):
            parts.append(flag if value else "--no-" + flag[2:])
        else:
            parts.append(f"{flag} {shlex.quote(str(value))}")
    return " ".join(parts)
