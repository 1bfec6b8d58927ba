"""The simulated vehicle's physical world and its sensors: what is true, and what a sensor makes of it.

:mod:`~sitl.physics.dynamics` flies one quad-X in JSBSim; :mod:`~sitl.physics.wind` blows on it;
:mod:`~sitl.physics.geo` maps local NED to WGS84; :mod:`~sitl.physics.gps` is the GPS receiver and
:mod:`~sitl.physics.heading_error` the heading estimate's error against the truth. Nothing here knows the
autopilot, the scenario or a socket.
"""
