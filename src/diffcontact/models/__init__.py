"""Learnable models: the Simulator with learnable Params (CM/CMr × CLNN/CHNN)."""

from diffcontact.models.model import MODEL_NAMES, ContactModelNet, build_model
from diffcontact.models.params import LearnedParams, MLPPotential

__all__ = ["MODEL_NAMES", "ContactModelNet", "LearnedParams", "MLPPotential", "build_model"]
