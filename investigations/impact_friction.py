"""The exact model with one friction coefficient for impacts and another for sustained contact (an experiment).

``investigations/toss_friction.py`` measures on the recorded tosses a flat-sliding deceleration of 0.20–0.23 g and
a first-impact impulse ratio of 0.155 at the median: one Coulomb μ cannot match both. This script scores the
nominal model of the task file on a split's whole tosses (as ``evaluate`` does) with μ replaced, for each contact,
by ``--mu-impact`` where the contact approaches faster than ``--speed`` (m/s) at the start of the compression
phase, and by ``--mu`` otherwise. It patches the contact solver's call for this run only; the package has no such
option.

    python investigations/impact_friction.py data/CubeToss --split val --mu 0.215 --mu-impact 0.16 --speed 0.3
    python investigations/impact_friction.py data/CubeToss --split val --mu 0.215 --mu-impact 0.175 --e 0 \
        --moments-scale 1.37 --com 0 0 0.007          # as the models that learn the centre of mass

The output holds each toss's position error (``per_toss_position_error``), so that two settings are compared toss by
toss: ``python investigations/com_offset.py --paired A.json B.json``, and the signed error along each toss's travel
(``travel_bias``, as ``investigations/travel_bias.py`` computes it from an evaluation).
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json

import torch
from travel_bias import travel_bias  # (this folder's script: run as python investigations/impact_friction.py)

from diffcontact.eval.pose_metrics import per_toss_position_error
from diffcontact.eval.tosses import predict_tosses, recorded_tosses, score_tosses
from diffcontact.models.model import known_model
from diffcontact.solver.contact_solver import ContactSolver
from diffcontact.systems.registry import build_task


def two_friction_coefficients(mu_impact: float, speed: float) -> None:
    """Patch ``ContactSolver.__call__``: the compression phase (no lower bound) picks μ per contact from the normal
    contact velocity it is given, and the restitution phase that follows uses the same μ."""
    call = ContactSolver.__call__
    chosen: dict[str, torch.Tensor] = {}

    def patched(self, A, q, mu, lower=None, active=None):
        if lower is None:
            normal = q[:, :: q.shape[1] // mu.shape[1]]
            chosen["mu"] = torch.where(normal < -speed, torch.full_like(mu, mu_impact), mu)
        return call(self, A, q, chosen["mu"], lower, active)

    ContactSolver.__call__ = patched


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="an imported dataset folder (diffcontact import contactnets)")
    parser.add_argument("--split", default="val")
    parser.add_argument("--task", default="CubeToss")
    parser.add_argument("--mu", type=float, required=True, help="μ of sustained contact")
    parser.add_argument("--mu-impact", type=float, required=True, help="μ of contacts approaching faster than --speed")
    parser.add_argument("--speed", type=float, default=0.3, help="m/s")
    parser.add_argument("--e", type=float, default=None, help="default: the task file's")
    parser.add_argument("--moments-scale", type=float, default=1.0, help="a multiple of the task file's moments")
    parser.add_argument("--com", type=float, nargs=3, default=None, help="the centre of mass (m, body frame)")
    args = parser.parse_args()
    torch.set_num_threads(1)

    moments = build_task(args.task).params.inertia.moments.flatten().tolist()
    overrides = {"contact": {"mu": [args.mu]}, "body": {"moments": [args.moments_scale * m for m in moments]}}
    if args.e is not None:
        overrides["contact"]["cor"] = [args.e]
    if args.com is not None:
        overrides["body"]["centre_of_mass"] = args.com
    net = known_model(build_task(args.task, overrides))
    two_friction_coefficients(args.mu_impact, args.speed)
    predicted = predict_tosses(net, args.data, args.split)
    metrics = score_tosses(predicted, args.data, args.split)
    tosses, request = recorded_tosses(args.data, args.split)
    half = request["half_extents_m"]
    per_toss = per_toss_position_error(predicted["position"], tosses.position, tosses.offsets, half)
    result = {
        "settings": vars(args),
        "metrics": metrics,
        "per_toss_position_error": per_toss.tolist(),
        "travel_bias": travel_bias(predicted, tosses, 2.0 * float(half[0])),
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
