"""Evaluation of closed-loop flights: the flight log, the paper's metrics, reports and plots.

The metrics are computed from a :class:`~companion.lab.evaluation.log.FlightLog` recorded by the simulation
harness; truth comes from the simulator and is used only here, never by the service's estimate.
"""
