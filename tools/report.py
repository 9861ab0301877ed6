"""Reporting helpers shared by the benchmarks and the ablation: number formatting, CSV
files, text tables and matplotlib figures (headless)."""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: figures are only ever saved to files
import matplotlib.pyplot as plt  # noqa: E402

from engine.io.fileio import atomic_write  # noqa: E402

__all__ = ["fmt", "plt", "save_figure", "text_table", "write_csv"]


def fmt(x, nd: int = 2) -> str:
    """``x`` with ``nd`` decimals; "-" for None, NaN and inf."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.{nd}f}" if isinstance(x, float) else str(x)


def write_csv(rows: list[dict], path, fields, *, digits: int | None = None) -> Path:
    """``rows`` as CSV with columns ``fields`` (missing values empty, floats rounded to
    ``digits`` when given), written atomically."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(fields), extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else
                        round(r[k], digits) if digits is not None and isinstance(r[k], float) else r[k])
                    for k in fields})
    path = Path(path)
    atomic_write(path, lambda fh: fh.write(buf.getvalue().encode("utf-8")))
    return path


def text_table(head: list[str], lines: list[list]) -> str:
    """Columns aligned with spaces: the first left-aligned, the others right-aligned."""
    widths = [max(len(str(x)) for x in col) for col in zip(head, *lines)]

    def row(vals):
        return "  ".join(str(v).rjust(w) if i else str(v).ljust(w) for i, (v, w) in enumerate(zip(vals, widths)))

    return "\n".join([row(head), row(["-" * w for w in widths])] + [row(line) for line in lines])


def save_figure(fig, path, title: str = "") -> Path:
    """Title, tight layout, save as PNG (110 dpi) and close ``fig``."""
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
