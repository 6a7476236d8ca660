"""Printable tag bands (``gtsjax tags``): each robot's band at full size, to cut from tape or to lay
tape on.

The SVG is one strip per robot at 1:1 (print at 100 %): cell 0 at the left, going round the robot
counter-clockwise seen from above, each cell a rectangle (grey and marked ``TAPE`` where the code has
tape), dashed cut lines along the band's edges and between cells, and the robot's name, code and a
millimetre scale. Each cell's rectangle carries the id ``cell-<i>`` so that the geometry can be read
back (the tests do: the band reread from its own SVG gives its code). The PDF holds every robot's band
on A4 landscape pages at 1:1, cut into parts no longer than :data:`PART_MM` with their offsets printed,
to be joined end to end.
"""

from pathlib import Path

import numpy as np

MM_PER_INCH = 25.4
#: The longest part of a band on an A4 landscape page (297 mm wide, with margins), mm.
PART_MM = 260.0
TAPE_COLOUR = "#9a9a9a"
BODY_COLOUR = "#ffffff"
_MARGIN_MM = 12.0


def _draw(ax, code: np.ndarray, cell_mm: float, height_mm: float, x0_mm: float, x1_mm: float, y_mm: float,
          gid_prefix: str = "cell") -> None:
    """Cells of ``code`` that fall in ``[x0_mm, x1_mm]`` of the band, drawn from ``x = 0`` at ``y_mm``."""
    from matplotlib.patches import Rectangle

    for i, tape in enumerate(np.asarray(code, bool)):
        a, b = max(i * cell_mm, x0_mm), min((i + 1) * cell_mm, x1_mm)
        if b <= a:
            continue
        ax.add_patch(Rectangle((a - x0_mm, y_mm), b - a, height_mm, facecolor=TAPE_COLOUR if tape else BODY_COLOUR,
                               edgecolor="none", gid=f"{gid_prefix}-{i}"))
        ax.text((a + b) / 2 - x0_mm, y_mm + height_mm / 2, f"{i}\n{'TAPE' if tape else ''}", ha="center",
                va="center", fontsize=7, color="black")
    for i in range(len(code) + 1):  # cut lines between cells
        x = i * cell_mm
        if x0_mm <= x <= x1_mm:
            ax.plot([x - x0_mm] * 2, [y_mm, y_mm + height_mm], color="black", lw=0.4, ls=(0, (3, 2)))
    for y in (y_mm, y_mm + height_mm):  # cut lines along the band
        ax.plot([0, x1_mm - x0_mm], [y, y], color="black", lw=0.4, ls=(0, (3, 2)))


def _figure(width_mm: float, height_mm: float):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(width_mm / MM_PER_INCH, height_mm / MM_PER_INCH))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, width_mm)
    ax.set_ylim(0, height_mm)
    ax.set_axis_off()
    return fig, ax


def band_svg(path: Path, name: str, code: np.ndarray, perimeter_m: float, height_m: float) -> None:
    """One robot's band at 1:1 as an SVG (see the module)."""
    import matplotlib.pyplot as plt

    n = len(code)
    length, height = perimeter_m * 1000.0, height_m * 1000.0
    cell = length / n
    fig, ax = _figure(length + 2 * _MARGIN_MM, height + 3 * _MARGIN_MM)
    ax.set_xlim(-_MARGIN_MM, length + _MARGIN_MM)
    ax.set_ylim(-2 * _MARGIN_MM, height + _MARGIN_MM)
    _draw(ax, code, cell, height, 0.0, length, 0.0)
    code_str = "".join("1" if b else "0" for b in code)
    ax.text(0, height + 3, f"{name}  code {code_str}  ({n} cells of {cell:.1f} mm; cell 0 first, "
                           "counter-clockwise seen from above)", fontsize=7, va="bottom")
    for mm in range(0, int(length) + 1, 10):  # a millimetre scale to check the print is 1:1
        ax.plot([mm, mm], [-4, -4 - (3 if mm % 50 else 6)], color="black", lw=0.3)
        if mm % 100 == 0:
            ax.text(mm, -13, f"{mm} mm", fontsize=6, ha="center", va="top")
    fig.savefig(path, format="svg", metadata={"Date": None})
    plt.close(fig)


def bands_pdf(path: Path, names: list[str], codes: np.ndarray, perimeter_m: float, height_m: float) -> int:
    """Every robot's band on A4 landscape pages at 1:1, in parts of at most :data:`PART_MM`; returns the
    number of pages."""
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_pdf import PdfPages

    length, height = perimeter_m * 1000.0, height_m * 1000.0
    n_parts = int(np.ceil(length / PART_MM))
    part = length / n_parts
    row = height + 16.0
    page_w, page_h = 297.0, 210.0
    per_page = max(1, int((page_h - 2 * _MARGIN_MM) // row))
    rows = [(name, code, k) for name, code in zip(names, codes, strict=True) for k in range(n_parts)]
    pages = 0
    with PdfPages(path, metadata={"CreationDate": None}) as pdf:
        for start in range(0, len(rows), per_page):
            fig, ax = _figure(page_w, page_h)
            for j, (name, code, k) in enumerate(rows[start:start + per_page]):
                y = page_h - _MARGIN_MM - (j + 1) * row
                x0, x1 = k * part, (k + 1) * part
                ax.text(_MARGIN_MM, y + height + 2, f"{name}  part {k + 1}/{n_parts}: {x0:.0f}–{x1:.0f} mm of "
                        f"{length:.0f}  (code {''.join('1' if b else '0' for b in code)})", fontsize=7, va="bottom")
                sub = ax.inset_axes((_MARGIN_MM / page_w, y / page_h, part / page_w, height / page_h))
                sub.set_xlim(0, part)
                sub.set_ylim(0, height)
                sub.set_axis_off()
                _draw(sub, code, length / len(code), height, x0, x1, 0.0)
            pdf.savefig(fig)
            plt.close(fig)
            pages += 1
    return pages
