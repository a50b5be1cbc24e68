"""The one way figures are made, for report pages and reproduction reports alike.

Figures are drawn on `matplotlib.figure.Figure` with the Agg canvas: no GUI backend, no global
pyplot state (reports run inside the service and the command line alike). They use
constrained layout and are saved with a tight bounding box, so no label is clipped, at
FIGURE_DPI, sharp on a high-resolution screen and in print.
"""

from __future__ import annotations

import base64
import io
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # matplotlib is imported when a figure is drawn, not at start-up
    from matplotlib.typing import RcKeyType

FIGURE_DPI = 150
FONT_SIZES: dict[RcKeyType, Any] = {
    "font.size": 9,
    "axes.titlesize": 9,
    "axes.labelsize": 9,
    "xtick.labelsize": 8,
    "ytick.labelsize": 8,
    "legend.fontsize": 8,
}


def new_figure(
    nrows: int = 1, ncols: int = 1, size: tuple[float, float] = (8.0, 5.0), *, squeeze: bool = True
) -> tuple[Any, Any]:
    """A figure and its axes: one Axes when squeeze and 1 x 1, else a 2-D array of them."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    with matplotlib.rc_context(FONT_SIZES):
        fig = Figure(figsize=size, layout="constrained")
        FigureCanvasAgg(fig)
        axes = fig.subplots(nrows, ncols, squeeze=False)
    if squeeze and nrows * ncols == 1:
        return fig, axes[0, 0]
    return fig, axes


def _save(fig: Any, target: Any, fmt: str) -> None:
    import matplotlib

    with matplotlib.rc_context(FONT_SIZES):
        fig.savefig(
            target,
            format=fmt,
            dpi=FIGURE_DPI,
            bbox_inches="tight",
            pad_inches=0.05,
            metadata={"Software": None},
        )


def save_figure(fig: Any, path: str | Path) -> None:
    """Write the figure as a PNG file (FIGURE_DPI, nothing clipped)."""
    _save(fig, path, "png")


def png_data_uri(fig: Any) -> str:
    """The figure as an inline PNG, for self-contained HTML pages."""
    buf = io.BytesIO()
    _save(fig, buf, "png")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")
