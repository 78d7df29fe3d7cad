"""Foundation layer: geometry, measurement and noise models, errors, atomic files, progress, topic names,
BLAS thread control.

Imports nothing else of the project (tests/test_layers.py checks it); every other layer builds on it.
"""
