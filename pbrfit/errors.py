"""The one error type that reaches users: a bad input, named."""

__all__ = ["CaptureError", "listed", "first_line"]


class CaptureError(ValueError):
    """A problem with user input (a capture, a material folder, an option).

    The message is one line that names the file or key and says what is wrong; the CLI prints
    it as ``pbrfit: error: <message>`` and exits with status 2.
    """


def listed(items, most: int = 3) -> str:
    """The first ``most`` of ``items`` for a one-line message: ``a, b, c and 4 more``."""
    items = [str(item) for item in items]
    return ", ".join(items[:most]) + (f" and {len(items) - most} more" if len(items) > most else "")


def first_line(message: str) -> str:
    """The first line of ``message`` that is not blank, stripped (a library's error, or XLA's, in
    a one-line message); "unknown error" where there is none."""
    lines = [ln.strip() for ln in str(message).splitlines() if ln.strip()]
    return lines[0] if lines else "unknown error"
