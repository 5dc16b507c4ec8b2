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
