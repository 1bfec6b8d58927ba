"""``sitl serve``: the lockstep world in real time on MAVLink/UDP (:mod:`~sitl.serve.server`).

:mod:`~sitl.serve.udp_link` puts one vehicle's message link on a UDP socket, as PX4 SITL's.
"""
