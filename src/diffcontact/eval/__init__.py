"""Evaluation: the published metrics on test rollouts, figures, GIFs, and the reproduction report."""
