"""Synthetic footage and marker data with exact ground truth, so every stage is measured."""
