"""Training: Lightning data module (and, later, the Lightning module, callbacks)."""
