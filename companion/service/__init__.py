"""The service's own machinery: mailboxes, supervision, health, the status endpoint, systemd, system readings.

Nothing here knows about flying; :mod:`companion.app` wires these around the perception and flight parts.
"""
