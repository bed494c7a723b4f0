"""The `softac` command: parses, calls, maps errors to exit codes (`main`), and the commands themselves.

`softac.cli.entry_point` and `softac.cli.main` stay importable here: console scripts written by an earlier
install call them by that name."""

from softac.cli.main import entry_point, main

__all__ = ["entry_point", "main"]
