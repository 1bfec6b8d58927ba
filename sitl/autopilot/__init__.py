"""The simulator's own PX4-like autopilot, transport-free: :class:`sitl.autopilot.autopilot.Autopilot`.

Its layers: :mod:`~sitl.autopilot.state` (parameters, estimate, health, outgoing MAVLink),
:mod:`~sitl.autopilot.flight` (commander, land detector, control) and :mod:`~sitl.autopilot.mavlink`
(incoming messages and commands). PX4's pure parts beside them: :mod:`~sitl.autopilot.commander`,
:mod:`~sitl.autopilot.navigator`, :mod:`~sitl.autopilot.control`, :mod:`~sitl.autopilot.inner_loop`,
:mod:`~sitl.autopilot.attitude`, :mod:`~sitl.autopilot.estimator`, :mod:`~sitl.autopilot.offboard`,
:mod:`~sitl.autopilot.params`, :mod:`~sitl.autopilot.modes`, :mod:`~sitl.autopilot.telemetry` and
:mod:`~sitl.autopilot.signing`. It flies :mod:`sitl.physics`; it knows no scenario and no socket.
"""
