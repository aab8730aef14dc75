"""μ calibrated on whole tosses (``train/calibrate.py``): the line search against functions whose least point is known,
and on simulated Cube tosses, recorded and imported as the real ones are, the true μ found again from a wrong one."""

from __future__ import annotations

import pytest
import torch

from diffcontact import build_task
from diffcontact.data.measured import import_tosses
from diffcontact.data.tosses import save_contactnets_npz, simulated_tosses
from diffcontact.models.model import known_model
from diffcontact.train.calibrate import MAX_EVALUATIONS, STEP, calibrate_mu, line_search


@pytest.mark.parametrize("least", [1.0, 0.93, 1.061, 0.8])
@pytest.mark.parametrize("shape", ["parabola", "V"])
def test_line_search_ends_near_the_least_point(least, shape):
    """On a parabola the vertex step lands on the least point; on a V (the whole-toss error near the best μ is
    closer to one) within a quarter step of it; never more than MAX_EVALUATIONS evaluations, and the answer is the
    least value seen."""
    seen: list[float] = []

    def objective(s: float) -> float:
        seen.append(s)
        return (s - least) ** 2 if shape == "parabola" else abs(s - least)

    chosen, values = line_search(objective)
    assert len(seen) == len(values) <= MAX_EVALUATIONS
    assert values[chosen] == min(values.values())
    if abs(least - 1.0) <= 3 * STEP:  # (within the walk's reach: 0.8 is beyond, and the search stops on its way)
        assert abs(chosen - least) <= (1e-12 if shape == "parabola" else STEP / 4)
    else:
        assert chosen < 1.0 - 2 * STEP


def test_calibrate_mu_finds_the_true_mu_of_simulated_tosses(tmp_path):
    """16 Cube tosses simulated with μ 0.18 (the data's pose noise), imported as measured tosses; the true model with
    μ 6 % too high (0.1908) is calibrated on the 12 training tosses back to within 0.003 of 0.18, kept on the 2
    validation tosses, and the record says what was tried."""
    task = build_task("Cube")
    save_contactnets_npz(tmp_path / "tosses.npz", simulated_tosses(task, 16, seed=5, frames=60))
    folder = tmp_path / "data" / "Cube"
    import_tosses(tmp_path / "tosses.npz", folder, task="Cube", split=(0.75, 0.125, 0.125), window=8, stride=8)
    net = known_model(task)
    mu = net.params.known.mu
    with torch.no_grad():
        mu.mul_(1.06)
    record = calibrate_mu(net, mu, folder)
    assert record["kept"] and abs(float(mu[0]) - 0.18) <= 0.003, record
    assert record["mu"] == mu.tolist() and record["mu_trained"] == [pytest.approx(0.1908)]
    assert record["val_objective_after"] <= record["val_objective_before"]
    assert len(record["train_objective"]) <= MAX_EVALUATIONS and net.training and record["diverged_tosses"] == {}
