"""A picture never costs the numbers it shows: every picture of the library (an evaluation's, a
training run's, a benchmark's) is drawn through ``draw_safely``, which turns a failure into a
warning naming the file, with no half-written file and no figure left open.

Importing this module imports no matplotlib (a failure closes the figures through pyplot, which
the drawing has loaded by then).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["draw_safely", "picture_warning"]


def picture_warning(name: str, error: BaseException) -> str:
    """The warning a job shows when the picture ``name`` failed: the file and why."""
    why = str(error).strip().splitlines()[0] if str(error).strip() else ""
    return f"{name} was not drawn: {type(error).__name__}{': ' + why if why else ''}"


def draw_safely(path: str | Path, draw: Callable[[Path], Any]) -> str | None:
    """``draw(path)``; None when it drew, else its warning (``picture_warning``), the figures
    closed and the file removed."""
    path = Path(path)
    try:
        draw(path)
    except Exception as e:  # a picture never fails what computed its numbers
        import matplotlib.pyplot as plt

        plt.close("all")
        path.unlink(missing_ok=True)
        return picture_warning(path.name, e)
    return None
