"""The optimisation-history figure shared by :mod:`gmjax.tune` and :mod:`gmjax.fitting`."""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np


def plot_curves(
    loss: np.ndarray,
    series: Mapping[str, np.ndarray],
    path: str | None = None,
    *,
    title: str | None = None,
    loss_title: str = "loss",
    label_y: bool = False,
) -> Any:
    """One panel for ``loss (S,)`` and one per ``series`` entry ``(S, ...)``, against the step
    (matplotlib, imported lazily); saved to ``path`` (PNG) when given. Returns the ``Figure``."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 1 + len(series), figsize=(4 * (1 + len(series)), 3.2), squeeze=False)
    steps = np.arange(1, len(loss) + 1)
    axes[0, 0].plot(steps, loss, marker=".")
    axes[0, 0].set(xlabel="step", ylabel="loss", title=loss_title)
    for ax, (name, values) in zip(axes[0, 1:], series.items()):
        ax.plot(steps, np.asarray(values).reshape(len(steps), -1), marker=".")
        ax.set(xlabel="step", title=name, **({"ylabel": name} if label_y else {}))
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=90)
    return fig
