"""Robust parametric motion estimation (paper §5.1).

Imports nothing: a run imports the stages it uses and no other (``registry.py``).
"""
