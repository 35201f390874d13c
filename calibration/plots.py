"""PNG plots: speed, measured vs predicted, residual, with transient windows shaded."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from compensator.io import atomic_write

from .runs import transient_mask


@dataclass(frozen=True)
class Panel:
    """One column of a figure: a run, a replay or a demo."""

    title: str
    time_s: np.ndarray
    speed_rpm: np.ndarray
    predicted_um: np.ndarray | None = None
    measured_um: np.ndarray | None = None
    measured_label: str = "measured"
    predicted_label: str = "model (free run)"
    residual_label: str = "measured - model"
    extra: tuple[tuple[str, np.ndarray], ...] = ()  # more elongation-axis lines
    scored: np.ndarray | None = None
    """bool: the samples the residual is judged on (the tool cutting); the rest drawn grey and
    left out of the figures in the title. None: every sample."""


def _shade(ax, t_min: np.ndarray, mask: np.ndarray) -> None:
    if not mask.any():
        return
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1):
        ax.axvspan(t_min[a], t_min[b], color="tab:orange", alpha=0.12, lw=0)


def plot_panels(
    path: str | os.PathLike[str],
    panels: Sequence[Panel],
    suptitle: str,
    max_rpm: float | None = None,
) -> None:
    """Write one PNG (atomically) with three rows per panel column."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = len(panels)
    fig, axes = plt.subplots(
        3,
        cols,
        figsize=(6.5 * cols, 8.5),
        sharex="col",
        squeeze=False,
        gridspec_kw={"height_ratios": [1, 2, 1.3]},
    )
    for c, p in enumerate(panels):
        t_h = (p.time_s - p.time_s[0]) / 3600.0
        top = max_rpm or float(np.abs(p.speed_rpm).max()) or 1.0
        mask = transient_mask(p.time_s, p.speed_rpm, top)
        ax_n, ax_s, ax_r = axes[0, c], axes[1, c], axes[2, c]
        ax_n.step(t_h, p.speed_rpm, where="pre", color="tab:gray", lw=1)
        ax_n.set_ylabel("speed [rpm]")
        ax_n.set_title(p.title)
        # a journal's probe measurements are isolated points: a line would not show them
        dots = (
            {}
            if p.measured_um is None or np.isfinite(p.measured_um).all()
            else {"marker": ".", "ls": "none"}
        )
        if p.measured_um is not None:
            ax_s.plot(t_h, p.measured_um, color="tab:blue", lw=1, label=p.measured_label, **dots)
        if p.predicted_um is not None:
            ax_s.plot(t_h, p.predicted_um, color="tab:red", lw=1.2, label=p.predicted_label)
        for (label, y), color in zip(p.extra, ("tab:green", "tab:orange", "tab:brown", "tab:pink")):
            ax_s.plot(t_h, y, lw=1, color=color, label=label)  # never the measured line's blue
        ax_s.set_ylabel("elongation [um]")
        ax_s.legend(loc="best", fontsize=8)
        if p.measured_um is not None and p.predicted_um is not None:
            res = p.measured_um - p.predicted_um
            keep = np.ones(res.size, bool) if p.scored is None else np.asarray(p.scored, bool)
            if not keep.all():
                ax_r.plot(
                    t_h, res, color="0.75", lw=0.8, label="not scored (tool clear of the part)"
                )
                ax_r.legend(loc="lower left", fontsize=7)
            ax_r.plot(t_h, np.where(keep, res, np.nan), color="tab:purple", lw=1, **dots)
            ax_r.axhline(0, color="k", lw=0.5)
            judged = res[keep]
            rms = float(np.sqrt(np.mean(judged**2)))
            ax_r.set_title(
                f"{p.residual_label}: RMS {rms:.2f} um, max {np.abs(judged).max():.2f} um",
                fontsize=9,
            )
        ax_r.set_ylabel("residual [um]")
        ax_r.set_xlabel("time [h]")
        for ax in (ax_n, ax_s, ax_r):
            _shade(ax, t_h, mask)
            ax.grid(alpha=0.3)
    shaded = any(
        transient_mask(
            p.time_s, p.speed_rpm, max_rpm or float(np.abs(p.speed_rpm).max()) or 1.0
        ).any()
        for p in panels
    )
    fig.suptitle(suptitle + ("\n(shaded: transient windows)" if shaded else ""), fontsize=11)
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=90)
    plt.close(fig)
