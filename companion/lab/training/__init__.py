"""Training, fine-tuning, evaluating and exporting the leader detector.

The network itself lives in :mod:`companion.perception.detector`, which the service runs.
"""
