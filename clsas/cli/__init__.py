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
import importlib
import logging
import sys
from importlib.metadata import entry_points

from . import (
    acquire,
    autofocus,
    bench,
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

__all__ = ["COMMANDS", "PLUGIN_GROUP", "build_parser", "load_plugins", "main"]

log = logging.getLogger("clsas.cli")

#: the entry-point group whose modules the command line imports (they register their algorithms)
PLUGIN_GROUP = "clsas.plugins"

# the subcommands in the order ``clsas --help`` lists them
COMMANDS = (demo, simulate, reconstruct, autofocus, preprocess, limits, compare, devices, acquire, importing,
            inspecting, export, bench)


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
    p = argparse.ArgumentParser(prog="clsas", description="In-air synthetic-aperture audio imaging")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = p.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    for sp in sub.choices.values():  # what every command takes, before or after its name
        opts = sp._option_string_actions
        sp.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks")
        if "-q" not in opts:
            sp.add_argument("-q", "--quiet", action="store_true", help="no progress output")
        if "-v" not in opts:
            sp.add_argument("-v", "--verbose", action="store_true", help="log what is computed")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.debug = getattr(args, "debug", False)
    logging.basicConfig(level=logging.INFO if getattr(args, "verbose", False) else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "quiet", False):
        # the first run on a machine checks each kernel variant in a child process: say so
        logging.getLogger("clsas.cl.variants").setLevel(logging.INFO)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print("clsas: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the CLI turns every error into one line
        if args.debug:
            raise
        print(f"clsas {args.command}: error: {exc}".splitlines()[0], file=sys.stderr)
        return 2 if isinstance(exc, ValueError | TypeError | FileNotFoundError) else 1
