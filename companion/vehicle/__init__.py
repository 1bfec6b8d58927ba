"""The autopilot link: what the mission needs (``VehicleLink``), snapshot and setpoint types.

Only :mod:`companion.vehicle.mavsdk_link` imports mavsdk, and nothing here imports it: import that module
explicitly where the real link is built.
"""
