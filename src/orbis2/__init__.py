"""Orbis 2: a hierarchical world model for driving — training and evaluation pipeline."""

__version__ = "0.1.0"
