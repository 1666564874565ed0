"""Pictures for the CLI and examples: maximum-intensity projections in dB with metric axes.

Presentation only: the compute functions never plot. Uses matplotlib's Agg backend.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .imaging.image import Image


def mip_png(image: Image, path: str | Path, truth_m: np.ndarray | None = None, title: str = "",
            dynamic_range_db: float = 30.0) -> Path:
    """Write the three maximum-intensity projections of ``image`` (in dB) to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    g = image.grid
    db = image.db(-dynamic_range_db)
    views = [
        ("front view (x-y)", db.max(axis=2).T, g.x_m, g.y_m, (0, 1), "x (m)", "y (m)"),
        ("top view (x-z)", db.max(axis=1).T, g.x_m, g.z_m, (0, 2), "x (m)", "z, range (m)"),
        ("side view (z-y)", db.max(axis=0), g.z_m, g.y_m, (2, 1), "z, range (m)", "y (m)"),
    ]
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), constrained_layout=True)
    for ax, (name, img, ha, va, (i, j), xl, yl) in zip(axes, views, strict=True):
        def extent(a):
            d = a[1] - a[0] if len(a) > 1 else 0.01
            return (a[0] - d / 2, a[-1] + d / 2)

        im = ax.imshow(img, origin="lower", extent=(*extent(ha), *extent(va)), aspect="equal",
                       cmap="inferno", vmin=-dynamic_range_db, vmax=0)
        if truth_m is not None and len(truth_m):
            ax.plot(truth_m[:, i], truth_m[:, j], "c+", ms=7, mew=1.2, label="truth")
        ax.set(title=name, xlabel=xl, ylabel=yl)
    axes[0].legend(loc="lower right", fontsize=8) if truth_m is not None and len(truth_m) else None
    fig.colorbar(im, ax=axes, shrink=0.8, label="dB re peak")
    if title:
        fig.suptitle(title)
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
