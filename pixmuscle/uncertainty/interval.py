"""The spread of F_max over the realisations: a 95 % prediction interval."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["prediction_interval", "INTERVAL_TEXT"]

#: how the interval is computed, in words (page, JSON)
INTERVAL_TEXT = ("95 % prediction interval of F_max for one more realisation: mean ± t(0.975, n−1) · s · √(1 + 1/n), "
                 "s the sample standard deviation of the n noisy realisations (normal theory); the spread of F_max, "
                 "not the standard error of its mean")


def prediction_interval(values, level: float = 0.95) -> dict:
    """Mean and prediction interval of a sample, assuming it is normal.

    The interval ``mean ± t_{(1+level)/2, n−1} · s · sqrt(1 + 1/n)`` contains one more draw from the
    same distribution with probability ``level``: the spread of the values, not the uncertainty of
    their mean (which would be ``t · s / sqrt(n)``). With n ≥ 40 the empirical 2.5–97.5 %
    percentiles would do as well; for the few realisations a run affords they do not exist.

    Parameters
    ----------
    values : (n,) array_like
        F_max of the realisations, N (NaN entries are dropped).
    level : float
        Coverage, 0..1.

    Returns
    -------
    dict
        ``n``, ``mean``, ``sd`` (sample, ddof 1), ``t``, ``low``, ``high``, ``min``, ``max``; ``sd``,
        ``t``, ``low`` and ``high`` are None when n < 2.
    """
    from scipy.stats import t as student_t

    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    n = int(v.size)
    out = {"n": n, "mean": float(v.mean()) if n else None, "sd": None, "t": None, "low": None, "high": None,
           "min": float(v.min()) if n else None, "max": float(v.max()) if n else None}
    if n >= 2:
        sd = float(v.std(ddof=1))
        t = float(student_t.ppf(0.5 + level / 2.0, n - 1))
        half = t * sd * math.sqrt(1.0 + 1.0 / n)
        out.update(sd=sd, t=t, low=out["mean"] - half, high=out["mean"] + half)
    return out
