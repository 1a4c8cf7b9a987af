"""The ``seathru`` command: one subcommand per pipeline step."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from seathru import __version__
from seathru.errors import PipelineError
from seathru.steps import STEP_ORDER


def _available_steps() -> dict:
    steps = {}
    for name in STEP_ORDER:
        try:
            steps[name] = importlib.import_module(f"seathru.steps.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"seathru.steps.{name}":
                raise
    return steps


def build_parser(steps: dict | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="seathru", description=__doc__)
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="step", required=True, metavar="STEP")
    for name, module in (_available_steps() if steps is None else steps).items():
        doc = (module.__doc__ or name).strip().splitlines()[0]
        step_parser = sub.add_parser(name, help=doc, description=module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(step_parser)
        step_parser.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None, only: str | None = None) -> int:
    """Run ``seathru STEP ...``. ``only`` imports that one step alone, for scripts on machines
    that lack another step's dependencies (a GPU node without pycolmap, say)."""
    if only is not None:
        argv = [only, *(sys.argv[1:] if argv is None else argv)]
    argv = sys.argv[1:] if argv is None else list(argv)
    # A step's run imports that step alone: every step's dependencies took seconds to load.
    named = next((word for word in argv if not word.startswith("-")), None)
    steps = {named: importlib.import_module(f"seathru.steps.{named}")} \
        if named in STEP_ORDER else None
    args = build_parser(steps).parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # One path for messages: log records go through tqdm.write while a progress bar is shown, so
    # bars and log lines never interleave and nothing is printed twice.
    from tqdm.contrib.logging import logging_redirect_tqdm

    try:
        with logging_redirect_tqdm():
            args._run(args)
    except PipelineError as exc:
        print(f"seathru {args.step}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
