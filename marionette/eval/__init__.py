"""Evaluation: the state-layer metrics of DESIGN "Evaluation definitions" (``metrics``) and Fréchet video distances
with bootstrap intervals (``fvd``)."""
