"""The one exception type the command line turns into a clean message."""


class LatentForceError(Exception):
    """A problem with the user's input (file, config key, column or value).

    The message is one paragraph that names the file, key, column or value
    at fault and says what would be accepted instead. The CLI prints it
    without a traceback and exits non-zero.
    """
