"""Learnable models: the Simulator with learnable Params (CM/CMr × CLNN/CHNN), and the baselines."""

from diffcontact.models.baselines import BASELINE_NAMES
from diffcontact.models.model import MODEL_NAMES, ContactModelNet, build_model
from diffcontact.models.params import LearnedParams, MLPPotential

ALL_MODELS = (*MODEL_NAMES, *BASELINE_NAMES)  # every model build_model builds and diffcontact train trains

__all__ = [
    "ALL_MODELS",
    "BASELINE_NAMES",
    "MODEL_NAMES",
    "ContactModelNet",
    "LearnedParams",
    "MLPPotential",
    "build_model",
]
