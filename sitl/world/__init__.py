"""The lockstep world: vehicles, their autopilots, wind, the scenario and its scripted pilots. No sockets.

:class:`sitl.world.lockstep.World` steps everything in sim time; :mod:`~sitl.world.scenario` reads the
scenario files, :mod:`~sitl.world.trajectory` holds the leader's paths and :mod:`~sitl.world.pilot` flies
them; :mod:`~sitl.world.links` are the vehicles' message-level MAVLink links with the scenario's faults.
``sitl bench`` (:mod:`~sitl.world.bench`) measures the world's real-time factor.
"""
