"""PASS / FAIL against a maximum permissible error, with the test's own uncertainty, by
the decision rules of ISO 14253-1 (guard bands of the expanded uncertainty U)."""

from __future__ import annotations

import numpy as np

__all__ = ["DECISION_RULE", "PASS", "FAIL", "UNDECIDED", "decide", "combine"]

PASS = "PASS"
FAIL = "FAIL"
UNDECIDED = "UNDECIDED"

#: The rule, in words (written into result.json).
DECISION_RULE = (
    "ISO 14253-1 guard bands of width U (expanded uncertainty of the test, k = 2): PASS when "
    "conformity is proven (|E| + U <= MPE), FAIL when non-conformity is proven "
    "(|E| - U > MPE), UNDECIDED otherwise (the value lies within U of the MPE). A "
    "characteristic passes when every position passes and fails when any position fails.")


def decide(value: float, U: float, mpe: float) -> str:
    """The decision for one value ``value`` (mm, signed or not) with expanded uncertainty
    ``U`` (mm, >= 0) against ``mpe`` (mm, > 0): PASS, FAIL or UNDECIDED
    (:data:`DECISION_RULE`).

    >>> decide(0.004, 0.001, 0.006), decide(-0.0055, 0.001, 0.006), decide(0.008, 0.001, 0.006)
    ('PASS', 'UNDECIDED', 'FAIL')
    """
    if not (np.isfinite(mpe) and mpe > 0):
        raise ValueError(f"the MPE must be > 0, got {mpe}")
    if not (np.isfinite(U) and U >= 0):
        raise ValueError(f"U must be >= 0, got {U}")
    e = abs(float(value))
    if e + U <= mpe:
        return PASS
    if e - U > mpe:
        return FAIL
    return UNDECIDED


def combine(decisions) -> str:
    """One decision for several positions: FAIL if any fails, PASS if all pass, else
    UNDECIDED.

    >>> combine(["PASS", "UNDECIDED"]), combine(["PASS", "FAIL", "UNDECIDED"])
    ('UNDECIDED', 'FAIL')
    """
    d = list(decisions)
    if FAIL in d:
        return FAIL
    if d and all(x == PASS for x in d):
        return PASS
    return UNDECIDED
