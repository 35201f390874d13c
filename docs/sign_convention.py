"""Draw docs/sign-convention.png: the growth S, the offset A = -S and the machine's +Z.

.venv/bin/python docs/sign_convention.py        # rewrites docs/sign-convention.png
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import FancyArrowPatch, Rectangle

OUT = Path(__file__).with_name("sign-convention.png")


def arrow(ax, x0, y0, x1, y1, color, text, tx, ty, ha="left"):
    ax.add_patch(
        FancyArrowPatch((x0, y0), (x1, y1), arrowstyle="-|>", mutation_scale=16, lw=2, color=color)
    )
    ax.text(tx, ty, text, color=color, fontsize=10.5, ha=ha, va="center")


def spindle(ax, x, grown, lift, title, label=False):
    """A vertical spindle at x: housing, shaft, tool. grown: the shaft 1 unit longer (the tool
    tip lower); lift: the whole head taken up by this much (the compensation on Z)."""
    g = 1.0 if grown else 0.0
    ax.add_patch(Rectangle((x - 1.0, 6.0 + lift), 2.0, 3.2, fc="#cfd8dc", ec="#37474f", lw=1.2))
    ax.text(x, 8.6 + lift, "spindle", ha="center", fontsize=9, color="#37474f")
    ax.add_patch(
        Rectangle((x - 0.35, 4.0 - g + lift), 0.7, 2.0 + g, fc="#90a4ae", ec="#37474f", lw=1.2)
    )
    ax.add_patch(
        Rectangle((x - 0.15, 2.6 - g + lift), 0.3, 1.4, fc="#546e7a", ec="#263238", lw=1.2)
    )
    ax.add_patch(Rectangle((x - 2.0, 0.0), 4.0, 1.2, fc="#ffe0b2", ec="#6d4c41", lw=1.2))
    ax.text(x, 0.6, "workpiece", ha="center", va="center", fontsize=9, color="#6d4c41")
    ax.plot([x - 1.4, x + 1.4], [2.6, 2.6], ls="--", lw=1, color="#1565c0")
    if label:
        ax.text(x - 1.5, 2.6, "tip, cold", ha="right", va="center", fontsize=8.5, color="#1565c0")
    ax.text(x, 10.8, title, ha="center", fontsize=11, weight="bold")


def main() -> None:
    fig, ax = plt.subplots(figsize=(9.6, 5.2), dpi=110)
    ax.set_xlim(-4.5, 17.5)
    ax.set_ylim(-0.6, 11.4)
    ax.set_aspect("equal")
    ax.axis("off")

    # the machine's axis
    arrow(ax, -3.6, 3.0, -3.6, 6.5, "#263238", "+Z\n(away from\nthe work)", -3.4, 6.2)

    spindle(ax, 1.5, False, 0.0, "cold", label=True)
    spindle(ax, 7.0, True, 0.0, "warm: grown by S")
    arrow(
        ax, 7.5, 2.6, 7.5, 1.6, "#c62828", "S > 0: the tip\nmoved toward\nthe work (−Z)", 7.75, 3.7
    )

    spindle(ax, 12.5, True, 1.0, "compensated")
    # the compensation: the axis takes the head up by S, the tip back to the cold line
    arrow(ax, 14.0, 6.0, 14.0, 7.0, "#2e7d32", "", 14.2, 6.5)
    ax.text(
        14.3,
        5.8,
        "A = −S along the\ngrowth = +S on Z:\nthe axis takes the\nhead up by S",
        color="#2e7d32",
        fontsize=9.5,
        va="top",
        ha="left",
    )

    fig.text(
        0.5,
        0.02,
        "thermocomp's S is the growth, positive toward the workpiece; the offset "
        "it computes is A = −S. Each control family is written S or A in its own unit: "
        "see the table on this page.",
        ha="center",
        fontsize=9,
        wrap=True,
    )
    fig.savefig(OUT, bbox_inches="tight")
    print(OUT)


if __name__ == "__main__":
    main()
