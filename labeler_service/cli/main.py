"""``mocap-labeler``: one console script, one module per command, imported only when run.

Each command module defines ``add_arguments(parser)`` and ``run(args) -> int``. A command may
be a group (``train structure``, ``bench latency``): a nested table below. Heavy imports (numba,
matplotlib) belong inside ``run`` so ``--help`` and ``info`` stay instant. A
:class:`~labeler_service.errors.MocapError` ends the command with its message and exit code 2,
never a traceback; so does a ``MemoryError`` (the commands refuse the sizes they know of first).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence
from typing import Any

from labeler_service import __version__
from labeler_service.errors import MocapError

# name -> (module, one-line help) or name -> (group help, {sub: (module, help)})
Command = tuple[str, str]
COMMANDS: dict[str, Command | tuple[str, dict[str, Command]]] = {
    "demo": ("labeler_service.cli.demo", "the whole pipeline on a composed scene"),
    "serve": ("labeler_service.cli.serve", "the streaming labeling service (UDP/MQTT)"),
    "replay": ("labeler_service.cli.replay_capture", "stream a capture unlabeled to the service"),
    "subscribe": ("labeler_service.cli.subscribe_stream", "receive labeled frames, summarise"),
    "view": ("labeler_service.cli.view", "live 3D view of the labeled stream in a browser"),
    "label": (
        "labeler_service.cli.label",
        "batch-label a capture with the online labeler (Yu, Li and Deng 2007)",
    ),
    "info": ("labeler_service.cli.info", "summary of a capture file"),
    "compose": ("labeler_service.cli.compose_scene", "multi-person scene from single takes"),
    "simulate": ("labeler_service.cli.simulate_scene", "simulated multi-person scene"),
    "simulate-shoulder": (
        "offline.shoulder.simulate_cli",
        "synthetic dense shoulder capture with ground truth",
    ),
    "evaluate": ("labeler_service.cli.evaluate", "score labelers on a labeled capture"),
    "bench": (
        "benchmarks through real transports",
        {"latency": ("labeler_service.cli.bench_latency", "end-to-end latency")},
    ),
    "train": (
        "offline training",
        {
            "structure": ("offline.structure_cli", "subject templates from labeled captures"),
            "shoulder": (
                "offline.shoulder.cli",
                "data-driven shoulder skeleton (Hong, Park and Hodgins 2009)",
            ),
        },
    ),
}


class _Defaults(argparse.HelpFormatter):
    """``--help`` that says every option's default (argparse's ``ArgumentDefaultsHelpFormatter``,
    except where the help says it already, ``default ...`` or a closing ``[value]``, or there is
    none to say: no value, a flag off, an empty list)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        d = action.default
        if (
            not action.option_strings
            or d is None
            or d is False
            or d is argparse.SUPPRESS
            or (isinstance(d, list | tuple) and not d)
            or "default" in text
            or text.rstrip().endswith("]")
        ):
            return text
        return f"{text} (default: %(default)s)"


def _add(sub: argparse._SubParsersAction, name: str, entry: Any, argv: Sequence[str]) -> None:
    """Adds one (possibly nested) command; imports its module only if ``argv`` selects it."""
    selected = bool(argv) and argv[0] == name
    if isinstance(entry[1], dict):
        group_help, children = entry
        p = sub.add_parser(name, help=group_help, description=group_help, formatter_class=_Defaults)
        inner = p.add_subparsers(dest=f"{name}_command", metavar="COMMAND", required=True)
        for child, child_entry in children.items():
            _add(inner, child, child_entry, argv[1:] if selected else ())
        return
    module_name, help_text = entry
    p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=_Defaults)
    if selected:
        module = importlib.import_module(module_name)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)


def build_parser(argv: Sequence[str] = ()) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mocap-labeler",
        description="Real-time labeling of optical motion-capture markers.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, entry in COMMANDS.items():
        _add(sub, name, entry, argv)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args_list = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(args_list)
    args = parser.parse_args(args_list)
    try:
        code = int(args._run(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, inside the handler below
        return code
    except BrokenPipeError:
        # the reader went away (``| head``): stop quietly; stdout to devnull so the flush at
        # interpreter exit does not raise again (Python docs, "Note on SIGPIPE")
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except MocapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except MemoryError as exc:  # numpy says what it could not allocate: one line, no traceback
        print(
            f"error: out of memory: {str(exc) or 'an allocation failed'} (ask for less: fewer "
            "frames, a frame range FILE:start:stop)",
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
