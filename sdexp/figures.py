"""Figures are files: every plot goes through :func:`pyplot`, the one place that picks
matplotlib's backend (Agg: no display needed, the same pixels on a laptop, a server and CI).
Callers import it where they plot, so a run that draws nothing never imports matplotlib."""
from __future__ import annotations


def pyplot():
    """matplotlib.pyplot on the Agg backend."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_figure(fig, path, dpi: int = 120) -> None:
    """``fig`` into ``path`` (its suffix: the format), written whole or not at all (a full disk
    mid-write leaves no truncated picture, sdexp.cache.atomic_write); the figure is closed."""
    from pathlib import Path

    from sdexp.files import atomic_write
    path = Path(path)
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png"))
    finally:
        pyplot().close(fig)
