"""Diagnosis: what a Hammerstein model's simulation gets wrong, why, and the extended model
that accounts for it (``hammer-ros diagnose``, the node's ``~/diagnosis``)."""
