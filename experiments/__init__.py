"""Runnable entry points: ``python -m experiments.forest`` (city, indoor) and ``python -m experiments.bench NAME``."""
