"""The one error type that reaches users: a bad input, named."""

__all__ = ["CaptureError"]


class CaptureError(ValueError):
    """A problem with user input (a capture, a material folder, an option).

    The message is one line that names the file or key and says what is wrong; the CLI prints
    it as ``pbrfit: error: <message>`` and exits with status 2.
    """
