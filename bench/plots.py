"""Plot helpers: matplotlib (the ``bench`` extra) with the Agg backend, or None without it."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def pyplot() -> Any:
    """``matplotlib.pyplot`` on a file-only backend, or None when matplotlib is absent."""
    try:
        import matplotlib
    except ImportError:
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig: Any, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def cdf(ax: Any, samples: Sequence[float], label: str) -> None:
    """An empirical CDF of ``samples`` on ``ax``."""
    a = np.sort(np.asarray(samples, np.float64))
    if a.size:
        ax.step(a, np.arange(1, a.size + 1) / a.size, where="post", label=label)


def log_scale_if_positive(ax: Any, axis: str = "y") -> None:
    """Log scale on ``axis`` when the plotted data have a positive finite value (a log axis
    with none cannot be drawn)."""
    values: list[float] = []
    for line in ax.get_lines():
        data = line.get_ydata() if axis == "y" else line.get_xdata()
        values += [float(v) for v in np.asarray(data, np.float64).ravel()]
    for patch in ax.patches:
        values.append(float(patch.get_height() if axis == "y" else patch.get_width()))
    if any(np.isfinite(v) and v > 0 for v in values):
        (ax.set_yscale if axis == "y" else ax.set_xscale)("log")
