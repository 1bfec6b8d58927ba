"""The kernel shared by the flight service and the simulator: what both programs need, and nothing else.

Frames and rotations, clocks, the error tree, the config loader, the camera model and the camera wire format,
logging and where the shipped files are. It imports nothing else of ``companion`` (nor ``sitl``), and the
simulator imports nothing of ``companion`` but this (and the version). Importing it has no side effects.
"""
