"""One assignment rule for pairing two sets within a gate (joint ids across updates, scoring),
and the Hungarian assignment it and the limbs' ends' matching share."""
from __future__ import annotations

import numpy as np


def min_cost_assignment(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (P,) int of the assignment of least total cost (R, C), P = min(R, C):
    scipy's linear_sum_assignment.

    scipy.optimize is imported on the first call, not with this module: it holds about 10 MB
    in every process that loads it, and two of the nodes' processes (the joint node, the
    registration node's camera stage) import the method's modules but never pair anything."""
    from scipy.optimize import linear_sum_assignment
    return linear_sum_assignment(cost)


def gated_assignment(cost: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (P,) int of the pairs within the gate (cost <= gate) of the assignment
    that pairs the most rows and columns within it, and among those the cheapest.

    cost: (R, C), any units (non-finite = never a pair). The bare Hungarian assignment
    minimises the total over every pair, so it can give up a pair within the gate to make
    one beyond it cheaper, and pairs beyond the gate are dropped anyway: they are all priced
    the same, above any total of pairs within it, so their costs choose nothing."""
    cost = np.asarray(cost, dtype=float)
    if cost.ndim != 2:
        raise ValueError(f'cost must be a 2-D array, got shape {cost.shape}')
    if cost.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    within = np.isfinite(cost) & (cost <= gate)
    beyond_price = (min(cost.shape) + 1) * max(float(gate), np.finfo(float).tiny)
    rows, cols = min_cost_assignment(np.where(within, cost, beyond_price))
    keep = within[rows, cols]
    return rows[keep], cols[keep]
