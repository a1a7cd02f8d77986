"""The one exception type that reaches the user as a one-line ``Error: ...``."""


class CondtrackError(Exception):
    """Bad input or configuration: the message names the file, key or frame.

    The command line prints ``Error: <message>`` on stderr and exits non-zero,
    without a traceback and without leaving a partial output file.
    """
