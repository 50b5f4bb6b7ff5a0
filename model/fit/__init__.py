"""Identification: fitting model parameters to runs (staged estimates, joint refinement, uncertainty)."""
