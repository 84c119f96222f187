"""The one exception type that the command line turns into a one-line message."""


class InputError(Exception):
    """Bad user input (missing/corrupt file, ids out of range, degenerate geometry...).

    The CLI prints ``error: <message>`` and exits with status 2, never a traceback.
    """
