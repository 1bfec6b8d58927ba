"""The PX4 backend: each vehicle is a real PX4 SITL process with SIH physics built in.

``sitl serve --autopilot px4`` flies the same scenarios as the project's own autopilot, against the
firmware users fly: :mod:`sitl.px4.instance` runs one PX4 per vehicle in a working folder of its own,
:mod:`sitl.px4.link` talks MAVLink to it on SIH's display link (ground truth, state, commands),
:mod:`sitl.px4.world` shares one world between them and flies the scenario (the leader's pilot, wind,
GPS loss), and :mod:`sitl.px4.serve` serves it with the same components as ``sitl serve``.
"""
