"""The threshold between good and bad scores, set from good images' held-out scores.

A training image's own score says little (a model remembers what it saw), so each good image is
scored as if held out (:mod:`.patches`, :mod:`.variation`). The threshold is the larger of two
estimates of the score that a share ``false_reject`` of good parts exceeds: the held-out scores'
empirical quantile, and the upper prediction bound of a log-normal fitted to them (scores are
positive and skewed to the right): mean + t * spread * sqrt(1 + 1/n) of the logarithms, with
Student's t for n - 1 degrees of freedom, because the mean and spread are themselves estimated
from n scores. With few images the bound reaches past the highest score seen, as it should:
10 scores cannot show a 1 % tail (docs/BENCHMARKS.md, section 19, compares the observed
false-reject rates with the target).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from statistics import NormalDist

import numpy as np

FLOOR = 1e-6


def set_threshold(held_out: Sequence[float], false_reject: float) -> float:
    """The score above which a part fails, for a target false-reject rate in (0, 0.5)."""
    scores = np.maximum(np.asarray(held_out, np.float64), FLOOR)
    empirical = float(np.quantile(scores, 1.0 - false_reject))
    logs = np.log(scores)
    spread = float(logs.std(ddof=1)) if scores.size > 1 else 0.0
    count = int(scores.size)
    quantile = student_t_quantile(1.0 - false_reject, max(count - 1, 1))
    bound = float(logs.mean()) + quantile * spread * math.sqrt(1.0 + 1.0 / count)
    return max(empirical, math.exp(bound))


def student_t_quantile(p: float, dof: int) -> float:
    """Student's t quantile for ``dof`` degrees of freedom (Cornish-Fisher expansion around the
    normal quantile): within 1 % of the exact value for dof >= 4 at p <= 0.999 (training has
    at least 8 images: dof >= 7)."""
    z = NormalDist().inv_cdf(p)
    v = float(dof)
    return (
        z
        + (z**3 + z) / (4 * v)
        + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * v**2)
        + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * v**3)
    )


__all__ = ["set_threshold"]
