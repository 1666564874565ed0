"""The ``clsas`` command: one module per subcommand, each with ``add_parser(sub)``.

Adding a command is one new module here and one line in :data:`COMMANDS`. The choices a command
offers (formations, sparse methods, compressions, importers, backends) are read from the
libraries' registries, not typed again here. A package of the user's own registers its
algorithms when imported; to have the command line import it, name the module under the entry-point
group ``clsas.plugins`` in that package's pyproject.toml::

    [project.entry-points."clsas.plugins"]
    my_formation = "my_package.my_formation"
"""

from __future__ import annotations

import argparse
import contextvars
import importlib
import logging
import sys
from importlib.metadata import entry_points

from . import (
    acquire,
    autofocus,
    bench,
    calibrate,
    compare,
    demo,
    devices,
    export,
    importing,
    inspecting,
    limits,
    preprocess,
    reconstruct,
    simulate,
)
from .common import WRITERS, check_device_request, check_input_files, check_method_dependencies, check_output_files

__all__ = ["COMMANDS", "EXIT_BAD_INPUT", "EXIT_FAILURE", "EXIT_OK", "EXIT_RESUMABLE", "PLUGIN_GROUP", "build_parser",
           "load_plugins", "main"]

log = logging.getLogger("clsas.cli")

#: the entry-point group whose modules the command line imports (they register their algorithms)
PLUGIN_GROUP = "clsas.plugins"

# the subcommands in the order ``clsas --help`` lists them
COMMANDS = (demo, simulate, reconstruct, autofocus, preprocess, limits, compare, devices, acquire, importing,
            inspecting, export, calibrate, bench)


#: the exit codes of every command (docs/guide/command-line.md: "Exit codes")
EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_RESUMABLE = 0, 1, 2, 3
#: what the user can fix in the command line, the files or the settings: exit 2
BAD_INPUT = (ValueError, TypeError, FileNotFoundError, FileExistsError, IsADirectoryError)
#: what every command takes, before or after its name
_COMMON = ("quiet", "verbose", "debug")


class _Once(logging.Filter):
    """Pass each distinct warning once per process (info and debug lines always)."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[tuple[str, str]] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        key = (record.name, record.getMessage())
        if key in self.seen:
            return False
        self.seen.add(key)
        return True


def load_plugins() -> list[str]:
    """Import every module named under the entry-point group :data:`PLUGIN_GROUP`; a module that
    fails to import is skipped with a warning naming it. Returns the modules imported."""
    loaded = []
    for ep in entry_points(group=PLUGIN_GROUP):
        try:
            importlib.import_module(ep.value.split(":")[0])
        except Exception as exc:  # noqa: BLE001 - a broken plug-in must not take the command line down
            log.warning("plug-in %s (%s) not loaded: %s: %s", ep.name, ep.value, type(exc).__name__, exc)
        else:
            loaded.append(ep.value)
    return loaded


def build_parser() -> argparse.ArgumentParser:
    load_plugins()
    p = argparse.ArgumentParser(prog="clsas", description="In-air synthetic-aperture audio imaging",
                                epilog="exit status: 0 done, 1 failed, 2 bad input (the message says what to fix), "
                                "3 scan interrupted (resume it with --resume)")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.add_argument("-v", "--verbose", action="store_true", help="log what is computed")
    sub = p.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    for name in WRITERS:
        sub.choices[name].add_argument("--overwrite", action="store_true",
                                       help="replace the files it writes where they exist (else it refuses)")
    for sp in sub.choices.values():
        opts = sp._option_string_actions
        sp.add_argument("--debug", action="store_true", help="show tracebacks")
        if "-q" not in opts:
            sp.add_argument("-q", "--quiet", action="store_true", help="no progress output")
        if "-v" not in opts:
            sp.add_argument("-v", "--verbose", action="store_true", help="log what is computed")
        for action in sp._actions:  # given before the command's name, a flag is not reset after it
            if action.dest in _COMMON:
                action.default = argparse.SUPPRESS
    return p


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns its exit status (0 done, 1 failed, 2 bad input, 3 scan interrupted)."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    # a warning repeated word for word is said once per command (one filter per handler)
    filters = [(handler, _Once()) for handler in logging.getLogger().handlers]
    for handler, once in filters:
        handler.addFilter(once)
    try:
        # each command in a context of its own: what a command records there (the grids it checked)
        # ends with it
        return contextvars.copy_context().run(_run, args)
    finally:
        for handler, once in filters:
            handler.removeFilter(once)


def _run(args) -> int:
    from clsas.rig.grbl_link import StageRefused

    if not args.quiet:
        # the first run on a machine checks each kernel variant in a child process: say so
        logging.getLogger("clsas.cl.variants").setLevel(logging.INFO)
    try:
        check_input_files(args)  # every guard on the command line runs before any work
        check_output_files(args)
        check_device_request(args)
        check_method_dependencies(getattr(args, "method", None))
        return args.func(args)
    except KeyboardInterrupt:
        print("clsas: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the CLI turns every error into one line
        if args.debug:
            raise
        print(f"clsas {args.command}: error: {exc}".splitlines()[0], file=sys.stderr)
        return EXIT_BAD_INPUT if isinstance(exc, (*BAD_INPUT, StageRefused)) else EXIT_FAILURE
