"""One small module per pipeline step.

Each module exposes ``add_arguments(parser)`` and ``run(args) -> None``: it parses arguments,
reads inputs, calls the core and writes outputs atomically. ``seathru.cli`` lists the modules
that exist; a step that is not built yet is simply absent.
"""

STEP_ORDER = ("simulate", "ingest", "poses", "export", "train", "render", "evaluate", "report")
