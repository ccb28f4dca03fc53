"""PNG plots of an evaluation (matplotlib, Agg backend): error over time and per-group bars.

Every figure carries the citation of its data set (BROAD or DIDO) in its footer.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from ahrs_service.evaluation.broad import CITATION

_MAX_POINTS = 4000  # per line; more only slows drawing and bloats the PNG


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text)


def _footer(fig, citation: str = CITATION) -> None:
    fig.text(0.01, 0.005, "Data: " + citation, fontsize=6, ha="left", va="bottom", wrap=True, color="0.3")


def error_over_time(
    trial: Any, errors: dict[str, dict[str, np.ndarray]], columns: list[Any], out_dir: Path, citation: str = CITATION
) -> str:
    """One figure per trial: inclination error of every column, heading error of those with heading.

    ``errors``: column → {"heading", "inclination", ...} → (N,) degrees. Samples outside
    ``movement`` are greyed out. Returns the file name (relative to ``out_dir``).
    """
    plt = _pyplot()
    n = len(trial)
    t = np.arange(n) / trial.rate_hz
    step = max(1, n // _MAX_POINTS)
    fig, axes = plt.subplots(2, 1, figsize=(11, 6.5), sharex=True)
    for col in columns:
        e = errors.get(col.name)
        if e is None:
            continue
        axes[0].plot(t[::step], e["inclination"][::step], lw=0.8, label=col.name)
        if col.scores_heading:
            axes[1].plot(t[::step], e["heading"][::step], lw=0.8, label=col.name)
    still = ~np.asarray(trial.movement, bool)
    for ax in axes:
        ax.fill_between(t, 0, 1, where=still, color="0.9", transform=ax.get_xaxis_transform(), step="mid", lw=0)
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("inclination error (°)")
    axes[1].set_ylabel("heading error (°)")
    axes[1].set_xlabel("time (s)   — grey: not scored (outside movement)")
    axes[0].set_title(f"{trial.name}: error over time")
    axes[0].legend(fontsize=7, ncol=4, loc="upper right")
    if axes[1].lines:
        axes[1].legend(fontsize=7, ncol=4, loc="upper right")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    _footer(fig, citation)
    name = f"error_{_slug(trial.name)}.png"
    fig.savefig(out_dir / name, dpi=100)
    plt.close(fig)
    return name


def group_bars(results: dict, out_dir: Path) -> list[str]:
    """One bar chart per group: total, heading and inclination RMSE of each column (n/a left out)."""
    plt = _pyplot()
    cols = [c["name"] for c in results["columns"]]
    kinds = ("total", "heading", "inclination")
    files = []
    for gname, members in results["groups"].items():
        fig, ax = plt.subplots(figsize=(max(6.0, 0.8 * len(cols) + 2), 4.5))
        x = np.arange(len(cols))
        width = 0.27
        for i, kind in enumerate(kinds):
            vals = [results["per_group"][c][gname][kind] for c in cols]
            vals = [np.nan if v is None else v for v in vals]
            ax.bar(x + (i - 1) * width, vals, width, label=f"{kind} RMSE")
        ax.set_xticks(x, cols, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel("RMSE (°)")
        ax.set_title(f"group {gname}: mean of {len(members)} trial RMSE(s)")
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout(rect=(0, 0.05, 1, 1))
        _footer(fig, results.get("citation", CITATION))
        name = f"group_{_slug(gname)}.png"
        fig.savefig(out_dir / name, dpi=100)
        plt.close(fig)
        files.append(name)
    return files
