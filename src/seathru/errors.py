"""User-facing errors.

A ``PipelineError`` carries a message meant for the person running the pipeline: it names the
file or field at fault and says what to do. The CLI prints it without a traceback and exits 2.
"""


class PipelineError(Exception):
    """An error caused by the user's input or configuration, with an actionable message."""
