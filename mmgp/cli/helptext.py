"""How ``--help`` shows the options of every command: flags as flags (no ``<bool>``), arguments
as ``LOGS...``, and each option's default, a setting's read from the shipped ``default.yaml``.

typer prints a ``<type>`` after every option, flags included, ``{logs}...`` for a required
argument, and no default where the option's own default is None, which for a setting means
"from --config, else the shipped default". :class:`App` builds every command and group with
:class:`Command` / :class:`Group`, whose parameters render as below; nothing else changes
(parsing is typer's own).
"""
from __future__ import annotations

import functools

import typer
from typer.core import TyperArgument, TyperCommand, TyperGroup, TyperOption


@functools.lru_cache(maxsize=None)
def shipped_defaults() -> dict:
    """The sections of the shipped ``default.yaml`` (read once, when help is shown)."""
    from ..config import read_sections
    from ..resources import config_file

    return read_sections(config_file("default"))


class ConfigDefault:
    """An option's ``show_default`` for a setting whose option defaults to None (the value then
    comes from ``--config``, else the shipped default): help shows ``section.key`` of the shipped
    ``default.yaml`` (nothing when that is null: the help text says what null means)."""

    def __init__(self, section: str, key: str):
        self.section, self.key = section, key

    def value(self):
        return shipped_defaults()[self.section][self.key]

    def __repr__(self) -> str:
        return f"ConfigDefault({self.section!r}, {self.key!r})"


class _Option(TyperOption):
    def display_type_rich(self, ctx):
        return None if self.is_flag or self.count else super().display_type_rich(ctx)

    def _extract_default_help_str(self, *, ctx):
        if isinstance(self.show_default, ConfigDefault):
            return self.show_default.value()
        return super()._extract_default_help_str(ctx=ctx)

    def _get_default_string(self, *, ctx, show_default_is_str, default_value) -> str:
        if isinstance(self.show_default, ConfigDefault) and self.is_bool_flag and self.secondary_opts:
            return (self.opts if default_value else self.secondary_opts)[0].lstrip("-")
        return super()._get_default_string(ctx=ctx, show_default_is_str=show_default_is_str,
                                           default_value=default_value)


class _Argument(TyperArgument):
    @property
    def display_name_raw(self) -> str:
        return (self.metavar or self.name).upper()

    def _rich_display_name(self) -> str:
        return self.display_name_raw + ("..." if self.nargs != 1 else "")

    def _usage_display_name(self) -> str:
        name = self._rich_display_name()
        return name if self.required else f"[{name}]"


def _shaped(params: list) -> list:
    for p in params:
        if type(p) is TyperOption:
            p.__class__ = _Option
        elif type(p) is TyperArgument:
            p.__class__ = _Argument
    return params


class Command(TyperCommand):
    def get_params(self, ctx):
        return _shaped(super().get_params(ctx))


class Group(TyperGroup):
    def get_params(self, ctx):
        return _shaped(super().get_params(ctx))


class App(typer.Typer):
    """A typer app whose groups and commands show their options as the module docstring says."""

    def __init__(self, **kwargs):
        super().__init__(cls=kwargs.pop("cls", Group), **kwargs)

    def command(self, *args, cls=None, **kwargs):
        return super().command(*args, cls=cls or Command, **kwargs)


def setting_option(section: str, key: str, *decls: str, help: str, **kwargs):
    """An option for setting ``key`` of ``section``: None unless given (then ``--config`` or the
    shipped default decides), its help showing the shipped default."""
    return typer.Option(None, *decls, help=help, show_default=ConfigDefault(section, key), **kwargs)
