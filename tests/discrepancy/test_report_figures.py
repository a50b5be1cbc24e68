"""Report figures come from one helper and are sharp: at least 150 dpi, with the page's figures
several times wider than a 72-dpi rendering of the same size would be."""

from __future__ import annotations

import base64
import re
import struct
from pathlib import Path

from service.cli import main
from service.io.figures import FIGURE_DPI, new_figure, save_figure


def _png_size_and_dpi(data: bytes) -> tuple[int, int, float]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", data[16:24])
    i = data.find(b"pHYs")
    ppm_x = struct.unpack(">I", data[i + 4 : i + 8])[0]
    return width, height, ppm_x * 0.0254


def test_the_helper_saves_at_150_dpi_or_more(tmp_path: Path) -> None:
    fig, ax = new_figure(1, 1, (4.0, 3.0))
    ax.plot([0, 1], [0, 1])
    ax.set_ylabel("a long label that a tight layout must keep inside the picture [arcsec]")
    save_figure(fig, tmp_path / "f.png")
    width, height, dpi = _png_size_and_dpi((tmp_path / "f.png").read_bytes())
    assert FIGURE_DPI >= 150 and round(dpi) == FIGURE_DPI
    assert width >= 3.0 * FIGURE_DPI and height >= 2.0 * FIGURE_DPI


def test_discrepancy_page_figures_are_sharp(tmp_path: Path) -> None:
    data, report = tmp_path / "run.csv", tmp_path / "report.json"
    assert main(["simulate", "--scenario", "seed000", "--out", str(data)]) == 0
    assert main(["discrepancy", "--kind", "stage", "--input", str(data), "--out", str(report)]) == 0
    page = report.with_suffix(".html").read_text()
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(images) >= 2
    for encoded in images:
        width, _, dpi = _png_size_and_dpi(base64.b64decode(encoded))
        assert round(dpi) >= 150 and width >= 800, (width, dpi)
