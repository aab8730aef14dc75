"""Datasets: generation (ground-truth trajectories + chunks), verified storage, torch Datasets."""

from diffcontact.data.generate import generate_dataset
from diffcontact.data.store import SPLITS, Split, load_split, verify_dataset

__all__ = ["SPLITS", "Split", "generate_dataset", "load_split", "verify_dataset"]
