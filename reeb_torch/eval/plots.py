"""Table 3's two plots, with matplotlib (the ``extras``; imported only when plotting).

- ``recall_vs_proposals_iou0.7.png``: recall at IoU 0.7 against the number of proposals;
- ``recall_vs_iou_k2000.png``: recall of the top 2000 against the IoU threshold.

One line per method; rows without regions dashed, rows ranked by a model fitted on the
frames measured (in sample, no estimate) dotted and said so in the legend.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

__all__ = ["plot_curves"]


def _style(label: str, in_sample: bool = False) -> str:
    return ":" if in_sample else "--" if "no regions" in label else "-"


def plot_curves(curves: dict[str, dict], out: str | os.PathLike, in_sample: Sequence[str] = ()) -> list[str]:
    """Draw the two recall plots into the folder ``out``, a line per method (``curves`` by
    label: ``ks``, ``recall_vs_k``, ``ious``, ``recall_vs_iou``, as
    :attr:`reeb_torch.eval.table3.Table3.curves`); the methods labelled ``in_sample`` (ranked
    by a model fitted on these frames) dotted, and said so. Returns the files' names; none,
    with a note, without matplotlib."""
    try:
        import matplotlib
    except ImportError:
        print("plots skipped: matplotlib is not installed (pip install 'reeb-torch[extras]')", flush=True)
        return []
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    files: list[str] = []

    def line_plot(x: str, y: str, xlabel: str, ylabel: str, title: str, name: str, log: bool) -> None:
        fig, ax = plt.subplots(figsize=(6.4, 4.4))
        for label, c in curves.items():
            seen = label in in_sample
            ax.plot(c[x], [100 * r for r in c[y]], label=label + (" - in sample, no estimate" if seen else ""),
                    ls=_style(label, seen))
        if log:
            ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_ylim(0, 100)
        ax.grid(True, which="both" if log else "major", alpha=0.3)
        ax.legend(fontsize=8)
        ax.set_title(title)
        fig.tight_layout()
        fig.savefig(out / name, dpi=120)
        plt.close(fig)
        files.append(name)

    line_plot("ks", "recall_vs_k", "number of proposals", "recall at IoU 0.7 (%)",
              "Recall vs number of proposals (KITTI, IoU 0.7)", "recall_vs_proposals_iou0.7.png", log=True)
    line_plot("ious", "recall_vs_iou", "IoU threshold", "recall of the top 2000 (%)",
              "Recall vs IoU (KITTI, 2000 proposals)", "recall_vs_iou_k2000.png", log=False)
    return files
