"""Measurement: SSD matching in the validation gate and R_k from the correlation surface (§5.2).

Imports nothing: a run imports the stages it uses and no other (``registry.py``).
"""
