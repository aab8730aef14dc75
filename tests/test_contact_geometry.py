"""Contact geometry: the closed-form lowest rim point of a 3D disk against a plane vs dense sampling."""

from __future__ import annotations

import math

import torch

from diffcontact.systems import build_task

SAMPLES = 20000  # rim samples of the brute-force oracle: angle step 3e-4 rad, gap error <= R (step)²/2 ~ 1.5e-8


def test_gyroscope_rim_gap_is_the_minimum_over_the_rim():
    for planes in ([[0.0, 1.0, 0.0, 0.33]], [[0.6, 0.0, 0.8, 0.5]], [[-1.0, 1.0, 1.0, 0.4]]):
        task = build_task("Gyro", overrides={"walls": {"planes": planes}})
        x = task.sample(64, seed=2).x
        R = 0.3
        n = torch.tensor(planes[0][:3], dtype=torch.float64)
        c = planes[0][3] / n.norm()
        n = n / n.norm()
        com, e1, e2 = x[:, 0], x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
        a = torch.linspace(0, 2 * math.pi, SAMPLES + 1, dtype=torch.float64)[:-1]
        rim = com[:, None] + R * (a.cos()[None, :, None] * e1[:, None] + a.sin()[None, :, None] * e2[:, None])
        brute = (rim @ n + c).min(dim=1).values
        gap = task.system.detector.gaps(x)[:, 0]
        torch.testing.assert_close(gap, brute, atol=2e-8, rtol=0)
        assert (gap <= brute + 1e-12).all()  # the closed form is the exact minimum, never above a sample
