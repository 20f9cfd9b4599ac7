"""The language of the management commands' human output (`manage.py lifecycle`, add_robot,
add_gateway, create_api_token): the shell's, as for any command-line tool."""
from __future__ import annotations

import argparse
import os
from typing import Any

from django.conf import settings
from django.utils import translation

CLI_LANGUAGES = ("de", "en")


def cli_language() -> str:
    """The language of a management command's human output: $LIFECYCLE_LANGUAGE if set, else the
    shell's locale ($LC_ALL, $LC_MESSAGES, $LANG: the first one set, as gettext reads them), by its
    first two letters ("de_DE.UTF-8" gives "de"). Only "de" and "en" are taken; anything else (C,
    POSIX, fr_FR.UTF-8) gives settings.LANGUAGE_CODE.

    A command activates it around all it does (InCliLanguage): Django 5.2's BaseCommand leaves the
    active language alone (only a handle() decorated with @no_translations deactivates it), so
    nothing undoes it while the command runs, and translation.override restores the language
    that was active before once it is done (call_command in a test or another command)."""
    for name in ("LIFECYCLE_LANGUAGE", "LC_ALL", "LC_MESSAGES", "LANG"):
        value = os.environ.get(name, "").strip()
        if value:
            code = value[:2].lower()
            return code if code in CLI_LANGUAGES else settings.LANGUAGE_CODE
    return settings.LANGUAGE_CODE


class InCliLanguage:
    """A BaseCommand mixin (put it before BaseCommand): the command's help, argument errors, output
    and errors in cli_language(). ``help`` may be a lazy translation."""

    def run_from_argv(self, argv: list[str]) -> None:  # the command line: --help and argument errors too
        with translation.override(cli_language()):
            super().run_from_argv(argv)

    def print_help(self, prog_name: str, subcommand: str) -> None:  # manage.py help COMMAND
        with translation.override(cli_language()):
            super().print_help(prog_name, subcommand)

    def create_parser(self, prog_name: str, subcommand: str, **kwargs: Any) -> argparse.ArgumentParser:
        parser = super().create_parser(prog_name, subcommand, **kwargs)
        parser.description = str(self.help) if self.help else None  # (argparse takes text, not a lazy one)
        return parser

    def execute(self, *args: Any, **options: Any) -> Any:  # call_command too
        with translation.override(cli_language()):
            return super().execute(*args, **options)
