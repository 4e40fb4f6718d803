"""Pareto front of (model size, PSNR) points used by the sweep report's size plot."""

from __future__ import annotations

import random

from cusgs_jax.eval.sweep_plots import pareto_front


def _brute_front(points):
    def dominated(i):
        si, pi = points[i]
        return any(sj <= si and pj >= pi and (sj < si or pj > pi) for sj, pj in points)
    return sorted((i for i in range(len(points)) if not dominated(i)), key=lambda i: (points[i][0], -points[i][1], i))


def test_pareto_front_hand_case():
    points = [(100, 20.0), (50, 21.0), (200, 25.0), (300, 24.0), (200, 23.0), (50, 21.0), (400, 26.0)]
    assert pareto_front(points) == [1, 5, 2, 6]
    assert pareto_front([]) == []
    assert pareto_front([(1.0, 1.0)]) == [0]


def test_pareto_front_matches_brute_force():
    rng = random.Random(0)
    for trial in range(300):
        n = rng.randint(1, 25)
        if trial % 2:  # small integer grid: many ties
            points = [(rng.randint(1, 6), float(rng.randint(1, 6))) for _ in range(n)]
        else:
            points = [(rng.lognormvariate(12, 2), rng.uniform(15, 35)) for _ in range(n)]
        front = pareto_front(points)
        assert sorted(front) == sorted(_brute_front(points))
        assert [points[i][0] for i in front] == sorted(points[i][0] for i in front)
