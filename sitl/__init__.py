"""Wingman SITL: a JSBSim-backed simulator that speaks MAVLink as PX4 SITL does. No import side effects."""
