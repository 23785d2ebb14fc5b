"""The one exception type the CLI turns into a one-line message and exit code 2."""


class UserError(Exception):
    """Bad input a user can fix: missing file, wrong schema, too few LEDs, degenerate geometry.

    The CLI prints ``robtraj: error: <message>`` and exits with code 2, never a traceback.
    """
