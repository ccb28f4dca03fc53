"""Friedman test and Nemenyi post-hoc across estimators, as the third source paper compared its filters.

The table is blocks × treatments: one row per trial (block), one column per estimator, the
entries the per-trial RMSEs (lower is better). Friedman's test asks whether the estimators'
ranks differ more than chance allows (H0: no difference); if it rejects, Nemenyi's test tells
which pairs differ — two estimators differ when their mean ranks are at least the critical
difference CD = q_α √(k(k+1)/(6N)) apart (Demšar 2006), the paper's eq. 63.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np


@dataclass
class RankTest:
    """Friedman result plus the Nemenyi pairwise p-values over the same table.

    ``columns`` the estimators kept, ``trials`` the blocks kept (rows with a missing value are
    dropped), ``mean_ranks`` rank 1 = lowest error. ``nemenyi[i][j]`` the p-value of columns
    i and j (1 on the diagonal). ``cd`` Nemenyi's critical difference of mean ranks at ``alpha``.
    ``statistic``/``pvalue`` are NaN and ``note`` says why when the test cannot be run.
    """

    columns: list[str]
    trials: list[str]
    statistic: float = math.nan
    pvalue: float = math.nan
    mean_ranks: list[float] = field(default_factory=list)
    nemenyi: list[list[float]] = field(default_factory=list)
    cd: float = math.nan
    alpha: float = 0.05
    note: str = ""

    @property
    def significant(self) -> bool:
        return bool(self.pvalue < self.alpha)

    def as_dict(self) -> dict:
        return {
            "columns": self.columns,
            "trials": self.trials,
            "friedman_chi2": _finite_or_none(self.statistic),
            "friedman_p": _finite_or_none(self.pvalue),
            "mean_ranks": dict(zip(self.columns, self.mean_ranks)),
            "nemenyi_p": {a: dict(zip(self.columns, row)) for a, row in zip(self.columns, self.nemenyi)},
            "critical_difference": _finite_or_none(self.cd),
            "alpha": self.alpha,
            "note": self.note,
        }


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def rank_test(table: Mapping[str, Sequence[float | None]], trials: Sequence[str], alpha: float = 0.05) -> RankTest:
    """Friedman + Nemenyi over ``table`` (estimator → per-trial values, in ``trials`` order)."""
    columns = list(table)
    data = np.array([[np.nan if v is None else float(v) for v in table[c]] for c in columns], dtype=float).T
    if data.size and data.shape[0] != len(trials):
        raise ValueError(f"each column needs {len(trials)} values (one per trial), got {data.shape[0]}")
    keep = ~np.isnan(data).any(axis=1) if data.size else np.zeros(len(trials), bool)
    data = data[keep] if data.size else data
    kept = [t for t, k in zip(trials, keep) if k]
    result = RankTest(columns=columns, trials=kept, alpha=alpha)
    k, n = len(columns), len(kept)
    if k < 3:
        result.note = f"Friedman's test needs at least 3 estimators, got {k}"
        return result
    if n < 2:
        result.note = f"Friedman's test needs at least 2 complete trials, got {n}"
        return result

    from scipy.stats import friedmanchisquare, rankdata, studentized_range

    ranks = rankdata(data, axis=1)
    result.mean_ranks = [float(r) for r in ranks.mean(axis=0)]
    if np.ptp(data, axis=1).max() == 0.0:
        result.note = "all estimators score identically on every trial"
        return result
    stat, p = friedmanchisquare(*data.T)
    result.statistic, result.pvalue = float(stat), float(p)

    import scikit_posthocs as sp

    nem = sp.posthoc_nemenyi_friedman(data)
    result.nemenyi = [[float(v) for v in row] for row in np.asarray(nem, dtype=float)]
    # q_α of the Studentised range for k groups and infinite degrees of freedom, over √2
    q_alpha = float(studentized_range.ppf(1.0 - alpha, k, np.inf)) / math.sqrt(2.0)
    result.cd = q_alpha * math.sqrt(k * (k + 1) / (6.0 * n))
    return result


def friedman_markdown(test: RankTest, title: str) -> str:
    """The Friedman result and mean ranks as a Markdown section."""
    lines = [f"#### Friedman: {title}", ""]
    if test.note and not np.isfinite(test.statistic):
        return "\n".join(lines + [f"Not computed: {test.note}.", ""])
    verdict = "differences are significant" if test.significant else "no significant difference"
    lines += [
        f"χ²_F = {test.statistic:.2f}, p = {test.pvalue:.3g} over {len(test.trials)} trials and "
        f"{len(test.columns)} estimators ({verdict} at α = {test.alpha}); Nemenyi critical "
        f"difference of mean ranks CD = {test.cd:.2f}.",
        "",
        "| estimator | mean rank |",
        "|---|---:|",
    ]
    order = np.argsort(test.mean_ranks)
    lines += [f"| {test.columns[i]} | {test.mean_ranks[i]:.2f} |" for i in order]
    return "\n".join(lines + [""])


def nemenyi_markdown(test: RankTest, title: str) -> str:
    """Nemenyi pairwise p-values as a Markdown matrix; p < α in bold."""
    if not test.nemenyi:
        return ""
    cols = test.columns
    lines = [f"#### Nemenyi p-values: {title}", "", "| | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
    for name, row in zip(cols, test.nemenyi):
        cells = []
        for j, p in enumerate(row):
            if cols[j] == name:
                cells.append("–")
            else:
                cells.append(f"**{p:.3f}**" if p < test.alpha else f"{p:.3f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines + [""])
